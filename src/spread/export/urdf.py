"""A scene as URDF files that pybullet (and other URDF readers) load: one URDF per object, one for the floor.

URDF describes one articulated tree, and the objects of a room are separate free bodies, so a scene is a
folder::

    <scene>/scene.json          gravity, up axis, and per object: its URDF, base position and orientation
    <scene>/floor.urdf          a static box whose top face is the plane y = 0
    <scene>/objects/<k>_<asset>.urdf
    <scene>/meshes/<asset>/visual.obj, part_<j>.obj

Each object URDF has one link whose frame is the Scene's canonical frame of the asset (bbox centre), so
the base pose in ``scene.json`` is the scene pose (``t``, quaternion of ``R``, x y z w) as it is.
Inertial: the asset's mass (kg), its centre of mass and principal inertia (the watertight mesh at uniform
density, :func:`spread.physics.shapes.mass_frame`; ``rpy`` turns the link frame into the principal axes).
Collision: one element per convex part — cuboid parts as ``<box>``, others as an .obj of the part (loaded
as its convex hull). Parts are exact; note that Bullet grows mesh hulls by a 1 mm margin (the platform's
own world insets them, :mod:`spread.physics.shapes`), so in plain pybullet objects rest ≈ 1 mm higher.
Visual: the asset's mesh, coloured by category. ``<contact>`` carries pybullet's per-body friction values
that multiply to the platform's pairwise coefficients (:class:`~spread.physics.PhysicsParams`).
Frame y-up, metres; gravity (0, −9.81, 0) is in ``scene.json`` (URDF has no gravity).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from spread.io import read_json

#: Thickness of the exported floor box, metres (its top face is y = 0).
FLOOR_THICKNESS = 0.1
#: The floor box reaches this far beyond the room (or the objects), metres.
FLOOR_MARGIN = 1.0


def _num(values) -> str:
    return " ".join("%.10g" % float(v) for v in np.ravel(values))


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw of a rotation: R = Rz(yaw) · Ry(pitch) · Rx(roll)."""
    import warnings

    from scipy.spatial.transform import Rotation

    with warnings.catch_warnings():  # at pitch ±90° scipy picks yaw = 0: still the same rotation
        warnings.simplefilter("ignore", UserWarning)
        return Rotation.from_matrix(np.asarray(R, np.float64)).as_euler("xyz")


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = ["v %.9g %.9g %.9g" % tuple(v) for v in np.asarray(vertices, np.float64)]
    lines += ["f %d %d %d" % tuple(f + 1) for f in np.asarray(faces, np.int64)]
    path.write_text("\n".join(lines) + "\n")


def floor_rect(scene, margin: float = FLOOR_MARGIN) -> tuple[float, float, float, float]:
    """(x0, z0, x1, z1) of the exported floor: the room's rectangle, else the objects' centres, grown by ``margin``."""
    if scene.room is not None:
        room = np.asarray(scene.room, np.float64)
        lo, hi = room[0, [0, 2]], room[1, [0, 2]]
    else:
        t = np.asarray(scene.translation, np.float64).reshape(-1, 3)
        lo, hi = (t[:, [0, 2]].min(0), t[:, [0, 2]].max(0)) if len(t) else (np.zeros(2), np.zeros(2))
    return float(lo[0] - margin), float(lo[1] - margin), float(hi[0] + margin), float(hi[1] + margin)


def _link_urdf(name: str, mass: float, geom, mesh_dir: str, visual_rgba, friction) -> str:
    from spread.physics.frames import quat_to_matrix

    inertia = geom.inertia_per_kg * mass
    out = [f'<robot name={quoteattr(name)}>', '  <link name="base">',
           '    <contact>',
           f'      <lateral_friction value="{friction[0]:.10g}"/>',
           f'      <rolling_friction value="{friction[1]:.10g}"/>',
           f'      <spinning_friction value="{friction[2]:.10g}"/>',
           '    </contact>',
           '    <inertial>',
           f'      <origin xyz="{_num(geom.com)}" rpy="{_num(_rpy(geom.axes))}"/>',
           f'      <mass value="{mass:.10g}"/>',
           f'      <inertia ixx="{inertia[0]:.10g}" ixy="0" ixz="0" iyy="{inertia[1]:.10g}" iyz="0" izz="{inertia[2]:.10g}"/>',
           '    </inertial>',
           '    <visual>',
           f'      <geometry><mesh filename="{mesh_dir}/visual.obj"/></geometry>',
           f'      <material name={quoteattr(name + "_colour")}><color rgba="{_num(visual_rgba)}"/></material>',
           '    </visual>']
    for b in range(len(geom.box_centre)):
        w, x, y, z = geom.box_quat[b]
        R = quat_to_matrix(np.array([[x, y, z, w]]))[0]
        out += ['    <collision>',
                f'      <origin xyz="{_num(geom.box_centre[b])}" rpy="{_num(_rpy(R))}"/>',
                f'      <geometry><box size="{_num(2.0 * geom.box_half[b])}"/></geometry>',
                '    </collision>']
    for h in range(len(geom.hulls)):
        out += ['    <collision>', f'      <geometry><mesh filename="{mesh_dir}/part_{h:02d}.obj"/></geometry>',
                '    </collision>']
    out += ['  </link>', '</robot>']
    return "\n".join(out) + "\n"


