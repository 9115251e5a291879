"""Data: 6D rotations, normalisation stats, the dataset, padding/collate, and the datamodule."""

import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from spread.assets.assemble import box_asset, library_from_specs
from spread.data import (
    INDEX_PAD, PHYSICAL_PAD, SPATIAL_PAD, SceneDataset, StatsError, collate_scenes, compute_stats,
    denormalize_translation, load_stats, matrix_to_rot6d, normalize_translation, rot6d_to_matrix, save_stats,
)
from spread.scene import write_scene

from helpers import scene_of

M = 64  # points per object in these tests
CATEGORIES = ["mug", "chair", "dining_table", "lamp"]  # manifest order, deliberately not sorted


def _yaw(a):
    return Rotation.from_rotvec([0.0, a, 0.0]).as_matrix()


def _scene(lib, rng, scene_id):
    """A table with 0–2 mugs on it and 1–2 chairs on the floor; graphs from the posed boxes."""
    tx, tz = rng.uniform(-1.5, 1.5, 2)
    ids, t, R = ["table"], [[tx, 0.375, tz]], [_yaw(rng.uniform(0, np.pi))]
    for _ in range(rng.integers(0, 3)):
        ids.append("mug"), t.append([tx + rng.uniform(-0.3, 0.3), 0.80, tz + rng.uniform(-0.15, 0.15)])
        R.append(_yaw(rng.uniform(0, 2 * np.pi)))
    for _ in range(rng.integers(1, 3)):
        ids.append("chair"), t.append([rng.uniform(-2.5, 2.5), 0.45, rng.uniform(-2.5, 2.5)])
        R.append(_yaw(rng.uniform(0, 2 * np.pi)))
    physical = np.zeros((len(ids),) * 2, np.int8)
    physical[0, [k for k, a in enumerate(ids) if a == "mug"]] = 1
    return scene_of(ids, t, R, library=lib, posed_codes=True, physical=physical,
                    room=np.array([[-3, 0, -3], [3, 3, 3]]), scene_id=scene_id)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset")
    lib = library_from_specs(root / "assets", [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("mug", (0.08, 0.1, 0.08), category="mug"),
        box_asset("chair", (0.45, 0.9, 0.45), category="chair", role="furniture"),
    ])
    rng = np.random.default_rng(0)
    scenes = {split: [_scene(lib, rng, f"{split}_{k}") for k in range(n)]
              for split, n in (("train", 6), ("val", 2), ("test", 3))}
    for split, items in scenes.items():
        for s in items:
            write_scene(s, root / split / f"{s.scene_id}.npz")
    save_stats(root / "stats.json", compute_stats(scenes["train"]))
    (root / "manifest.json").write_text(json.dumps({"categories": CATEGORIES}))
    return root


# ---- rotations -------------------------------------------------------------------------------------

def test_rot6d_round_trip_numpy_and_torch_batched():
    R = Rotation.random(4 * 5, random_state=0).as_matrix().reshape(4, 5, 3, 3)
    x = matrix_to_rot6d(R)
    assert x.shape == (4, 5, 6)
    assert np.allclose(x[..., :3], R[..., :, 0]) and np.allclose(x[..., 3:], R[..., :, 1])
    assert np.allclose(rot6d_to_matrix(x), R, atol=1e-6)
    Rt = torch.from_numpy(R)
    xt = matrix_to_rot6d(Rt)
    assert torch.allclose(xt, torch.from_numpy(x))
    assert torch.allclose(rot6d_to_matrix(xt), Rt, atol=1e-6)
    assert rot6d_to_matrix(xt.float()).dtype == torch.float32


def test_gram_schmidt_of_perturbed_input_is_a_rotation():
    rng = np.random.default_rng(1)
    x = matrix_to_rot6d(Rotation.random(100, random_state=1).as_matrix()) + rng.normal(0, 0.3, (100, 6))
    for R in (rot6d_to_matrix(x), rot6d_to_matrix(torch.from_numpy(x)).numpy()):
        assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-6)
        assert np.allclose(np.linalg.det(R), 1.0, atol=1e-6)
        assert np.allclose(R[:, :, 0], x[:, :3] / np.linalg.norm(x[:, :3], axis=1, keepdims=True))


# ---- stats -----------------------------------------------------------------------------------------

