"""A scene as a USD stage with UsdPhysics rigid bodies, what Isaac Sim (PhysX) and other USD physics readers load.

Stage: metres (``metersPerUnit`` 1), kilograms (``kilogramsPerUnit`` 1), **y-up** (``upAxis`` Y, the
platform's frame), default prim ``/World``. Layout::

    /World                     Xform
    /World/PhysicsScene        UsdPhysics.Scene: gravity (0, −1, 0) × 9.81 m/s²
    /World/PhysicsMaterial     UsdPhysics.MaterialAPI: friction 0.6 (static and dynamic), restitution 0
    /World/Floor               Cube scaled to a static box whose top face is y = 0 (collider, no rigid body)
    /World/Objects/o<k>_<asset>    Xform with RigidBodyAPI + MassAPI, pose = the scene pose (translate, orient);
                               wall and ceiling mounts are kinematic (``physics:kinematicEnabled``: welded,
                               gravity does not move them); ``spread:mount`` names the mount
        Visual                 Mesh: the asset's mesh, coloured by category
        Collision_<j>          a convex part: Cube (cuboid parts) or Mesh with convexHull approximation;
                               CollisionAPI, purpose "guide" (not rendered)

The body frame is the Scene's canonical frame (bbox centre), so the Xform's pose is ``t``, ``R`` as they
are; MassAPI gives the asset's mass, its centre of mass and principal inertia in that frame (the
watertight mesh at uniform density, :func:`spread.physics.shapes.mass_frame`), ``principalAxes`` the
rotation from the body frame to the principal axes. Colliders are the asset's exact convex parts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Thickness of the exported floor box, metres (its top face is y = 0).
FLOOR_THICKNESS = 0.1


def _quat(R: np.ndarray):
    """Gf.Quatf/d pieces (w, (x, y, z)) of a rotation matrix."""
    from spread.physics.mjcf import matrix_to_wxyz

    w, x, y, z = matrix_to_wxyz(np.asarray(R, np.float64)[None])[0]
    return float(w), (float(x), float(y), float(z))


def _mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray):
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(vertices, np.float32)))
    faces = np.asarray(faces, np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


def _set_pose(xformable, translation, R) -> None:
    from pxr import Gf, UsdGeom

    w, xyz = _quat(R)
    xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, translation)))
    xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(w, Gf.Vec3d(*xyz)))


def build_usd_stage(scene, library, path: str | Path, colours: np.ndarray, floor: bool = True,
                    floor_rect: tuple[float, float, float, float] | None = None):
    """Create and save the stage of ``scene`` at ``path`` (the file name picks .usda text or .usd/.usdc
    binary); returns the stage."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade
    from scipy.spatial import ConvexHull

    from spread.io import safe_name
    from spread.physics import PhysicsParams
    from spread.physics.mjcf import asset_geometry

    params = PhysicsParams()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    stage.GetRootLayer().customLayerData = {"spread:scene_id": str(scene.scene_id)}

    physics = UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")
    g = np.asarray(params.gravity, np.float64)
    physics.CreateGravityDirectionAttr(Gf.Vec3f(*(g / np.linalg.norm(g)).tolist()))
    physics.CreateGravityMagnitudeAttr(float(np.linalg.norm(g)))

    material = UsdShade.Material.Define(stage, "/World/PhysicsMaterial")
    mat_api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
    mat_api.CreateStaticFrictionAttr(float(params.friction))
    mat_api.CreateDynamicFrictionAttr(float(params.friction))
    mat_api.CreateRestitutionAttr(float(params.restitution))

    def collider(prim) -> None:
        UsdPhysics.CollisionAPI.Apply(prim)
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(material, UsdShade.Tokens.weakerThanDescendants, "physics")

    if floor:
        x0, z0, x1, z1 = floor_rect
        cube = UsdGeom.Cube.Define(stage, "/World/Floor")
        cube.CreateSizeAttr(1.0)
        cube.AddTranslateOp().Set(Gf.Vec3d((x0 + x1) / 2, -FLOOR_THICKNESS / 2, (z0 + z1) / 2))
        cube.AddScaleOp().Set(Gf.Vec3f(x1 - x0, FLOOR_THICKNESS, z1 - z0))
        cube.CreateDisplayColorAttr([Gf.Vec3f(0.75, 0.75, 0.75)])
        collider(cube.GetPrim())

    from spread.scene import MOUNT_NAMES, scene_mounts, welded_objects

    mounts, welded = scene_mounts(scene), welded_objects(scene)
    UsdGeom.Scope.Define(stage, "/World/Objects")
    for i, aid in enumerate(str(a) for a in scene.asset_id):
        geom = asset_geometry(library, aid)
        mass = float(library[aid].mass)
        body_path = f"/World/Objects/o{i:03d}_{safe_name(aid)}".replace(".", "_").replace("-", "_")
        body = UsdGeom.Xform.Define(stage, body_path)
        _set_pose(body, scene.translation[i], scene.rotation[i])
        prim = body.GetPrim()
        prim.CreateAttribute("spread:asset_id", Sdf.ValueTypeNames.String).Set(aid)
        prim.CreateAttribute("spread:category", Sdf.ValueTypeNames.String).Set(str(scene.category[i]))
        prim.CreateAttribute("spread:mount", Sdf.ValueTypeNames.String).Set(MOUNT_NAMES[int(mounts[i])])
        rigid = UsdPhysics.RigidBodyAPI.Apply(prim)
        if welded[i]:
            rigid.CreateKinematicEnabledAttr(True)
        mass_api = UsdPhysics.MassAPI.Apply(prim)
        mass_api.CreateMassAttr(mass)
        mass_api.CreateCenterOfMassAttr(Gf.Vec3f(*geom.com.tolist()))
        mass_api.CreateDiagonalInertiaAttr(Gf.Vec3f(*(geom.inertia_per_kg * mass).tolist()))
        w, xyz = _quat(geom.axes)
        mass_api.CreatePrincipalAxesAttr(Gf.Quatf(w, Gf.Vec3f(*xyz)))

        canon = library.mesh(aid)
        visual = _mesh(stage, f"{body_path}/Visual", canon.vertices, canon.faces)
        visual.CreateDisplayColorAttr([Gf.Vec3f(*map(float, colours[i][:3]))])
        for b in range(len(geom.box_centre)):
            cube = UsdGeom.Cube.Define(stage, f"{body_path}/Collision_box{b:02d}")
            cube.CreateSizeAttr(2.0)  # half extents 1, scaled below
            q = [float(v) for v in geom.box_quat[b]]  # w, x, y, z
            cube.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*geom.box_centre[b].tolist()))
            cube.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(q[0], Gf.Vec3d(*q[1:])))
            cube.AddScaleOp().Set(Gf.Vec3f(*geom.box_half[b].tolist()))
            cube.CreatePurposeAttr(UsdGeom.Tokens.guide)
            collider(cube.GetPrim())
        for h, verts in enumerate(geom.hulls):
            part = _mesh(stage, f"{body_path}/Collision_hull{h:02d}", verts, ConvexHull(verts).simplices)
            part.CreatePurposeAttr(UsdGeom.Tokens.guide)
            collider(part.GetPrim())
            UsdPhysics.MeshCollisionAPI.Apply(part.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)
    stage.GetRootLayer().Save()
    return stage
