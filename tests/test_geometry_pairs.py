"""Pair geometry on the edges (``model.config.geometry_pairs``): each ordered pair's own distance, known answers on
boxes and the per-point distance as its minimum, an edge input that starts at zero and then carries the geometry,
and a clear refusal without the parts distance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from spread.data.parts import asset_part_planes
from spread.model import SceneDenoiser
from spread.model.geometry import state_distances
from spread.model.parts_distance import PARTS_RANGE, parts_distances
from spread.model.perceiver import DISTANCE_SCALES, PAIR_DIM, pair_features

from test_model import BOUNDS, pad_with_junk, random_batch, tiny
from test_parts_distance import _batch_of, _rot_y


def _three_objects():
    """A 1 × 0.5 × 0.4 m box (object 0) turned 90° about y at (2, 0.25, 1), its points far away; object 1 a 1 cm
    probe with a point 3 cm inside the box and one far away; object 2 a probe 5 cm outside the box."""
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.4))
    probe = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    R = np.stack([_rot_y(math.pi / 2), np.eye(3, dtype=np.float32), np.eye(3, dtype=np.float32)])
    t = np.array([[2.0, 0.25, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], np.float32)
    to_world = lambda local: local @ R[0].T + t[0]  # noqa: E731  (the box's frame → world)
    points = np.zeros((3, 2, 3), np.float32)
    points[0] = [[5.0, 5.0, 5.0], [5.0, 5.0, 5.0]]  # the box's own points: far from everything
    points[1, 0] = to_world(np.array([0.47, 0.0, 0.0], np.float32))  # 3 cm inside the box's local +x face
    points[1, 1] = [0.0, 3.0, 0.0]
    probe_at = to_world(np.array([0.0, 0.0, 0.25], np.float32))  # 5 cm outside the box's local +z face
    t[2] = probe_at
    points[2] = [probe_at, probe_at]
    return _batch_of([[box], [probe], [probe]], points, t, R)


def test_each_pair_reads_its_own_depth_and_the_point_distance_is_the_minimum_over_the_pairs():
    parts, world, t, R, mask = _three_objects()
    d, pair = parts_distances(parts, world, t, R, mask, pairs=True)
    # object 1 is 3 cm deep in the box, object 2 5 cm off it; every other pair (and the diagonal) beyond the range
    expected = torch.full((3, 3), PARTS_RANGE)
    expected[1, 0], expected[2, 0] = -0.03, 0.05
    assert torch.allclose(pair[0], expected, atol=1e-5)
    assert torch.equal(d, parts_distances(parts, world, t, R, mask))  # the points' distances are as without pairs
    assert torch.allclose(d[0].amin(-1), pair[0].amin(-1), atol=1e-6)  # min over points = min over the pairs
    assert (pair[0].diagonal() == PARTS_RANGE).all()


def test_pair_features_read_both_directions_of_a_pair():
    pair = torch.full((1, 3, 3), PARTS_RANGE)
    pair[0, 1, 0] = -0.03
    f = pair_features(pair)
    assert f.shape == (1, 3, 3, PAIR_DIM)
    k = 2 + len(DISTANCE_SCALES)
    scales = torch.tensor(DISTANCE_SCALES)
    assert torch.allclose(f[0, 1, 0, :k], torch.cat([torch.tensor([-0.03, 1.0]), torch.tanh(-0.03 / scales)]))
    assert torch.allclose(f[0, 0, 1, k:], f[0, 1, 0, :k])  # (0, 1) reads the same pair from the other side
    assert f[0, 0, 1, 1].item() == 0.0 and f[0, 2, 2, k + 1].item() == 0.0  # 0 is not inside anything


def _with_parts(batch, seed=0):
    """``batch`` with a random box part per object (canonical, 0.2–0.6 m a side)."""
    rng = np.random.default_rng(seed)
    B, N = batch["mask"].shape
    arrays = [asset_part_planes([trimesh.creation.box(extents=rng.uniform(0.2, 0.6, 3))]) for _ in range(B * N)]
    planes, boxes, valid = (torch.from_numpy(np.stack(a)).view(B, N, *a[0].shape) for a in zip(*arrays))
    return {**batch, "part_planes": planes, "part_boxes": boxes, "part_valid": valid}


def test_a_pairs_model_starts_as_the_model_without_it_and_then_reads_the_pairs():
    torch.manual_seed(0)
    plain = SceneDenoiser(tiny(geometry_distance="parts"), "geometry", BOUNDS).eval()
    pairs = SceneDenoiser(tiny(geometry_distance="parts", geometry_pairs=True), "geometry", BOUNDS).eval()
    assert set(pairs.state_dict()) - set(plain.state_dict()) == {"pairs_in.weight", "pairs_in.bias"}
    with torch.no_grad():
        plain.denoiser.head[-1].weight.normal_()  # zero at initialisation: every output would be 0
    pairs.load_state_dict({**pairs.state_dict(), **plain.state_dict()})
    b = _with_parts(random_batch(sizes=(3, 5), seed=4))
    b["x"][:, :, :3] *= 0.1  # the objects near the room's centre, so that pairs lie within the 10 cm range
    t = torch.tensor([10, 300])
    x_t = b["x"] + 0.01 * torch.randn_like(b["x"]) * b["mask"][..., None]
    with torch.no_grad():
        assert torch.equal(pairs(x_t, t, pairs.condition(b)), plain(x_t, t, plain.condition(b)))
        pairs.pairs_in.weight.normal_()
        eps = pairs(x_t, t, pairs.condition(b))
        assert not torch.allclose(eps, plain(x_t, t, plain.condition(b)), atol=1e-4)
        # the pairs' features are not constant here: some pair is closer than the range
        cond = pairs.condition(b)
        _, pair = state_distances(cond.cloud, x_t, cond.pose_offset, cond.pose_scale, pairs=True)
        assert (pair[b["mask"]] < PARTS_RANGE).any()
        # padding never changes the real objects' outputs
        padded = pad_with_junk(b, extra=2)
        x_junk = torch.cat([x_t, torch.randn(2, 2, 9) * 3], 1)
        eps2 = pairs(x_junk, t, pairs.condition(padded))
    assert torch.allclose(eps2[:, :5][b["mask"]], eps[b["mask"]], atol=1e-5)


def test_pairs_without_the_parts_distance_are_refused():
    with pytest.raises(ValueError, match="geometry_pairs=true needs model.config.geometry_distance=parts"):
        SceneDenoiser(tiny(geometry_pairs=True), "geometry", BOUNDS)
    assert SceneDenoiser(tiny(geometry_pairs=True), "base", BOUNDS).state_dict().keys().isdisjoint({"pairs_in.weight"})