def test_normalise_round_trip_and_clipping(root):
    stats = load_stats(root / "stats.json")
    lo, hi = np.array(stats["bounds_translations"][:3]), np.array(stats["bounds_translations"][3:])
    assert stats["num_scenes"] == 6 and sum(stats["object_count_histogram"].values()) == 6
    t = np.random.default_rng(2).uniform(lo, hi, (7, 3)).astype(np.float32)
    x = normalize_translation(t, stats)
    assert x.dtype == np.float32 and (np.abs(x) <= 1 + 1e-6).all()
    assert np.allclose(denormalize_translation(x, stats), t, atol=1e-5)
    assert np.allclose(normalize_translation(np.stack([lo, hi]), stats), [[-1] * 3, [1] * 3])
    assert np.allclose(normalize_translation(hi + 5.0, stats), 1.0), "outside the bounds is clipped"
    tt = torch.from_numpy(t)
    assert torch.allclose(normalize_translation(tt, stats), torch.from_numpy(x), atol=1e-6)
    assert torch.allclose(denormalize_translation(normalize_translation(tt, stats), stats), tt, atol=1e-5)


def test_load_stats_errors_name_file_and_key(tmp_path):
    with pytest.raises(StatsError, match="missing.json"):
        load_stats(tmp_path / "missing.json")
    bad = tmp_path / "stats.json"
    bad.write_text(json.dumps({"bounds_sizes": [0, 0, 0, 1, 1, 1]}))
    with pytest.raises(StatsError, match=r"stats\.json: key 'bounds_translations' is missing"):
        load_stats(bad)
    bad.write_text(json.dumps({"bounds_translations": [0, 0, 0, 1, 0, 1]}))
    with pytest.raises(StatsError, match="max ≤ min"):
        load_stats(bad)


# ---- dataset ---------------------------------------------------------------------------------------

def test_item_encodes_the_scene(root):
    ds = SceneDataset(root, "train", num_points=M)
    scene = ds.read(0)
    item = ds[0]
    n = scene.num_objects
    assert item["scene_id"] == scene.scene_id and item["x"].shape == (n, 9)
    assert np.allclose(denormalize_translation(item["x"][:, :3].numpy(), ds.stats), scene.translation, atol=1e-5)
    assert np.allclose(rot6d_to_matrix(item["x"][:, 3:].numpy()), scene.rotation, atol=1e-5)
    assert item["spatial"].dtype == torch.long and torch.equal(item["spatial"], torch.from_numpy(scene.spatial).long())
    assert torch.equal(item["physical"], torch.from_numpy(scene.physical).long())
    assert ds.categories == CATEGORIES, "the manifest's category list wins over the library's"
    assert [CATEGORIES[i] for i in item["category_index"]] == list(scene.category)
    assert [ds.asset_ids[i] for i in item["asset_index"]] == list(scene.asset_id)
    assert ds.asset_ids == ["chair", "mug", "table"]
    assert item["points"].shape == item["normals"].shape == (n, M, 3)
    assert torch.allclose(item["normals"].norm(dim=-1), torch.ones(n, M), atol=1e-4)


def test_points_are_fixed_per_asset_and_seed(root):
    ds = SceneDataset(root, "train", num_points=M, seed=0)
    table_points = [it["points"][0] for it in (ds[k] for k in range(len(ds)))]
    assert all(torch.equal(p, table_points[0]) for p in table_points), "every scene's table: same points"
    fresh = SceneDataset(root, "val", num_points=M, seed=0)[0]["points"][0]
    assert torch.equal(fresh, table_points[0]), "another dataset instance / split: same points"
    other = SceneDataset(root, "train", num_points=M, seed=1)[0]["points"][0]
    assert not torch.equal(other, table_points[0])
    pts, _ = ds.library.surface_points("table")
    assert (table_points[0].numpy()[:, None, :] == pts[None]).all(-1).any(1).all(), "a subset of the cache"


def test_morton_codes_interleave_the_three_axes_bits_and_order_points_by_them():
    from spread.data.points import morton_order

    # in a unit box: x alone → code 4681 (bits 0, 3, 6, 9, 12), y alone → 9362, z alone → 18724, the origin → 0
    corners = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0], [1, 1, 1]])
    assert morton_order(corners).tolist() == [3, 0, 1, 2, 4]
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(2, 3, 200, 3, generator=g)
    assert torch.equal(morton_order(pts[1, 2]), morton_order(pts)[1, 2]), "any leading shape"
    assert torch.equal(morton_order(pts * 4.0 - 7.0), morton_order(pts)), "the object's own box: scale-free"
    many = torch.rand(2048, 3, generator=g) * torch.tensor([2.0, 0.1, 0.7])
    tile_extent = lambda p: (p.view(-1, 64, 3).amax(1) - p.view(-1, 64, 3).amin(1)).norm(dim=-1).mean()
    assert tile_extent(many[morton_order(many)]) < 0.6 * tile_extent(many), "tiles of 64 points: compact boxes"


