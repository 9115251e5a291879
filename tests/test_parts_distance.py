"""The ``parts`` geometry distance (spread.data.parts, spread.model.parts_distance): known answers on boxes, the
union's surface at zero, far parts skipped without changing what is measured, mirrored assets, clean rooms read
clean (where the release's chamfer proxy reads most objects penetrating), and a +Geometry model that reads it,
trained and sampled from the command line."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from spread.data.parts import FACE_CAP, PART_CAP, asset_part_planes, mirror_planes
from spread.model.parts_distance import PARTS_RANGE, PartPlanes, parts_distances

from helpers import FAST_SAMPLE, FAST_TRAIN, SMALL_MODEL, make_dataset, run_script, train_in_process


def _batch_of(parts_per_object, points, translation, rotation):
    """A one-scene batch: part planes of each object, its world points (N, M, 3), poses (N, 3), (N, 3, 3)."""
    arrays = [asset_part_planes(p) for p in parts_per_object]
    planes, boxes, valid = (torch.from_numpy(np.stack(a))[None] for a in zip(*arrays))
    mask = torch.ones(1, len(arrays), dtype=torch.bool)
    parts = PartPlanes.from_batch({"part_planes": planes, "part_boxes": boxes, "part_valid": valid}, mask)
    world = torch.as_tensor(points, dtype=torch.float32)[None]
    return parts, world, torch.as_tensor(translation, dtype=torch.float32)[None], \
        torch.as_tensor(rotation, dtype=torch.float32)[None], mask


def _rot_y(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32)


def test_a_point_inside_a_box_reads_minus_its_depth_outside_its_distance_and_far_away_the_range():
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.4))  # j: half sizes 0.5, 0.25, 0.2
    probe = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    # object 0 is the box, posed at (2, 0.25, 1) turned 90° about y (its local x along world −z); object 1's
    # "points" are world positions placed against it
    R = np.stack([_rot_y(math.pi / 2), np.eye(3, dtype=np.float32)])
    t = np.array([[2.0, 0.25, 1.0], [0.0, 0.0, 0.0]], np.float32)
    local = np.array([[0.47, 0.0, 0.0],    # 3 cm inside the local +x face
                      [0.0, 0.0, 0.25],    # 5 cm outside the local +z face
                      [0.0, 0.40, 0.0],    # 15 cm above the top: beyond the range
                      [0.0, 0.0, 0.0]], np.float32)  # the centre: 20 cm deep (the nearest face is z)
    world = local @ R[0].T + t[0]
    points = np.zeros((2, 4, 3), np.float32)
    points[0] = np.array([[0.1, 0.2, 0.1]] * 4)  # object 0's own points (far from object 1's little probe)
    points[1] = world
    parts, world_t, tt, RR, mask = _batch_of([[box], [probe]], points, t, R)
    d = parts_distances(parts, world_t, tt, RR, mask[0:1])
    assert torch.allclose(d[0, 1], torch.tensor([-0.03, 0.05, PARTS_RANGE, -0.2]), atol=1e-5)


def test_the_surface_of_an_asset_of_several_parts_reads_zero_and_inside_the_union_reads_negative():
    # an L of two overlapping boards and a post: every point of the union's surface lies on one part's boundary
    # and outside (or on) the others, so min over parts of max over planes is 0 there
    parts = [trimesh.creation.box(extents=(1.0, 0.05, 0.6)),
             trimesh.creation.box(extents=(0.05, 0.8, 0.6), transform=trimesh.transformations.translation_matrix(
                 (0.475, 0.375, 0.0))),
             trimesh.creation.cylinder(radius=0.05, height=0.5, sections=16,
                                       transform=trimesh.transformations.translation_matrix((-0.3, 0.25, 0.0)))]
    union = trimesh.boolean.union(parts, engine="manifold")
    surface, _ = trimesh.sample.sample_surface(union, 400, seed=0)
    inside = np.array([[0.0, 0.0, 0.0], [0.475, 0.5, 0.1], [-0.3, 0.25, 0.1]])  # (the post's axis is z)
    planes, boxes, valid = asset_part_planes(parts)
    assert planes.shape == (PART_CAP, FACE_CAP, 4) and valid.sum() == 3
    q = torch.from_numpy(np.concatenate([surface, inside]).astype(np.float32))
    s = (torch.einsum("mj,pfj->mpf", q, torch.from_numpy(planes[:3, :, :3])) - torch.from_numpy(planes[:3, :, 3])) \
        .amax(-1).amin(-1)
    assert s[:400].abs().max() < 1e-4
    assert torch.allclose(s[400:], torch.tensor([-0.025, -0.025, -0.05 * math.cos(math.pi / 16)]), atol=1e-5)


def test_a_part_of_many_faces_keeps_a_spread_of_them_round_the_part():
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)  # 320 faces: more planes than the cap
    planes, _, valid = asset_part_planes([ball])
    n, d = planes[0, :, :3], planes[0, :, 3]
    assert valid.sum() == 1 and len(np.unique(np.round(n, 4), axis=0)) == FACE_CAP
    vertices = np.asarray(ball.vertices)
    assert (vertices @ n.T - d).max() <= 1e-6  # every vertex inside or on the kept planes: a polytope round it
    assert (vertices @ n.T - d).max(1).min() > -0.03  # and close round it (24 planes round a 20 cm ball: 3 cm)


def test_skipping_far_parts_changes_nothing_within_the_range():
    rng = np.random.default_rng(0)
    shapes = [[trimesh.creation.box(extents=rng.uniform(0.1, 0.6, 3))] for _ in range(4)]
    shapes[1].append(trimesh.creation.box(extents=(0.1, 0.4, 0.1)))
    points = np.stack([trimesh.sample.sample_surface(s[0], 64, seed=k)[0] for k, s in enumerate(shapes)])
    for trial in range(5):
        R = np.stack([_rot_y(a) for a in rng.uniform(-math.pi, math.pi, 4)])
        t = rng.uniform(-0.4, 0.4, (4, 3)).astype(np.float32)
        world = np.einsum("nij,nmj->nmi", R, points) + t[:, None]
        parts, w, tt, RR, mask = _batch_of(shapes, world, t, R)
        pruned = parts_distances(parts, w, tt, RR, mask)
        every = parts_distances(parts, w, tt, RR, mask, reach=100.0).clamp(max=PARTS_RANGE)
        assert (pruned >= every - 1e-6).all()  # a skipped part's lower bound never beats what was measured
        near = pruned < PARTS_RANGE
        assert near.any() and torch.allclose(pruned[near], every[near], atol=1e-6)
        assert torch.allclose(pruned, parts_distances(parts, w, tt, RR, mask, max_elements=1000), atol=0)


def test_a_mirrored_asset_has_the_mirrored_planes_and_boxes():
    wedge = trimesh.creation.box(extents=(0.4, 0.2, 0.3), transform=trimesh.transformations.translation_matrix(
        (0.3, 0.0, 0.0)))
    planes, boxes, _ = asset_part_planes([wedge])
    mirrored = wedge.copy()
    mirrored.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))
    m_planes, m_boxes = mirror_planes(planes, boxes)
    assert np.allclose(m_boxes[0], mirrored.bounds, atol=1e-6)
    probe = np.array([[-0.3, 0.0, 0.0], [-0.45, 0.0, 0.0], [0.3, 0.0, 0.0]])  # inside, on the face, outside
    s = (probe @ m_planes[0, :, :3].T - m_planes[0, :, 3]).max(1)
    assert np.allclose(s, [-0.1, -0.05, 0.4], atol=1e-6)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("partsdata"))


def test_ground_truth_rooms_read_no_penetration_where_the_chamfer_proxy_reads_many(dataset):
    from spread.data import SceneDataset
    from spread.data.collate import collate_scenes
    from spread.model.geometry import prepare_points, state_distances
    from spread.model.poses import denormalize_affine

    ds = SceneDataset(dataset, "train", num_points=256, geometry_distance="parts")
    batch = collate_scenes([ds[i] for i in range(len(ds))])
    assert batch["part_planes"].shape[2:] == (PART_CAP, FACE_CAP, 4)
    offset, scale = denormalize_affine(torch.tensor(ds.stats["bounds_translations"]))
    cloud = prepare_points(batch["points"], batch["normals"], batch["mask"])
    chamfer = state_distances(cloud, batch["x"], offset, scale)
    cloud.parts = PartPlanes.from_batch(batch, batch["mask"])
    parts = state_distances(cloud, batch["x"], offset, scale)
    keep = cloud.has_other[..., 0]
    assert (parts.amin(-1)[keep] > -0.01).all()  # the generator's rooms are collision-free to the millimetre
    assert (chamfer.amin(-1)[keep] < -0.01).float().mean() > 0.3
    assert (parts[~batch["mask"]] == 0).all() and (parts <= PARTS_RANGE).all()


def test_a_batch_without_part_planes_and_an_unknown_distance_are_refused(dataset):
    from spread.model.config import ModelConfig
    from spread.model.network import SceneDenoiser

    with pytest.raises(ValueError, match="geometry_distance.*'box'"):
        SceneDenoiser(ModelConfig(geometry_distance="box"), "geometry")
    with pytest.raises(ValueError, match=r"data.geometry_distance: unknown 'part' \(choose from \['chamfer', "):
        from spread.data import SceneDataset

        SceneDataset(dataset, "train", num_points=8, geometry_distance="part")
    with pytest.raises(ValueError, match=r"geometry_distance=parts: the batch has no \['part_planes'"):
        PartPlanes.from_batch({"points": torch.zeros(1, 1, 1, 3)}, torch.ones(1, 1, dtype=torch.bool))


def test_a_geometry_model_reading_parts_trains_and_samples_from_the_command_line(dataset, tmp_path):
    import json

    from spread.scene import list_scene_files

    out = tmp_path / "run"
    train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=2",
                     "model.variant=geometry", "model.config.geometry_distance=parts", *SMALL_MODEL, *FAST_TRAIN)
    hparams = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")["hyper_parameters"]
    assert hparams["config"]["geometry_distance"] == "parts"
    scenes = tmp_path / "samples"
    run_script("spread-sample", f"ckpt={out / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}",
               f"out_dir={scenes}", *FAST_SAMPLE)
    assert len(list_scene_files(scenes / "scenes")) == 3
    assert json.loads((scenes / "sampling.json").read_text())["written_this_run"] == 3
