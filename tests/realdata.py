"""Fixtures for the real-data tests, built by the tests themselves (no download).

Meshes are written the hard way, as public asset sets ship them:

* ``table``: a **multi-body** mesh — a closed top board (1.0 × 0.08 × 0.6 m, top at y = 0.75) and four
  legs that are **open shells** (boxes without their bottom face) pushed 2 cm into the board (their tops
  are buried in it), in an **off-centre local frame** (the file's origin is 0.3 m from the bbox centre);
* ``mug``: an **open-topped** single-layer cylinder (r 4 cm, h 10 cm) with its winding **inverted**;
* ``cube``: a 0.2 m cube whose vertices are **split at UV seams** (24 vertices, each face its own), off-centre.

Scenes with known answers (the table supports the mug and the cube; spatial codes from the poses):
``rest`` (mug and cube resting on the table: Col_mesh 0, ASD 0), ``sunk`` (the mug 3 cm into the top:
mug and table collide, the mug's support distance is 3 cm), ``float`` (the mug 4 cm above: no collision,
support distance 4 cm), ``turned`` (``rest`` with the whole room turned 37° about y: the same answers).

:func:`release_layout` writes the SPREAD release's layout, :func:`threed_front_layout` InstructScene's
3D-FRONT layout (with 3D-FUTURE-style ``raw_model.obj`` files), :func:`add_bad_rooms` the bad inputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

TABLE = (1.0, 0.75, 0.6)  # extents, metres
BOARD = 0.08
MUG_R, MUG_H = 0.04, 0.10
CUBE = 0.2
TABLE_OFFSET = np.array([0.3, 0.0, -0.2])  # the file's origin is off the bbox centre
CUBE_OFFSET = np.array([0.5, 0.1, 0.5])
TURN = np.deg2rad(37.0)
MUG_X, CUBE_X = -0.25, 0.25
SINK, LIFT = 0.03, 0.04


def box_shell(extents, centre=(0, 0, 0), drop_normal=None):
    """A box (trimesh); ``drop_normal`` removes the faces facing that way (an open shell)."""
    import trimesh

    box = trimesh.creation.box(extents=np.asarray(extents, float))
    if drop_normal is not None:
        keep = ~np.all(np.isclose(box.face_normals, drop_normal), axis=1)
        box = trimesh.Trimesh(box.vertices, box.faces[keep], process=False)
        box.remove_unreferenced_vertices()
    return box.apply_translation(np.asarray(centre, float))


def table_bodies():
    """(name, mesh) bodies of the table in its bbox-centred frame (y from −0.375 to 0.375)."""
    w, h, d = TABLE
    bodies = [("board", box_shell((w, BOARD, d), (0, h / 2 - BOARD / 2, 0)))]
    leg_h = h - BOARD + 0.02  # 2 cm into the board
    for k, (x, z) in enumerate([(-0.45, -0.25), (0.45, -0.25), (-0.45, 0.25), (0.45, 0.25)]):
        bodies.append((f"leg{k}", box_shell((0.05, leg_h, 0.05), (x, -h / 2 + leg_h / 2, z), drop_normal=(0, -1, 0))))
    return bodies


def open_mug():
    """The open-topped, single-layer mug, bbox-centred, with inverted winding."""
    import trimesh

    cyl = trimesh.creation.cylinder(radius=MUG_R, height=MUG_H, sections=48)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # axis z → y
    keep = ~(cyl.face_normals[:, 1] > 0.9)  # no top cap
    mug = trimesh.Trimesh(cyl.vertices, cyl.faces[keep][:, ::-1], process=False)
    mug.remove_unreferenced_vertices()
    return mug


def write_table_glb(path: Path) -> Path:
    """The table as a glTF scene: one node per body, each with its own translation (the off-centre frame)."""
    import trimesh

    scene = trimesh.Scene()
    for name, body in table_bodies():
        centre = body.bounds.mean(0)
        local = body.copy().apply_translation(-centre)  # each body centred in its own node
        scene.add_geometry(local, node_name=name, geom_name=name,
                           transform=trimesh.transformations.translation_matrix(centre + TABLE_OFFSET))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(scene.export(file_type="glb"))
    return path


def write_table_obj(path: Path, scale: float = 1.0) -> Path:
    """The table as one OBJ with one ``o`` group per body, scaled by ``scale`` (3D-FUTURE-style raw model)."""
    lines, base = [], 1
    for name, body in table_bodies():
        lines.append(f"o {name}")
        lines += ["v %.9f %.9f %.9f" % tuple(v) for v in (body.vertices + TABLE_OFFSET) * scale]
        lines += ["f %d %d %d" % tuple(f + base) for f in body.faces]
        base += len(body.vertices)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def write_uv_split_obj(path: Path, mesh, offset=(0, 0, 0), scale: float = 1.0) -> Path:
    """``mesh`` as an OBJ whose every triangle has its own three vertices and texture coordinates."""
    tri = (np.asarray(mesh.triangles) + np.asarray(offset, float)) * scale
    lines = ["v %.9f %.9f %.9f" % tuple(v) for v in tri.reshape(-1, 3)]
    lines += ["vt %.3f %.3f" % ((k % 3) / 2.0, (k // 3) % 2) for k in range(len(tri) * 3)]
    lines += ["f " + " ".join(f"{3 * i + c + 1}/{3 * i + c + 1}" for c in range(3)) for i in range(len(tri))]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def write_mug_ply(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(open_mug().export(file_type="ply"))
    return path


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def room_poses(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """World bbox centres (3, 3) and rotations (3, 3, 3) of table, mug, cube in scene ``kind``."""
    top = TABLE[1]
    mug_y = top + MUG_H / 2 + {"rest": 0.0, "turned": 0.0, "sunk": -SINK, "float": LIFT}[kind]
    T = np.array([[0.0, TABLE[1] / 2, 0.0], [MUG_X, mug_y, 0.05], [CUBE_X, top + CUBE / 2, -0.05]])
    R = np.tile(np.eye(3), (3, 1, 1))
    if kind == "turned":
        Ry = rot_y(TURN)
        T, R = T @ Ry.T, np.einsum("ij,njk->nik", Ry, R)
    return T, R


def spatial_of(T, R):
    """Spatial codes of the three objects from their exact boxes (what a source file would carry)."""
    from spread.relations import spatial_codes

    ext = np.array([TABLE, (2 * MUG_R, MUG_H, 2 * MUG_R), (CUBE, CUBE, CUBE)])
    corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
    lo, hi = [], []
    for t, r, e in zip(T, R, ext):
        w = (corners * e) @ r.T + t
        lo.append(w.min(0))
        hi.append(w.max(0))
    return spatial_codes(np.array(lo), np.array(hi))


KINDS = ("rest", "sunk", "float", "turned")
RELEASE_NAMES = ["Table_1", "Mug_3", "Cube_7"]


def release_boxes(kind: str, names=RELEASE_NAMES) -> dict:
    """The arrays of one release ``boxes.npz`` (index 0 the placeholder)."""
    T, R = room_poses(kind)
    n1 = 4
    Tb = np.zeros((n1, 3))
    Rb = np.tile(np.eye(3), (n1, 1, 1))
    Tb[1:], Rb[1:] = T, R
    centres = np.zeros((n1, 3))
    centres[1] = TABLE_OFFSET
    centres[2] = 0.0
    centres[3] = CUBE_OFFSET
    regions = np.full((n1, n1), 0, np.int64)
    regions[1:, 1:] = spatial_of(T, R)
    np.fill_diagonal(regions, 6)
    return {"T_bbox": Tb, "R_bbox": Rb, "bbox_center": centres,
            "obj_names": np.array(["root"] + list(names)),
            "relations": np.array([[1, 1, 2], [1, 1, 3], [0, 1, 1]], np.int64),
            "regions_bbox": regions, "size": np.ones((n1, 3))}


def release_layout(root: Path, split=None) -> Path:
    """A release-layout folder ``root`` with the four known-answer rooms (tags ``ProcTHOR-Test-<k>-room|<kind>``)."""
    import trimesh

    root.mkdir(parents=True, exist_ok=True)
    write_table_glb(root / "meshes" / "Table_1_unpacked.glb")
    mug_scene = trimesh.Scene()
    mug_scene.add_geometry(open_mug(), node_name="mug")
    (root / "meshes" / "Mug_3_unpacked.glb").write_bytes(mug_scene.export(file_type="glb"))
    write_uv_split_obj(root / "cube_src.obj", trimesh.creation.box(extents=(CUBE,) * 3), offset=CUBE_OFFSET)
    cube_scene = trimesh.load(root / "cube_src.obj", force="scene", process=False)
    (root / "meshes" / "Cube_7_unpacked.glb").write_bytes(cube_scene.export(file_type="glb"))
    (root / "cube_src.obj").unlink()
    tags = {}
    for k, kind in enumerate(KINDS):
        tag = f"ProcTHOR-Test-{k}-room|{kind}"
        tags[kind] = tag
        (root / tag).mkdir(exist_ok=True)
        np.savez(root / tag / "boxes.npz", **release_boxes(kind))
    split = split or {"train": [tags["rest"], tags["sunk"]], "val": [tags["float"], tags["turned"]]}
    (root / "train_test_split.json").write_text(json.dumps(split))
    (root / "dataset_stats.txt").write_text(json.dumps({
        "bounds_translations": [-2.0, 0.0, -2.0, 2.0, 1.5, 2.0], "bounds_sizes": [0, 0, 0, 1, 1, 1],
        "bounds_angles": []}))
    return root


def add_bad_rooms(root: Path, outside: Path) -> dict:
    """Bad inputs added to a release folder; returns {case: tag}. ``outside`` is a folder beside ``root``
    holding a valid room that only a hostile tag (``../<outside>``) could reach."""
    good = release_boxes("rest")
    cases = {}

    def room(tag, arrays=None):
        (root / tag).mkdir(exist_ok=True)
        if arrays is not None:
            np.savez(root / tag / "boxes.npz", **arrays)
        cases[tag.split("-")[0]] = tag
        return tag

    room("nobox-room")  # a listed tag whose folder has no boxes.npz
    room("nomesh-room", {**good, "obj_names": np.array(["root", "Table_1", "Ghost_9", "Cube_7"])})
    room("shapes-room", {**good, "R_bbox": good["R_bbox"][1:]})
    nan = good["T_bbox"].copy()
    nan[2, 1] = np.nan
    room("nan-room", {**good, "T_bbox": nan})
    (root / "pickle-room").mkdir(exist_ok=True)
    np.savez(root / "pickle-room" / "boxes.npz", **{**good, "obj_names": np.array(["root", "Table_1", "Mug_3", "Cube_7"],
                                                                                      dtype=object)})
    cases["pickle"] = "pickle-room"
    outside.mkdir(parents=True, exist_ok=True)
    np.savez(outside / "boxes.npz", **good)
    cases["hostile"] = f"../{outside.name}"
    split = json.loads((root / "train_test_split.json").read_text())
    split["train"] = split["train"] + [t for t in cases.values()]
    (root / "train_test_split.json").write_text(json.dumps(split))
    return cases


# ---- InstructScene's 3D-FRONT layout -------------------------------------------------------------

FRONT_CLASSES = ["desk", "mug", "box", "start", "end"]
JIDS = ["0a1b2c3d-table", "4e5f6a7b-mug", "8c9d0e1f-cube"]
FLOOR_CENTROID = np.array([3.0, 0.0, -2.0])


def threed_front_layout(root: Path, models: Path) -> tuple[Path, Path]:
    """(src folder, splits CSV): rooms ``<house>_<RoomId>`` for the four kinds, 3D-FUTURE-style models in
    ``models/<jid>/raw_model.obj`` (the table at half scale, the cube UV-split), and ``dataset_stats.txt``."""
    import trimesh

    root.mkdir(parents=True, exist_ok=True)
    write_table_obj(models / JIDS[0] / "raw_model.obj", scale=0.5)
    mug_lines, mug = [], open_mug()
    mug_lines += ["v %.9f %.9f %.9f" % tuple(v) for v in mug.vertices]
    mug_lines += ["f %d %d %d" % tuple(f + 1) for f in mug.faces]
    (models / JIDS[1]).mkdir(parents=True, exist_ok=True)
    (models / JIDS[1] / "raw_model.obj").write_text("\n".join(mug_lines) + "\n")
    write_uv_split_obj(models / JIDS[2] / "raw_model.obj", trimesh.creation.box(extents=(CUBE,) * 3), offset=CUBE_OFFSET)
    sizes = np.array([TABLE, (2 * MUG_R, MUG_H, 2 * MUG_R), (CUBE,) * 3]) / 2
    one_hot = np.eye(len(FRONT_CLASSES))[[0, 1, 2]]
    floor = np.array([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], float) + FLOOR_CENTROID
    rows = []
    for k, kind in enumerate(KINDS):
        T, R = room_poses(kind)
        angles = np.arctan2(R[:, 0, 2], R[:, 0, 0])[:, None]
        tag = f"{k:04d}aaaa-house_Bedroom-{100 + k}"
        (root / tag).mkdir(exist_ok=True)
        np.savez_compressed(root / tag / "boxes.npz", uids=np.array([f"u{i}" for i in range(3)]), jids=np.array(JIDS),
                            scene_id=np.asarray(f"Bedroom-{100 + k}"), scene_type=np.asarray("MasterBedroom"),
                            class_labels=one_hot.astype(np.float32), translations=T.astype(np.float32),
                            sizes=sizes.astype(np.float32), angles=angles.astype(np.float32),
                            floor_plan_vertices=floor.astype(np.float32),
                            floor_plan_faces=np.array([[0, 2, 1], [0, 3, 2]], np.int32),
                            floor_plan_centroid=FLOOR_CENTROID.astype(np.float32))
        rows.append(f"Bedroom-{100 + k},{'train' if kind in ('rest', 'sunk') else 'test'}")
    (root / "dataset_stats.txt").write_text(json.dumps({
        "class_labels": FRONT_CLASSES, "object_types": FRONT_CLASSES[:3],
        "bounds_translations": [-2.0, 0.0, -2.0, 2.0, 1.5, 2.0]}))
    splits = root.parent / "bedroom_splits.csv"
    splits.write_text("\n".join(rows) + "\n")
    return root, splits
