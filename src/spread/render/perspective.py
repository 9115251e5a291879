"""Perspective 3D view of a scene, shaded and coloured by category, rendered headless on the CPU.

**Renderer: pybullet's TinyRenderer** (``getCameraImage(..., renderer=ER_TINY_RENDERER)`` on a DIRECT
client). Why this one: pybullet is already the platform's physics engine (a dependency with wheels for
every platform), and TinyRenderer is a software rasteriser inside it — no display, no OpenGL, EGL or
OSMesa, no GPU, nothing to install — with a z-buffer, per-pixel Lambert + ambient + specular shading
from vertex normals, and a segmentation mask (which body each pixel shows) for free. The alternatives
need more: pyrender / Open3D / trimesh's viewer need an OpenGL context (a display, EGL or an OSMesa
build), Blender is a 300 MB install, matplotlib's 3D axes sort whole polygons (wrong occlusion where
meshes interpenetrate — exactly what a generated scene does). TinyRenderer's shadow map is unreliable
(light leaks in bands over large floors), so shadows are off; there is no anti-aliasing, so the image
is rendered ``supersample`` times larger and box-filtered down.

**What is drawn.** Every object's canonical mesh from the asset library, placed by
``v_world = R · v_local + t`` (DESIGN §3), smooth-shaded within 30° creases (trimesh's
``smooth_shaded``: boxes keep sharp edges, cylinders look round), in its category's palette colour
(:mod:`spread.render.palette`); the floor, the room's xz rectangle (or the objects' xz bounds grown by
:data:`FLOOR_MARGIN` without a room) as a slab whose top is y = 0, with grid lines every ``grid`` metres.
The camera is :func:`spread.render.camera.fit_camera`'s three-quarter view of the room unless one is given
(give the same camera to two renders to compare them, as :mod:`spread.render.figures` does for before /
after physics). The light comes from above, a little from the camera's side, so top faces are brightest
and faces towards the camera brighter than faces turned away.

One DIRECT client per process (``_client()``), made on first use; each asset's visual shape is built once
per client (keyed by the mesh's content hash) and shared by every body of every render. A render adds
the scene's bodies, takes the picture and removes them again.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from spread.render.camera import Camera, fit_camera
from spread.render.palette import DEFAULT_PALETTE, PALETTES, category_colours
from spread.render.settings import VIEW_SETTINGS_FLOOR

#: Metres of floor around the objects when the scene has no room rectangle.
FLOOR_MARGIN = 0.5
#: Thickness of the floor slab below y = 0, metres.
FLOOR_THICKNESS = 0.02
#: Label of floor pixels in :func:`render_perspective`'s label image (objects are 0..N−1, background −1).
FLOOR_LABEL = -2
#: Face normals further apart than this (degrees) keep a sharp edge between them.
CREASE_ANGLE = 30.0


@dataclass(frozen=True)
class PerspectiveSettings:
    """Everything that changes a 3D view. width, height: output pixels; fov_y: vertical field of view,
    degrees; elevation, azimuth, margin: the default camera (:func:`~spread.render.camera.fit_camera`);
    supersample: render this many times larger per side, then average (anti-aliasing); background, floor,
    grid_colour: RGB (floor None: no floor); grid: metres between floor grid lines (None: none); palette;
    ambient, diffuse, specular: TinyRenderer's light coefficients."""

    width: int = 640
    height: int = 480
    fov_y: float = 40.0
    elevation: float = 40.0
    azimuth: float = 30.0
    margin: float = 0.04
    supersample: int = 2
    background: tuple[int, int, int] = (255, 255, 255)
    floor: tuple[int, int, int] | None = VIEW_SETTINGS_FLOOR
    grid: float | None = 1.0
    grid_colour: tuple[int, int, int] = (200, 196, 188)
    palette: str = DEFAULT_PALETTE
    ambient: float = 0.55
    diffuse: float = 0.5
    specular: float = 0.08

    def __post_init__(self) -> None:
        if int(self.width) < 8 or int(self.height) < 8:
            raise ValueError(f"width and height must be at least 8 pixels, got {self.width} × {self.height}")
        if not 1 <= int(self.supersample) <= 4:
            raise ValueError(f"supersample must be 1..4, got {self.supersample}")
        if self.palette not in PALETTES:
            raise ValueError(f"unknown palette '{self.palette}' (known: {sorted(PALETTES)})")
        if self.grid is not None and not self.grid > 0:
            raise ValueError(f"grid must be None or > 0 metres, got {self.grid}")
        for name in ("background", "floor", "grid_colour"):
            value = getattr(self, name)
            if value is None and name == "floor":
                continue
            if len(value) != 3 or not all(0 <= int(v) <= 255 for v in value):
                raise ValueError(f"{name} must be an RGB triple of 0..255, got {value}")
            object.__setattr__(self, name, tuple(int(v) for v in value))

    @property
    def aspect(self) -> float:
        return self.width / self.height