def test_an_assets_points_come_in_morton_order_the_same_subset_as_drawn(root):
    from spread.data.points import asset_points, morton_order, point_indices

    ds = SceneDataset(root, "train", num_points=M, seed=0)
    pts, _ = ds.library.surface_points("chair")
    points, normals = asset_points(ds.library, "chair", M, seed=0)
    drawn = pts[point_indices("chair", M, len(pts), 0)]
    assert sorted(map(tuple, points.tolist())) == sorted(map(tuple, drawn.tolist())), "the same draw, reordered"
    assert torch.equal(morton_order(torch.from_numpy(points)), torch.arange(M)), "already in Morton order"
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5), "normals follow their points"


def test_bad_scene_file_fails_with_its_name(root, tmp_path):
    import shutil

    for name in ("assets", "stats.json"):
        (shutil.copytree if name == "assets" else shutil.copy)(root / name, tmp_path / name)
    (tmp_path / "train").mkdir()
    good = np.load(root / "train" / "train_0.npz")
    arrays = {k: good[k] for k in good.files}
    arrays["translation"] = arrays["translation"].copy()
    arrays["translation"][0, 0] = np.nan
    np.savez(tmp_path / "train" / "broken.npz", **arrays)
    with pytest.raises(ValueError, match=r"train: none of its 1 scene files is usable .*broken\.npz: key 'translation'"):
        SceneDataset(tmp_path, "train", num_points=M)
    shutil.copy(root / "train" / "train_0.npz", tmp_path / "train" / "train_0.npz")
    ds = SceneDataset(tmp_path, "train", num_points=M)  # the bad file is skipped and named, the good one kept
    assert len(ds) == 1 and ds.files[0].name == "train_0.npz"
    assert [s["file"] for s in ds.skipped] == [str(tmp_path / "train" / "broken.npz")]
    assert "key 'translation'" in ds.skipped[0]["error"]


# ---- collate ---------------------------------------------------------------------------------------

def test_collate_pads_and_matches_unbatched(root):
    ds = SceneDataset(root, "train", num_points=M)
    items = [ds[k] for k in range(len(ds))]
    sizes = [it["x"].shape[0] for it in items]
    assert len(set(sizes)) > 1, "the fixture must mix scene sizes"
    batch = collate_scenes(items)
    B, N = len(items), max(sizes)
    assert batch["mask"].shape == (B, N) and batch["mask"].dtype == torch.bool
    assert batch["mask"].sum(1).tolist() == sizes == batch["num_objects"].tolist()
    assert batch["scene_id"] == [it["scene_id"] for it in items]
    for b, (it, n) in enumerate(zip(items, sizes)):
        for key in ("x", "asset_index", "category_index", "points", "normals"):
            assert torch.equal(batch[key][b, :n], it[key])
        for key in ("spatial", "physical"):
            assert torch.equal(batch[key][b, :n, :n], it[key])
        pad = ~batch["mask"][b]
        assert (batch["x"][b, pad] == 0).all() and (batch["points"][b, pad] == 0).all()
        assert (batch["asset_index"][b, pad] == INDEX_PAD).all() and (batch["category_index"][b, pad] == INDEX_PAD).all()
        assert (batch["spatial"][b, n:, :] == SPATIAL_PAD).all() and (batch["spatial"][b, :, n:] == SPATIAL_PAD).all()
        assert (batch["physical"][b, n:, :] == PHYSICAL_PAD).all() and (batch["physical"][b, :, n:] == PHYSICAL_PAD).all()
    assert (SPATIAL_PAD, PHYSICAL_PAD, INDEX_PAD) == (7, 3, -1)



