"""The guidance's geometry found on the states' device (``guidance.detect: device``, spread.guidance.dense) against
the host path (python-fcl, scipy): the same triangle pairs, footprints, steps; known answers of the triangle test."""

import numpy as np
import pytest
import torch

from helpers import asset_library
from spread.guidance import GuidanceConfig, SceneGuidance
from spread.guidance.dense import hull_edges, resolve_detect, triangles_intersect
from spread.guidance.relation import footprint, outside_distances, polygon_distance, segments_distance
from spread.model.opcount import OperatorCounter
from spread.model.poses import poses_from_state

BOUNDS = torch.tensor([-1.0, 0.0, -1.0, 1.0, 1.5, 1.0])


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    return asset_library(tmp_path_factory.mktemp("device_guidance_lib"))


def crowded(lib, seed: int, B: int = 4, N: int = 10, dtype=torch.float64, supports: float = 0.0):
    """Guidance inputs for B crowded rooms (objects at random poses in a 2 m box, so many interpenetrate); scene 0
    has padding. Returns (ids, physical, mask, states)."""
    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(seed)
    ids = [list(rng.choice(sorted(lib.records), N)) for _ in range(B)]
    mask = torch.ones(B, N, dtype=torch.bool)
    mask[0, N - 3:] = False
    ids[0] = ids[0][:N - 3]
    physical = (torch.rand(B, N, N, generator=g) < supports).long()
    x = torch.cat([torch.rand(B, N, 3, generator=g) * 2 - 1, torch.randn(B, N, 6, generator=g)], -1).to(dtype)
    return ids, physical, mask, x


def pairs_at(lib, detect: str, ids, physical, mask, x, **config):
    g = SceneGuidance({"mode": "refine", "detect": detect, **config}, lib, ids, physical, mask, BOUNDS)
    t, R = poses_from_state(x, g._graph(x.device, x.dtype)["bounds"])
    world = g.meshes.pose(t, R)
    p = g.detect(t, R, g.meshes.hull_points(world), world)
    return torch.stack([p.b, p.i, p.fi, p.j, p.fj], 1).tolist(), p.object_pairs


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_device_finds_the_triangle_pairs_python_fcl_finds(lib, dtype):
    for seed in range(3):
        inputs = crowded(lib, seed, dtype=dtype)
        host, host_objects = pairs_at(lib, "host", *inputs, max_contacts=100_000)
        device, device_objects = pairs_at(lib, "device", *inputs, max_contacts=100_000)
        assert len(host) > 100 and host_objects > 5  # a crowd: many pairs to agree on
        assert sorted(map(tuple, device)) == sorted(map(tuple, host)) and device_objects == host_objects


def test_chunks_of_object_pairs_and_of_candidate_triangle_pairs_change_nothing(lib, monkeypatch):
    import spread.guidance.dense as dense

    inputs = crowded(lib, 2)
    whole, _ = pairs_at(lib, "device", *inputs)
    monkeypatch.setitem(dense.CHUNK_ELEMENTS, "cpu", 1)  # one object pair per chunk
    assert pairs_at(lib, "device", *inputs)[0] == whole and len(whole) > 100
    monkeypatch.setattr(dense, "CANDIDATES", 7)  # and its candidate triangle pairs 7 at a time
    assert pairs_at(lib, "device", *inputs)[0] == whole


def test_both_paths_keep_at_most_max_contacts_per_object_pair_the_device_the_first_in_face_order(lib):
    inputs = crowded(lib, 1)
    every, _ = pairs_at(lib, "device", *inputs, max_contacts=100_000)
    host, _ = pairs_at(lib, "host", *inputs, max_contacts=5)
    device, _ = pairs_at(lib, "device", *inputs, max_contacts=5)

    def per_object_pair(rows):
        out = {}
        for b, i, fi, j, fj in rows:
            out.setdefault((b, i, j), []).append((fi, fj))
        return out

    all_pairs = per_object_pair(every)
    assert max(len(v) for v in all_pairs.values()) > 5  # the cap binds somewhere
    want = {k: sorted(v)[:5] for k, v in all_pairs.items()}
    assert per_object_pair(device) == want
    assert {k: len(v) for k, v in per_object_pair(host).items()} == {k: len(v) for k, v in want.items()}


def tri(*corners):
    return torch.tensor([corners], dtype=torch.float64)