def posed_bounds(scene, library) -> tuple[np.ndarray, np.ndarray]:
    """World (lo, hi) corners (3,) of the posed meshes of ``scene`` (metres)."""
    if scene.num_objects == 0:
        return np.zeros(3), np.zeros(3)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for aid, R, t in zip(scene.asset_id, scene.rotation.astype(np.float64), scene.translation.astype(np.float64)):
        v = np.asarray(library.mesh(str(aid)).vertices, np.float64) @ R.T + t
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    return lo, hi


def floor_rect(scene, library) -> tuple[float, float, float, float]:
    """(x_min, z_min, x_max, z_max) of the floor drawn under ``scene``: its room, else the objects' xz bounds
    grown by :data:`FLOOR_MARGIN`."""
    if scene.room is not None:
        room = np.asarray(scene.room, np.float64)
        return float(room[0, 0]), float(room[0, 2]), float(room[1, 0]), float(room[1, 2])
    lo, hi = posed_bounds(scene, library)
    return (float(lo[0] - FLOOR_MARGIN), float(lo[2] - FLOOR_MARGIN),
            float(hi[0] + FLOOR_MARGIN), float(hi[2] + FLOOR_MARGIN))


def view_box(scenes, library) -> tuple[np.ndarray, np.ndarray]:
    """The world box a default camera frames for ``scenes`` (one or several, e.g. before and after
    physics): the union of their floors (y = 0) and posed objects."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for scene in scenes:
        x0, z0, x1, z1 = floor_rect(scene, library)
        lo, hi = np.minimum(lo, [x0, 0.0, z0]), np.maximum(hi, [x1, 0.0, z1])
        if scene.num_objects:
            a, b = posed_bounds(scene, library)
            lo, hi = np.minimum(lo, a), np.maximum(hi, b)
    return lo, hi


def default_camera(scenes, library, settings: PerspectiveSettings | None = None) -> Camera:
    """The default three-quarter view (:func:`~spread.render.camera.fit_camera`) framing ``scenes``."""
    settings = settings or PerspectiveSettings()
    scenes = [scenes] if hasattr(scenes, "asset_id") else list(scenes)
    lo, hi = view_box(scenes, library)
    return fit_camera(lo, hi, settings.aspect, settings.fov_y, settings.elevation, settings.azimuth,
                      settings.margin)


class _Client:
    """One pybullet DIRECT client used only for pictures, with its visual shapes."""

    def __init__(self):
        import pybullet

        self.pb = pybullet
        self.id = pybullet.connect(pybullet.DIRECT)
        if self.id < 0:
            raise RuntimeError("pybullet: could not open a DIRECT client for rendering")
        weakref.finalize(self, _disconnect, pybullet, self.id)
        self.shapes: dict[tuple, int] = {}

    def call(self, name: str, *args, **kwargs):
        return getattr(self.pb, name)(*args, physicsClientId=self.id, **kwargs)

    def mesh_shape(self, key: tuple, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> int:
        if key not in self.shapes:
            sid = self.call("createVisualShape", self.pb.GEOM_MESH, vertices=np.asarray(vertices, float).tolist(),
                            indices=np.asarray(faces, np.int64).reshape(-1).tolist(),
                            normals=np.asarray(normals, float).tolist())
            if sid < 0:
                raise RuntimeError(f"pybullet could not create the visual shape {key}")
            self.shapes[key] = sid
        return self.shapes[key]

    def asset_shape(self, library, asset_id: str) -> int:
        key = ("asset", str(asset_id), library[asset_id].content_hash)
        if key not in self.shapes:
            smooth = _smooth(library.mesh(asset_id))
            return self.mesh_shape(key, smooth.vertices, smooth.faces, smooth.vertex_normals)
        return self.shapes[key]

    def body(self, shape: int, position, orientation, rgb) -> int:
        body = self.call("createMultiBody", baseMass=0.0, baseVisualShapeIndex=shape,
                         basePosition=list(map(float, position)), baseOrientation=list(map(float, orientation)))
        self.call("changeVisualShape", body, -1, rgbaColor=[c / 255.0 for c in rgb] + [1.0])
        return body


def _disconnect(pb, client: int) -> None:
    if pb.isConnected(physicsClientId=client):
        pb.disconnect(physicsClientId=client)


_CLIENT: _Client | None = None


def _client() -> _Client:
    global _CLIENT
    if _CLIENT is None:
        _CLIENT = _Client()
    return _CLIENT


def _smooth(mesh):
    import trimesh

    copy = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False)
    return copy.smooth_shaded if len(copy.faces) else copy


def _floor_meshes(rect, grid: float | None):
    """(slab, grid lines or None) trimeshes of the floor rectangle (top of the slab at y = 0)."""
    import trimesh

    x0, z0, x1, z1 = rect
    slab = trimesh.creation.box(extents=[x1 - x0, FLOOR_THICKNESS, z1 - z0])
    slab.apply_translation([(x0 + x1) / 2, -FLOOR_THICKNESS / 2, (z0 + z1) / 2])
    if grid is None:
        return slab, None
    width, lift = 0.012, 0.0008  # metres: line width, and how far above the floor (no z-fighting)
    lines = []
    for x in np.arange(math.ceil(x0 / grid) * grid, x1 + 1e-9, grid):
        box = trimesh.creation.box(extents=[width, lift, z1 - z0])
        box.apply_translation([x, lift / 2, (z0 + z1) / 2])
        lines.append(box)
    for z in np.arange(math.ceil(z0 / grid) * grid, z1 + 1e-9, grid):
        box = trimesh.creation.box(extents=[x1 - x0, lift, width])
        box.apply_translation([(x0 + x1) / 2, lift / 2, z])
        lines.append(box)
    return slab, (trimesh.util.concatenate(lines) if lines else None)


def light_direction(camera: Camera) -> list[float]:
    """Direction towards the light: mostly world up, some towards the camera, a little from its right."""
    right, _, forward = camera.axes()
    d = np.array([0.0, 1.0, 0.0]) - 0.55 * forward + 0.3 * right
    return (d / np.linalg.norm(d)).tolist()


def render_perspective(scene, library, settings: PerspectiveSettings | None = None, camera: Camera | None = None,
                       return_labels: bool = False):
    """(H, W, 3) uint8 3D view of ``scene`` (module docstring); with ``return_labels`` also the (H, W) int64
    label image: object index, :data:`FLOOR_LABEL` on the floor, −1 on the background (the sample at each
    output pixel's centre)."""
    from spread.physics.frames import matrix_to_quat

    settings = settings or PerspectiveSettings()
    camera = camera or default_camera(scene, library, settings)
    s = int(settings.supersample)
    width, height = settings.width * s, settings.height * s
    client = _client()
    bodies: dict[int, int] = {}
    try:
        if settings.floor is not None:
            rect = floor_rect(scene, library)
            slab, grid = _floor_meshes(rect, settings.grid)
            key = tuple(round(v, 4) for v in rect) + (settings.grid,)
            sid = client.mesh_shape(("floor",) + key, slab.vertices, slab.faces, slab.vertex_normals)
            bodies[client.body(sid, (0, 0, 0), (0, 0, 0, 1), settings.floor)] = FLOOR_LABEL
            if grid is not None:
                gid = client.mesh_shape(("grid",) + key, grid.vertices, grid.faces, grid.vertex_normals)
                bodies[client.body(gid, (0, 0, 0), (0, 0, 0, 1), settings.grid_colour)] = FLOOR_LABEL
        if scene.num_objects:
            quats = matrix_to_quat(scene.rotation.astype(np.float64))
            colours = category_colours(scene.category, settings.palette)
            for i, aid in enumerate(scene.asset_id):
                shape = client.asset_shape(library, str(aid))
                bodies[client.body(shape, scene.translation[i], quats[i], colours[i].tolist())] = i
        view, projection = camera.gl_matrices()
        _, _, rgba, _, seg = client.call(
            "getCameraImage", width, height, view, projection, renderer=client.pb.ER_TINY_RENDERER,
            shadow=0, lightDirection=light_direction(camera), lightAmbientCoeff=settings.ambient,
            lightDiffuseCoeff=settings.diffuse, lightSpecularCoeff=settings.specular)
    finally:
        for body in bodies:
            client.call("removeBody", body)
    rgb = np.asarray(rgba, np.uint8).reshape(height, width, 4)[..., :3].astype(np.float64)
    seg = np.asarray(seg, np.int64).reshape(height, width)
    rgb[seg < 0] = settings.background
    image = rgb.reshape(settings.height, s, settings.width, s, 3).mean(axis=(1, 3))
    image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    if not return_labels:
        return image
    ids, inverse = np.unique(seg[s // 2::s, s // 2::s], return_inverse=True)
    labels = np.array([bodies.get(int(b), -1) for b in ids], np.int64)[inverse]
    return image, labels.reshape(settings.height, settings.width)
