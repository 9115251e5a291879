"""MJCF (MuJoCo's XML) of a Scene: the same convex parts, masses and mass frames as the pybullet world.

Per asset (:func:`asset_geometry`, cached per process by content hash): the centre of mass, principal
axes and inertia per kg of its watertight mesh (:func:`spread.physics.shapes.mass_frame`, as pybullet
uses), and its convex parts, each one collision geom. A part that is an exact cuboid becomes a MuJoCo
``box`` (exact, with MuJoCo's dedicated box–box and box–plane contacts, several points per face); any
other part becomes a ``mesh`` geom, whose collision shape MuJoCo takes as the part's convex hull — the
part itself, since parts are convex. No part is inset: MuJoCo adds no margin (``margin`` 0), unlike
Bullet's 1 mm hull margin that :mod:`spread.physics.shapes` compensates for.

Frames: a body's frame is the Scene's canonical frame of its asset (bbox centre, world-from-local ``R``),
so a free body's ``qpos`` is exactly ``(t, quaternion of R)`` and needs no conversion; the inertial frame
sits inside it (``<inertial pos=com quat=axes>``). With ``up="y"`` (the platform's frame, used by the
Stability world) gravity is −y and the floor plane's normal +y. With ``up="z"`` (export: MuJoCo's
viewer and most robotics code are z-up) every body sits in a ``<frame>`` that turns y-up into z-up
(x → x, y → z, z → −y) and gravity is −z; the physics is the same.

A diverging simulation is not reset to the start (``autoreset`` off: a reset would look perfectly still);
its poses turn non-finite and :class:`~spread.physics.mujoco_world.MujocoWorld` raises.

Units SI: metres, kilograms, seconds.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Sequence
from xml.sax.saxutils import quoteattr

import numpy as np

#: Rotation taking the platform's y-up frame to MuJoCo's customary z-up frame (x → x, y → z, z → −y),
#: as a (w, x, y, z) quaternion: +90° about x.
Y_UP_TO_Z_UP = (np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0)
#: A MuJoCo plane's normal is its local +z; this turns it to +y (−90° about x).
PLANE_Z_TO_Y = (np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0)


@dataclass(frozen=True)
class AssetGeometry:
    """One asset's physics geometry in its canonical frame (metres).

    com: (3,) centre of mass; axes: (3, 3) principal axes as columns (det +1); inertia_per_kg: (3,) m².
    boxes: (B, 3) centres, (B, 4) quaternions (w, x, y, z), (B, 3) half extents of the cuboid parts.
    hulls: vertex arrays (K_i, 3) of the other (convex) parts.
    """

    com: np.ndarray
    axes: np.ndarray
    inertia_per_kg: np.ndarray
    box_centre: np.ndarray
    box_quat: np.ndarray
    box_half: np.ndarray
    hulls: tuple[np.ndarray, ...]

    @property
    def num_geoms(self) -> int:
        return len(self.box_centre) + len(self.hulls)


_cache: dict[tuple[str, str], AssetGeometry] = {}
_cache_lock = threading.Lock()


def matrix_to_wxyz(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations → (..., 4) quaternions (w, x, y, z), MuJoCo's order (nearest rotation)."""
    from spread.physics.frames import matrix_to_quat

    R = np.asarray(R, np.float64)
    q = matrix_to_quat(R.reshape(-1, 3, 3))
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1).reshape(R.shape[:-2] + (4,))