def write_urdf_scene(scene, library, folder: Path, colours: np.ndarray, floor: bool = True) -> Path:
    """Write the URDF folder of ``scene`` into ``folder`` (which must exist and be empty); returns scene.json."""
    from scipy.spatial import ConvexHull

    from spread.io import safe_name
    from spread.physics import PhysicsParams
    from spread.physics.frames import matrix_to_quat
    from spread.physics.mjcf import asset_geometry

    params = PhysicsParams()
    own = math.sqrt(params.friction)  # pybullet multiplies the two bodies' coefficients
    friction = (own, params.rolling_friction, params.spinning_friction)
    (folder / "objects").mkdir()
    ids = [str(a) for a in scene.asset_id]
    for a in dict.fromkeys(ids):
        mesh_dir = folder / "meshes" / safe_name(a)
        mesh_dir.mkdir(parents=True)
        mesh = library.mesh(a)
        write_obj(mesh_dir / "visual.obj", mesh.vertices, mesh.faces)
        for h, verts in enumerate(asset_geometry(library, a).hulls):
            write_obj(mesh_dir / f"part_{h:02d}.obj", verts, ConvexHull(verts).simplices)
    from spread.scene import MOUNT_NAMES, scene_mounts, welded_objects

    quats = matrix_to_quat(np.asarray(scene.rotation, np.float64)) if ids else np.zeros((0, 4))
    mounts, welded = (scene_mounts(scene), welded_objects(scene)) if ids else (np.zeros(0, int), np.zeros(0, bool))
    objects = []
    for i, a in enumerate(ids):
        name = f"{i:03d}_{safe_name(a)}"
        path = folder / "objects" / f"{name}.urdf"
        path.write_text(_link_urdf(name, float(library[a].mass), asset_geometry(library, a),
                                   f"../meshes/{safe_name(a)}", colours[i], friction))
        objects.append({"urdf": f"objects/{name}.urdf", "asset_id": a, "category": str(scene.category[i]),
                        "mass": float(library[a].mass),
                        "position": np.asarray(scene.translation[i], np.float64).tolist(),
                        "orientation_xyzw": quats[i].tolist(),
                        "mount": MOUNT_NAMES[int(mounts[i])], "fixed": bool(welded[i])})
    info = {"scene_id": str(scene.scene_id), "up": "y", "units": "metres", "gravity": [0.0, -9.81, 0.0],
            "frame": "link frame = the asset's bbox centre; position/orientation = the scene pose",
            "fixed": "objects with fixed = true (wall and ceiling mounts) are welded to the world: load them "
                     "with a fixed base",
            "objects": objects, "floor": None}
    if floor:
        x0, z0, x1, z1 = floor_rect(scene)
        size = (x1 - x0, FLOOR_THICKNESS, z1 - z0)
        centre = ((x0 + x1) / 2, -FLOOR_THICKNESS / 2, (z0 + z1) / 2)
        (folder / "floor.urdf").write_text("\n".join([
            '<robot name="floor">', '  <link name="base">',
            f'    <contact><lateral_friction value="{params.floor_friction / own:.10g}"/>'
            f'<rolling_friction value="{params.rolling_friction:.10g}"/>'
            f'<spinning_friction value="{params.spinning_friction:.10g}"/></contact>',
            '    <inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>',
            f'    <visual><origin xyz="{_num(centre)}"/><geometry><box size="{_num(size)}"/></geometry>'
            '<material name="floor"><color rgba="0.75 0.75 0.75 1"/></material></visual>',
            f'    <collision><origin xyz="{_num(centre)}"/><geometry><box size="{_num(size)}"/></geometry></collision>',
            '  </link>', '</robot>']) + "\n")
        info["floor"] = {"urdf": "floor.urdf", "top": 0.0, "rect_xz": [x0, z0, x1, z1]}
    path = folder / "scene.json"
    path.write_text(json.dumps(info, indent=2) + "\n")
    return path


def load_urdf_scene(scene_json: str | Path, client: int) -> dict:
    """Load an exported URDF folder into pybullet client ``client``: gravity, the floor (static), every object
    at its pose (wall and ceiling mounts, ``fixed`` in scene.json, with a fixed base). Returns ``{"objects": [body ids], "floor": id or None}``. Objects are multibody bases (not
    ``useMaximalCoordinates``: pybullet's ``getDynamicsInfo`` misreports their inertial frame, which
    :func:`urdf_scene_poses` needs)."""
    import pybullet as pb

    scene_json = Path(scene_json)
    info = read_json(scene_json)
    root = scene_json.parent
    pb.setGravity(*info["gravity"], physicsClientId=client)
    floor = None
    if info.get("floor"):
        floor = pb.loadURDF(str(root / info["floor"]["urdf"]), useFixedBase=True, physicsClientId=client)
    bodies = [pb.loadURDF(str(root / o["urdf"]), basePosition=o["position"], baseOrientation=o["orientation_xyzw"],
                          useFixedBase=bool(o.get("fixed", False)), physicsClientId=client) for o in info["objects"]]
    return {"objects": bodies, "floor": floor}


def urdf_scene_poses(bodies, client: int) -> tuple[np.ndarray, np.ndarray]:
    """Scene poses (translation (N, 3) bbox centres, rotation (N, 3, 3)) of bodies loaded by
    :func:`load_urdf_scene`: pybullet reports a base's inertial frame, turned back here into its link frame."""
    import pybullet as pb

    from spread.physics.frames import quat_to_matrix

    t, R = np.zeros((len(bodies), 3)), np.zeros((len(bodies), 3, 3))
    for i, body in enumerate(bodies):
        pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=client)
        info = pb.getDynamicsInfo(body, -1, physicsClientId=client)
        local_pos, local_orn = info[3], info[4]  # inertial frame in the link frame
        R_inertial = quat_to_matrix(np.array([orn]))[0]
        R_local = quat_to_matrix(np.array([local_orn]))[0]
        R[i] = R_inertial @ R_local.T
        t[i] = np.asarray(pos) - R[i] @ np.asarray(local_pos)
    return t, R