def test_a_batch_padded_to_more_objects_equals_one_collated_beside_a_larger_scene(root):
    """``pad_objects(collate(items), n)`` is what collating the items beside a scene of n objects gives them (its
    row dropped): every per-object key padded with its code, the mask False there; per-scene keys unchanged."""
    from spread.data.collate import pad_objects

    ds = SceneDataset(root, "train", num_points=M)
    items = [ds[k] for k in range(len(ds))]
    sizes = [int(it["x"].shape[0]) for it in items]
    big = max(range(len(items)), key=sizes.__getitem__)
    small = [it for k, it in enumerate(items) if k != big and sizes[k] < sizes[big]]
    assert small, "the fixture must mix scene sizes"
    batch = collate_scenes(small)
    padded = pad_objects(batch, sizes[big])
    reference = collate_scenes(small + [items[big]])
    assert padded["x"].shape[1] == sizes[big] > batch["x"].shape[1]
    assert sorted(padded) == sorted(reference)
    for key, value in reference.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(padded[key], value[:len(small)]), key
            assert padded[key].dtype == value.dtype, key
        else:
            assert padded[key] == value[:len(small)], key
    assert pad_objects(batch, batch["x"].shape[1]) is batch
    with pytest.raises(ValueError, match=f"cannot pad a batch of {batch['x'].shape[1]} objects to 1"):
        pad_objects(batch, 1)
    with pytest.raises(ValueError, match="not a collated batch"):
        pad_objects({"points": batch["points"]}, 9)


# ---- datamodule ------------------------------------------------------------------------------------