def cuboid(vertices: np.ndarray, rel_tol: float = 1e-9):
    """(centre (3,), rotation (3, 3), half extents (3,)) when the convex hull of ``vertices`` is a cuboid,
    else None. Exact test: 8 hull vertices, and the hull's volume equals its oriented bounding box's."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(vertices, np.float64)
    try:
        hull = ConvexHull(pts)
    except QhullError:
        return None
    corners = pts[hull.vertices]
    if len(corners) != 8:
        return None
    centre = corners.mean(0)
    # a cuboid's corners are ±a ±b ±c about the centre: the edge directions are eigenvectors of the scatter
    _, axes = np.linalg.eigh((corners - centre).T @ (corners - centre))
    if np.linalg.det(axes) < 0:
        axes[:, -1] *= -1.0
    local = (corners - centre) @ axes
    half = np.abs(local).max(0)
    if half.min() <= 0 or abs(hull.volume - 8.0 * np.prod(half)) > rel_tol * 8.0 * np.prod(half) + 1e-15:
        return None
    return centre, axes, half


def asset_geometry(library, asset_id: str) -> AssetGeometry:
    """The asset's :class:`AssetGeometry`, computed once per process per (asset id, content hash)."""
    from spread.physics.shapes import mass_frame

    key = (str(asset_id), library[asset_id].content_hash)
    with _cache_lock:
        hit = _cache.get(key)
    if hit is not None:
        return hit
    com, axes, inertia = mass_frame(library.mesh(asset_id))
    centres, quats, halves, hulls = [], [], [], []
    for part in library.convex_parts(asset_id):
        box = cuboid(part.vertices)
        if box is None:
            hulls.append(np.asarray(part.vertices, np.float64).copy())
        else:
            centres.append(box[0])
            quats.append(matrix_to_wxyz(box[1]))
            halves.append(box[2])
    geom = AssetGeometry(com, axes, inertia, np.asarray(centres).reshape(-1, 3), np.asarray(quats).reshape(-1, 4),
                         np.asarray(halves).reshape(-1, 3), tuple(hulls))
    with _cache_lock:
        _cache[key] = geom
    return geom


def _on(flag: bool) -> str:
    return "enable" if flag else "disable"


def _num(values) -> str:
    return " ".join("%.10g" % float(v) for v in np.ravel(values))


def _floor_extent(scene) -> tuple[float, float]:
    """Half size (x, z) of the floor plane to draw; the plane itself is infinite for collisions."""
    if scene.room is not None:
        room = np.asarray(scene.room, np.float64)
        return float(max(abs(room[:, 0]).max(), 1.0)) + 1.0, float(max(abs(room[:, 2]).max(), 1.0)) + 1.0
    if scene.num_objects:
        reach = np.abs(np.asarray(scene.translation, np.float64)[:, [0, 2]]).max(0) + 2.0
        return float(reach[0]), float(reach[1])
    return 5.0, 5.0