@pytest.mark.parametrize("a, b, meet", [
    # crossing: b pierces a's interior
    (tri((0, 0, 0), (1, 0, 0), (0, 1, 0)), tri((0.2, 0.2, -1), (0.2, 0.2, 1), (0.3, 0.3, 1)), True),
    # parallel planes 1 mm apart
    (tri((0, 0, 0), (1, 0, 0), (0, 1, 0)), tri((0, 0, 1e-3), (1, 0, 1e-3), (0, 1, 1e-3)), False),
    # coplanar, overlapping
    (tri((0, 0, 0), (1, 0, 0), (0, 1, 0)), tri((0.2, 0.2, 0), (1.2, 0.2, 0), (0.2, 1.2, 0)), True),
    # coplanar, boxes overlap but the triangles do not (only an in-plane axis separates them)
    (tri((0, 0, 0), (1, 0, 0), (0, 1, 0)), tri((1, 1, 0), (0.6, 1, 0), (1, 0.6, 0)), False),
    # perpendicular planes, edges passing each other 1 mm apart (only an edge × edge axis separates them)
    (tri((-1, 0, 0), (1, 0, 0), (0, 0, 1)), tri((0, -1, -1e-3), (0, 1, -1e-3), (0, 0, -1)), False),
    # the same, the edges crossing (1 mm of overlap along the planes' common line)
    (tri((-1, 0, 0), (1, 0, 0), (0, 0, 1)), tri((0, -1, 1e-3), (0, 1, 1e-3), (0, 0, -1)), True),
    # touching at one corner
    (tri((0, 0, 0), (1, 0, 0), (0, 1, 0)), tri((1, 0, 0), (2, 0, 1), (2, 1, 0)), True),
])
def test_triangle_test_known_answers_and_symmetry(a, b, meet):
    assert triangles_intersect(a, b).tolist() == [meet]
    assert triangles_intersect(b, a).tolist() == [meet]
    assert triangles_intersect(a.float(), b.float()).tolist() == [meet]


def test_hull_edges_measure_the_distances_scipys_hull_measures():
    g = torch.Generator().manual_seed(0)
    S, H = 32, 24
    points = torch.randn(S, H, 2, generator=g, dtype=torch.float64)
    points[:4, 3] = 0.5 * (points[:4, 0] + points[:4, 1])  # a point on a chord (sometimes a hull edge)
    mask = torch.rand(S, H, generator=g) > 0.2
    mask[:, :3] = True
    points = torch.where(mask[..., None], points, points[:, :1])  # padding repeats the first point
    queries = 3 * torch.randn(S, 50, 2, generator=g, dtype=torch.float64)
    polygons = [footprint(p[m].numpy()) for p, m in zip(points, mask)]
    K = max(len(p) for p in polygons)
    padded = torch.tensor(np.stack([np.concatenate([p, np.repeat(p[:1], K - len(p), 0)]) for p in polygons]))
    want = polygon_distance(queries, padded)
    end, valid = hull_edges(points, mask)
    got = segments_distance(queries, points, end, valid)
    assert (want > 0).float().mean() > 0.3 and (want == 0).any()  # inside and outside both met
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert valid.sum(1).tolist() == [len(p) for p in polygons]  # one edge from each hull vertex, none else


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_footprints_on_the_device_equal_scipys_on_real_assets(lib, dtype):
    ids, physical, mask, x = crowded(lib, 2, dtype=dtype, supports=0.2)
    g = SceneGuidance("refine", lib, ids, physical, mask, BOUNDS)
    t, R = poses_from_state(x, g._graph(x.device, x.dtype)["bounds"])
    world = g.meshes.pose(t, R)
    hull = g.meshes.hull_points(world)
    b_host, host = outside_distances(world, hull, g.meshes, g.supports)
    b_dev, dev = outside_distances(world, hull, g.meshes, g.supports, device=True)
    assert torch.equal(b_host, b_dev) and (host > 0).sum() > 5
    torch.testing.assert_close(dev, host, rtol=0, atol=1e-12 if dtype == torch.float64 else 1e-5)


def test_a_refine_step_is_the_same_on_either_path_and_the_device_footprints_read_nothing_back(lib):
    ids, physical, mask, x = crowded(lib, 0, supports=0.2)
    weights = {"collision": 1.5e-2, "gravity": 0.0, "relation": 1e-3, "terms": {"over": 0.05, "settle": 0.3,
                                                                                 "home": 0.01}}
    steps = {}
    for detect in ("host", "device"):
        g = SceneGuidance({"mode": "refine", "detect": detect, **weights}, lib, ids, physical, mask, BOUNDS)
        steps[detect] = g.step(x, at=(99, 100))
        assert g.stats["last_colliding_pairs"] > 100
    assert not torch.equal(steps["host"], x)
    torch.testing.assert_close(steps["device"], steps["host"], rtol=0, atol=1e-12)
    # relation, over and home on the device path read nothing back (the host path copies every supporter's hull out)
    config = {"mode": "refine", "detect": "device", "collision": 0.0, "gravity": 0.0, "relation": 1e-3,
              "terms": {"over": 0.05, "home": 0.01}}
    g = SceneGuidance(config, lib, ids, physical, mask, BOUNDS)
    g._graph(x.device, x.dtype)  # the support pairs, found once per sample
    with OperatorCounter() as counter:
        moved = g.step(x, at=(0, 100))
    assert counter.syncs == 0 and not torch.equal(moved, x)


def test_detect_is_a_setting_of_its_own_named_in_errors_and_resolved_per_device():
    assert GuidanceConfig().detect == "auto"
    assert GuidanceConfig.from_config({"mode": "refine", "detect": "device"}).settings()["detect"] == "device"
    assert "detect=device" in GuidanceConfig.from_config({"mode": "refine", "detect": "device"}).label
    with pytest.raises(ValueError, match="'detect' is 'gpu'"):
        GuidanceConfig.from_config({"mode": "refine", "detect": "gpu"})
    assert resolve_detect("auto", "cpu") == "host" and resolve_detect("auto", "cuda") == "device"
    assert resolve_detect("device", "cpu") == "device" and resolve_detect("host", "cuda") == "host"