def _same_batches(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x["scene_id"] == y["scene_id"]
        for key in ("x", "mask", "spatial", "physical", "points", "asset_index"):
            assert torch.equal(x[key], y[key]), key


def test_dataloader_workers_match_single_process(root):
    from spread.data import SceneDataModule

    loaders = []
    for workers in (0, 2):
        dm = SceneDataModule(root, batch_size=4, num_workers=workers, num_points=M, seed=3)
        dm.setup("fit")
        loaders.append([list(dm.train_dataloader()), list(dm.val_dataloader())])
    for split in range(2):
        _same_batches(loaders[0][split], loaders[1][split])
    order = [sid for b in loaders[0][0] for sid in b["scene_id"]]
    assert sorted(order) == [f"train_{k}" for k in range(6)] and order != sorted(order), "train is shuffled"
    dm = SceneDataModule(root, batch_size=2, num_points=M, seed=3)
    again = [sid for b in dm.train_dataloader() for sid in b["scene_id"]]
    assert again == order, "the seeded generator fixes the order"
    assert len(list(dm.test_dataloader())) == 2


def test_unset_loader_workers_are_chosen_by_the_trainers_device_and_give_the_same_batches(root, caplog):
    """``data.num_workers=null`` (the config's default): none with a CPU trainer; beside a GPU up to 4 a training
    process, one CPU of its share left to it, kept across epochs — the batches are those of the loop's own loading.
    An explicit count is left alone (0 beside a GPU: a warning)."""
    from spread.configs import compose
    from spread.data import SceneDataModule
    from spread.data.datamodule import loader_workers
    from spread.training.fit import feed_the_device

    assert compose("train", []).data.num_workers is None and compose("train", []).data.persistent_workers is None
    assert [loader_workers(1, 16), loader_workers(8, 16), loader_workers(8, 64), loader_workers(1, 2),
            loader_workers(1, 1)] == [4, 1, 4, 1, 0]

    def trainer(kind: str, devices: int = 1):
        return type("Trainer", (), {"accelerator": type(kind, (), {})(), "num_devices": devices})()

    auto = SceneDataModule(root, batch_size=4, num_workers=None, persistent_workers=None, num_points=M, seed=3)
    feed_the_device(trainer("CPUAccelerator"), auto)
    assert auto.num_workers == 0 and not auto.pin_memory and not auto.persistent_workers
    auto.setup("fit")
    inline = [list(auto.train_dataloader()), list(auto.val_dataloader())]
    feed_the_device(trainer("CUDAAccelerator"), auto)
    assert auto.pin_memory and auto.num_workers == loader_workers(1) and auto.hparams["num_workers"] == auto.num_workers
    assert auto.persistent_workers == (auto.num_workers > 0)
    auto.use_workers(2)  # what a GPU machine's CPUs give (this one may have fewer): the batches are the same
    loaded = [list(auto.train_dataloader()), list(auto.val_dataloader())]
    assert auto.train_dataloader().num_workers == 2 and auto.train_dataloader().persistent_workers
    for split in range(2):
        _same_batches(inline[split], loaded[split])
    kept = SceneDataModule(root, num_workers=None, persistent_workers=False, num_points=M)
    feed_the_device(trainer("CUDAAccelerator", devices=8), kept)
    assert kept.num_workers == loader_workers(8) and not kept.persistent_workers
    explicit = SceneDataModule(root, num_workers=0, num_points=M)
    with caplog.at_level("WARNING"):
        feed_the_device(trainer("CUDAAccelerator"), explicit)
    assert explicit.num_workers == 0 and "data.num_workers=0" in caplog.text
    with pytest.raises(ValueError, match="^data.num_workers=-1: expected a whole number ≥ 0, or null for workers chosen"):
        SceneDataModule(root, num_workers=-1)


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_unset_loader_workers_in_a_ray_worker_follow_the_cpus_ray_gave_it():
    """A Ray Train worker, a sweep's trial or an ablation's training task sees the whole node's CPUs: its loaders take
    what Ray reserved for it, one left to the training (the driver, not a worker, keeps its own count)."""
    import ray

    from spread.data.datamodule import loader_workers, ray_cpus

    ray.init(address="local", num_cpus=3, include_dashboard=False, log_to_driver=False)  # never another test's cluster
    try:
        assert ray_cpus() is None  # the driver

        @ray.remote
        def workers() -> int:
            return loader_workers()

        assert ray.get([workers.options(num_cpus=n).remote() for n in (1, 2, 3)]) == [0, 1, 2]
    finally:
        ray.shutdown()


def test_size_buckets_batch_rooms_of_similar_object_count_and_keep_a_resumable_order():
    from spread.data.order import EpochOrder

    sizes = [3 + (7 * i) % 40 for i in range(64)]  # object counts 3..42, mixed
    plain = EpochOrder(64, seed=5)
    bucketed = EpochOrder(64, seed=5, sizes=sizes, batch_size=8, window=4)
    order = list(bucketed)
    assert sorted(order) == list(range(64)) and list(bucketed) != order  # every room once; epochs differ
    batches = [order[k:k + 8] for k in range(0, 64, 8)]
    # a window of 4 batches is sorted before it is cut: in every batch the counts are consecutive in that window
    spread_of = [max(sizes[i] for i in b) - min(sizes[i] for i in b) for b in batches]
    padded = lambda o: sum(8 * max(sizes[i] for i in o[k:k + 8]) for k in range(0, 64, 8))
    first_plain = list(plain)
    assert padded(order) < 0.8 * padded(first_plain)  # far less padding than the shuffled order
    assert max(spread_of) < max(sizes) - min(sizes)
    # the same (seed, epoch) gives the same order, and a resume at a batch boundary continues it
    assert list(EpochOrder(64, seed=5, sizes=sizes, batch_size=8, window=4)) == order
    resumed = EpochOrder(64, seed=5, position=lambda: (0, 16), sizes=lambda: sizes, batch_size=8, window=4)
    assert list(resumed) == order[16:]
    with pytest.raises(ValueError, match="bucket_batches"):
        EpochOrder(64, seed=5, sizes=sizes, batch_size=8, window=-1)
    with pytest.raises(ValueError, match="3 sizes for 64 items"):
        list(EpochOrder(64, seed=5, sizes=[1, 2, 3], batch_size=8, window=4))


def test_the_train_loader_with_size_buckets_holds_every_room_once_per_epoch(root):
    from spread.data import SceneDataModule

    dm = SceneDataModule(root, batch_size=2, num_points=M, seed=3, bucket_batches=3)
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    counts = dm.dataset("train").sizes()
    assert sorted(sid for b in batches for sid in b["scene_id"]) == [f"train_{k}" for k in range(6)]
    # one window holds all 3 batches: they are the sorted counts cut in pairs, in a shuffled order
    ranked = sorted(counts)
    assert sorted(sorted(b["num_objects"].tolist()) for b in batches) == [ranked[0:2], ranked[2:4], ranked[4:6]]
    padded = sum(b["x"].shape[0] * b["x"].shape[1] for b in batches)
    plain = SceneDataModule(root, batch_size=2, num_points=M, seed=3)
    plain.setup("fit")
    assert padded <= sum(b["x"].shape[0] * b["x"].shape[1] for b in plain.train_dataloader())
    with pytest.raises(ValueError, match="data.bucket_batches"):
        SceneDataModule(root, bucket_batches=-2)


def test_dataset_pickles_without_its_library(root):
    ds = SceneDataset(root, "val", num_points=M)
    blob = pickle.dumps(ds)
    clone = pickle.loads(blob)
    assert clone._library is None and len(blob) < 20_000
    a, b = ds[1], clone[1]
    assert all(torch.equal(a[k], b[k]) for k in ("x", "points", "spatial"))


def test_import_pulls_no_heavy_optional_modules():
    code = ("import sys, spread.data; "
            "print(sorted(m for m in ('pybullet', 'ray', 'wandb', 'lightning') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# ---- the object limit of the training rooms (data.max_objects) -----------------------------------------------

def test_rooms_over_the_object_limit_are_skipped_and_named_and_the_others_kept(root):
    from spread.data.datamodule import SceneDataModule

    every = SceneDataset(root, "train", num_points=M)
    counts = dict(zip((f.name for f in every.files), every.sizes()))
    limit = sorted(counts.values())[len(counts) // 2]
    kept = SceneDataset(root, "train", num_points=M, max_objects=limit)
    assert {f.name for f in kept.files} == {n for n, c in counts.items() if c <= limit}
    over = {n for n, c in counts.items() if c > limit}
    assert over and {Path(s["file"]).name for s in kept.skipped} == over
    assert all(f"more than the object limit {limit} (data.max_objects)" in s["error"] for s in kept.skipped)
    dm = SceneDataModule(root, batch_size=2, num_points=M, max_objects=limit)
    dm.setup("fit")
    assert sorted(sid for b in dm.train_dataloader() for sid in b["scene_id"]) == sorted(
        n.removesuffix(".npz") for n, c in counts.items() if c <= limit)
    assert dm.hparams["max_objects"] == limit and max(dm.dataset("train").sizes()) <= limit
    with pytest.raises(ValueError, match=r"train: none of its 6 scene files is usable .*object limit 1 "):
        SceneDataset(root, "train", num_points=M, max_objects=1)


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "12"])
def test_an_object_limit_that_is_not_a_whole_number_of_at_least_one_is_refused_naming_data_max_objects(root, bad):
    from spread.data.datamodule import SceneDataModule

    with pytest.raises(ValueError, match=r"^data\.max_objects=.*: expected a whole number ≥ 1, or null for no limit$"):
        SceneDataModule(root, max_objects=bad)


@pytest.mark.parametrize("key, bad, least", [("batch_size", 3.274, 1), ("batch_size", 4.0, 1), ("batch_size", 0, 1),
                                             ("num_points", True, 1), ("seed", -1, 0), ("bucket_batches", 1.5, 0)])
def test_a_loader_count_that_is_not_a_whole_number_is_refused_by_key_never_truncated(root, key, bad, least):
    """``int(3.274)`` made a swept ``data.batch_size=interval(2,4)`` train batches of 3 under the name 3.274."""
    from spread.data.datamodule import SceneDataModule

    with pytest.raises(ValueError, match=rf"^data\.{key}={bad!r}: expected a whole number ≥ {least}"):
        SceneDataModule(root, **{key: bad})


def test_the_object_limit_at_its_default_leaves_training_identities_as_they_were_and_a_set_one_is_another():
    """``data.max_objects`` came after stages and sweep points were trained: at its default (null) a training
    identity does not spell it (they are re-used); a limit is another identity, and a resumed checkpoint trained
    before it (on every room) is refused under a limit."""
    from spread.experiments.stages import typed_training
    from spread.runtime.fingerprint import training_config_identity
    from spread.training.fit import resumed_changes

    plain = typed_training({"overrides": ["experiment=quick", "data.root=/d"]})
    assert "max_objects" not in plain["config"]["data"] and "seed" in plain["config"]["data"]
    limited = typed_training({"overrides": ["experiment=quick", "data.root=/d", "data.max_objects=30"]})
    assert limited["config"]["data"]["max_objects"] == 30 and limited != plain
    config = {"data": {"max_objects": None, "seed": 1}, "seed": 1}
    assert training_config_identity(config) == {"data": {"seed": 1}, "seed": 1} and config["data"]["max_objects"] is None

    class Held:  # a datamodule's hyperparameters as a checkpoint written before the limit holds them
        hparams = {"batch_size": 2, "seed": 0}

    before = {"datamodule_hyper_parameters": dict(Held.hparams)}
    Held.hparams = {"batch_size": 2, "seed": 0, "max_objects": None}
    assert resumed_changes(before, object(), Held) == []
    Held.hparams = {"batch_size": 2, "seed": 0, "max_objects": 12}
    assert resumed_changes(before, object(), Held) == ["data.max_objects: None -> 12"]


def test_a_val_split_the_object_limit_empties_is_no_refusal_for_a_trainer_that_does_not_validate(root):
    from types import SimpleNamespace

    from spread.data.datamodule import SceneDataModule

    val = SceneDataset(root, "val", num_points=M).sizes()
    train = SceneDataset(root, "train", num_points=M).sizes()
    limit = min(val) - 1
    assert any(c <= limit for c in train)  # the fixture's rooms (seed 0): train has smaller rooms than any of val's
    dm = SceneDataModule(root, batch_size=2, num_points=M, max_objects=limit)
    dm.trainer = SimpleNamespace(limit_val_batches=0, check_val_every_n_epoch=1)
    dm.setup("fit")  # the val split is never read
    assert "val" not in dm._datasets and len(dm.dataset("train")) == sum(c <= limit for c in train)
    validating = SceneDataModule(root, batch_size=2, num_points=M, max_objects=limit)
    validating.trainer = SimpleNamespace(limit_val_batches=1.0, check_val_every_n_epoch=1)
    with pytest.raises(ValueError, match=r"val: none of its 2 scene files is usable .*object limit"):
        validating.setup("fit")


def test_the_resume_position_counts_an_epochs_last_partial_accumulation_as_one_step(root):
    """``trainer.accumulate_grad_batches=3`` over 3 batches an epoch of 6 rooms at batch 2: 1 step an epoch; over
    5 batches (batch 1 ... limited): ⌈5/3⌉ = 2 steps. The position is (epoch, rooms of it trained) at each step
    (``global_step × 3`` batches ran past the epochs made, and training stalled on one batch, exit 0)."""
    from types import SimpleNamespace

    from spread.data.datamodule import SceneDataModule

    dm = SceneDataModule(root, batch_size=1, num_points=M)
    dm.trainer = SimpleNamespace(limit_train_batches=5, accumulate_grad_batches=3, global_step=0)
    positions = []
    for step in range(5):
        dm.trainer.global_step = step
        positions.append(dm.train_position())
    assert positions == [(0, 0), (0, 3), (1, 0), (1, 3), (2, 0)]
    dm.trainer = SimpleNamespace(limit_train_batches=1.0, accumulate_grad_batches=1, global_step=7)
    assert dm.train_position() == (1, 1)  # 6 batches an epoch: step 7 is the second of epoch 1


def test_batches_per_epoch_reads_limit_train_batches_as_lightning_does():
    """An int is a count of batches, 1 included (it was read as the whole epoch: with gradient accumulation each
    one-batch epoch then started further on, and most rooms were never trained); a float is a fraction."""
    from spread.data.order import batches_per_epoch

    assert [batches_per_epoch(7, 1, limit) for limit in (1, 3, 20, 1.0, 0.5)] == [1, 3, 7, 7, 3]


def test_stats_bounds_that_do_not_hold_the_training_rooms_are_named_with_the_room_and_axis(tmp_path, caplog):
    """A hand-edited ``bounds_translations`` of 5 cm trained silently on translations clipped to it (98.8 % of the
    coordinates); the statistics come from the training rooms, so theirs always fit and say nothing."""
    import logging

    from helpers import make_dataset

    from spread.data.dataset import SceneDataset

    data = make_dataset(tmp_path)
    with caplog.at_level(logging.WARNING, logger="spread.data"):
        SceneDataset(data, "train")
    assert "bounds_translations" not in caplog.text
    stats = json.loads((data / "stats.json").read_text())
    lo, hi = stats["bounds_translations"][:3], stats["bounds_translations"][3:]
    stats["bounds_translations"] = [*lo, hi[0] - 0.5, *hi[1:]]  # x's max half a metre short
    (data / "stats.json").write_text(json.dumps(stats))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="spread.data"):
        SceneDataset(data, "train")
        SceneDataset(data, "val")  # other splits are not what the bounds were computed from
    messages = [r.getMessage() for r in caplog.records if "bounds_translations" in r.getMessage()]
    assert len(messages) == 1, messages
    assert messages[0].startswith(f"{data / 'stats.json'}: key 'bounds_translations' does not hold the training rooms "
                                  f"(x = ") and f"outside its max {hi[0] - 0.5:g}): their translations are clipped" \
        in messages[0] and f"{data / 'train'}/" in messages[0]