def scene_mjcf(scene, library, params=None, up: str = "y", visual: bool = False, floor: bool = True,
               names: Sequence[str] | None = None, colours: np.ndarray | None = None) -> str:
    """MJCF text of ``scene``: a static floor plane (y = 0) and one free body per object at its scene pose;
    wall and ceiling mounts (:func:`spread.scene.welded_objects`) are bodies without a joint (welded to the
    world at their scene pose), so ``qpos`` holds the free bodies only, in scene order.

    ``params``: :class:`~spread.physics.mujoco_world.MujocoParams` (timestep, solver, contact settings);
    defaults if None. ``visual``: also give each body its asset's visual mesh (group 1, no collisions,
    no mass), for viewers and export, coloured by ``colours`` (N, 4) RGBA in [0, 1] if given. ``names``: body
    names (default ``o<index>_<asset_id>``, made safe for XML ids). Masses: the asset records' (kg), inertia from the watertight mesh at uniform density.
    """
    from spread.physics.params import MujocoParams

    if up not in ("y", "z"):
        raise ValueError(f"scene_mjcf: up must be 'y' or 'z', got {up!r}")
    p = params or MujocoParams()
    n = scene.num_objects
    ids = [str(a) for a in scene.asset_id]
    if names is None:
        names = [f"o{i}_{_xml_id(a)}" for i, a in enumerate(ids)]
    masses = np.array([float(library[a].mass) for a in ids])
    if n and (masses <= 0).any():
        bad = ids[int(np.argmax(masses <= 0))]
        raise ValueError(f"asset '{bad}' has mass {masses.min()} kg; physics needs a positive mass")
    order = list(dict.fromkeys(ids))  # each asset's meshes once, in first-use order
    geoms = {a: asset_geometry(library, a) for a in order}
    gravity = (0.0, -p.gravity, 0.0) if up == "y" else (0.0, 0.0, -p.gravity)

    out = [f'<mujoco model={quoteattr(str(scene.scene_id))}>',
           '  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>',
           f'  <option timestep="{p.time_step!r}" gravity="{_num(gravity)}" integrator="{p.integrator}" '
           f'cone="{p.cone}" solver="{p.solver}" iterations="{p.iterations}" tolerance="{p.tolerance!r}" '
           f'noslip_iterations="{p.noslip_iterations}" ccd_iterations="{p.ccd_iterations}" '
           f'ccd_tolerance="{p.ccd_tolerance!r}" sleep_tolerance="{p.sleep_tolerance!r}">',
           f'    <flag refsafe="{_on(p.refsafe)}" multiccd="{_on(p.multiccd)}" sleep="{_on(p.sleep)}" '
           'autoreset="disable"/>',
           '  </option>',
           '  <default>',
           f'    <geom condim="{p.condim}" friction="{_num((p.friction, p.torsional_friction, p.rolling_friction))}" '
           f'solref="{_num(p.solref)}" solimp="{_num(p.solimp)}" margin="0" density="0" group="3"/>',
           '  </default>',
           '  <asset>']
    for k, a in enumerate(order):
        for h, verts in enumerate(geoms[a].hulls):
            out.append(f'    <mesh name="a{k}_hull{h}" vertex="{_num(verts)}"/>')
        if visual:
            mesh = library.mesh(a)
            out.append(f'    <mesh name="a{k}_visual" inertia="shell" vertex="{_num(mesh.vertices)}" '
                       f'face="{" ".join(str(int(f)) for f in np.ravel(mesh.faces))}"/>')
    out.append('  </asset>')
    out.append('  <worldbody>')
    if floor:
        fx, fz = _floor_extent(scene)
        plane_q = PLANE_Z_TO_Y if up == "y" else (1.0, 0.0, 0.0, 0.0)
        out.append(f'    <geom name="floor" type="plane" size="{fx:.6g} {fz:.6g} 0.1" quat="{_num(plane_q)}" '
                   f'priority="1" friction="{_num((p.floor_friction, p.torsional_friction, p.rolling_friction))}" '
                   f'group="0" rgba="0.75 0.75 0.75 1"/>')
    indent = "    "
    if up == "z" and n:
        out.append(f'    <frame name="y_up" quat="{_num(Y_UP_TO_Z_UP)}">')
        indent = "      "
    from spread.scene import welded_objects

    welded = welded_objects(scene) if n else np.zeros(0, bool)
    quats = matrix_to_wxyz(np.asarray(scene.rotation, np.float64)) if n else np.zeros((0, 4))
    t = np.asarray(scene.translation, np.float64)
    index = {a: k for k, a in enumerate(order)}
    for i, a in enumerate(ids):
        g, k = geoms[a], index[a]
        out.append(f'{indent}<body name={quoteattr(names[i])} pos="{_num(t[i])}" quat="{_num(quats[i])}">')
        if not welded[i]:
            out.append(f'{indent}  <freejoint name={quoteattr(names[i] + "_free")}/>')
        out.append(f'{indent}  <inertial pos="{_num(g.com)}" quat="{_num(matrix_to_wxyz(g.axes))}" '
                   f'mass="{float(masses[i])!r}" diaginertia="{_num(g.inertia_per_kg * masses[i])}"/>')
        for b in range(len(g.box_centre)):
            out.append(f'{indent}  <geom type="box" pos="{_num(g.box_centre[b])}" quat="{_num(g.box_quat[b])}" '
                       f'size="{_num(g.box_half[b])}"/>')
        for h in range(len(g.hulls)):
            out.append(f'{indent}  <geom type="mesh" mesh="a{k}_hull{h}"/>')
        if visual:
            rgba = "" if colours is None else f' rgba="{_num(colours[i])}"'
            out.append(f'{indent}  <geom type="mesh" mesh="a{k}_visual" contype="0" conaffinity="0" group="1"{rgba}/>')
        out.append(f'{indent}</body>')
    if up == "z" and n:
        out.append('    </frame>')
    out.append('  </worldbody>')
    out.append('</mujoco>')
    return "\n".join(out) + "\n"


def _xml_id(text: str) -> str:
    """``text`` with every character outside [A-Za-z0-9_.-] replaced by '_' (an MJCF name)."""
    return "".join(c if (c.isascii() and (c.isalnum() or c in "_.-")) else "_" for c in str(text))
