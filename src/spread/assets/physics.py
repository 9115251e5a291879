"""Assets in pybullet: each asset's convex parts as one compound collision shape.

pybullet's ``createCollisionShapeArray`` takes no raw vertices, but an OBJ file with one object
(``o`` line) per convex part loads as a compound of exactly those convex hulls. That file is a
per-asset cache, ``cache/<asset_id>.<hash16>.parts.obj``, written once per content hash.

Frames: the world is y-up (call :func:`y_up_world` for gravity (0, −9.81, 0) and the floor plane
y = 0). A body's *local origin* is the asset's bbox centre (the canonical frame); its inertial frame
sits at the mesh's centre of mass. :func:`add_body` takes and :func:`body_pose` returns the pose of
the local origin, ``v_world = R · v_local + t`` as everywhere else (DESIGN §3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spread.assets.library import AssetLibrary
from spread.io import write_text_atomic


def parts_obj_text(parts) -> str:
    """Wavefront OBJ text with one object per part (vertices to 0.1 µm)."""
    lines, offset = [], 1
    for k, part in enumerate(parts):
        lines.append(f"o part{k}")
        lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in np.asarray(part.vertices)]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in np.asarray(part.faces)]
        offset += len(part.vertices)
    return "\n".join(lines) + "\n"


def collision_obj_path(lib: AssetLibrary, asset_id: str) -> Path:
    """The asset's parts as an OBJ compound, written on first use (keyed by the content hash)."""
    path = lib.cache_path(asset_id).with_suffix(".parts.obj")
    if not path.exists():
        write_text_atomic(path, parts_obj_text(lib.convex_parts(asset_id)))
    return path


def y_up_world(client: int) -> int:
    """Set gravity (0, −9.81, 0) and add a static floor plane y = 0; returns the plane's body id."""
    import pybullet as p

    p.setGravity(0.0, -9.81, 0.0, physicsClientId=client)
    plane = p.createCollisionShape(p.GEOM_PLANE, planeNormal=[0, 1, 0], physicsClientId=client)
    return p.createMultiBody(0, plane, physicsClientId=client)


def _quat_xyzw(rotation: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(rotation, float)).as_quat().tolist()


def add_body(lib: AssetLibrary, asset_id: str, position, rotation, client: int, static: bool = False) -> int:
    """Add the asset with its local origin at ``position`` and world-from-local ``rotation``.

    Mass is the record's (0 for ``static``); the inertial frame is at the mesh's centre of mass.
    """
    import pybullet as p

    shape = p.createCollisionShape(p.GEOM_MESH, fileName=str(collision_obj_path(lib, asset_id)),
                                   physicsClientId=client)
    com = np.asarray(lib.mesh(asset_id).center_mass, float)
    return p.createMultiBody(
        0.0 if static else lib[asset_id].mass, shape, basePosition=np.asarray(position, float).tolist(),
        baseOrientation=_quat_xyzw(rotation), baseInertialFramePosition=com.tolist(), physicsClientId=client,
    )


def body_pose(lib: AssetLibrary, asset_id: str, body: int, client: int) -> tuple[np.ndarray, np.ndarray]:
    """(t, R) of the body's local origin; pybullet reports the centre-of-mass frame, undone here."""
    import pybullet as p
    from scipy.spatial.transform import Rotation

    com_world, quat = p.getBasePositionAndOrientation(body, physicsClientId=client)
    R = Rotation.from_quat(quat).as_matrix()
    com = np.asarray(lib.mesh(asset_id).center_mass, float)
    return np.asarray(com_world) - R @ com, R
