"""Read once per process (:mod:`spread.readonce`): one ``spread-sample`` run reads its checkpoint once (one load,
one sha256), each conditioning graph once and the asset library once; a second run in the same process (a
second sweep trial in a re-used trial process) reads none of them again and builds no second model; a file
changed on disk is read again.

The readers are wrapped by counting functions (monkeypatch) and the run is an in-process one (``workers=0``).
"""

from __future__ import annotations

import os
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from spread import readonce

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, sample_in_process, train_in_process


@pytest.fixture(autouse=True)
def fresh_tables():
    readonce.clear()
    yield
    readonce.clear()


# ---- the memo itself ------------------------------------------------------------------------------------------

def test_a_file_is_read_once_until_it_changes_on_disk(tmp_path):
    path = tmp_path / "x.txt"
    path.write_text("one")
    reads = []

    def load():
        reads.append(1)
        return path.read_text()

    assert readonce.memo("text", readonce.file_key(path), load) == "one"
    assert readonce.memo("text", readonce.file_key(path), load) == "one"
    assert len(reads) == 1
    path.write_text("second")  # another size (and mtime): another key
    assert readonce.memo("text", readonce.file_key(path), load) == "second"
    assert len(reads) == 2
    assert readonce.counts()["text"] == {"reads": 2, "hits": 1}


def test_a_failed_read_is_not_kept_and_is_tried_again(tmp_path):
    calls = []

    def load():
        calls.append(1)
        raise ValueError("damaged")

    for _ in range(2):
        with pytest.raises(ValueError, match="damaged"):
            readonce.memo("bad", "k", load)
    assert len(calls) == 2


def test_tables_are_bounded_least_recently_used_first(monkeypatch):
    monkeypatch.setitem(readonce.LIMITS, "small", 2)
    for k in ("a", "b", "a", "c"):  # "a" used again, so "b" is the least recently used when "c" comes
        readonce.memo("small", k, lambda k=k: k.upper())
    loads = []
    readonce.memo("small", "a", lambda: loads.append("a"))
    readonce.memo("small", "b", lambda: loads.append("b") or "B")
    assert loads == ["b"]


def test_the_environment_switch_turns_the_tables_off(tmp_path, monkeypatch):
    monkeypatch.setenv(readonce.ENV, "0")
    calls = []
    for _ in range(3):
        readonce.memo("off", "k", lambda: calls.append(1))
    assert len(calls) == 3


def test_sha256_is_the_files_and_is_computed_once(tmp_path, monkeypatch):
    import hashlib

    import spread.io

    path = tmp_path / "w.bin"
    path.write_bytes(b"weights" * 1000)
    hashed = Counter()
    real = spread.io.file_sha256
    monkeypatch.setattr(spread.io, "file_sha256", lambda *p: hashed.update([str(p[0])]) or real(*p))
    from spread.runtime.fingerprint import file_digest

    want = hashlib.sha256(path.read_bytes()).hexdigest()
    assert readonce.file_sha256(path) == want and file_digest(path) == want and readonce.file_sha256(str(path)) == want
    assert sum(hashed.values()) == 1, "the sampling run's hash and the point fingerprint's are one computation"
    assert file_digest(tmp_path / "none") == f"missing:{tmp_path / 'none'}"


def test_a_scene_read_against_a_library_is_kept_and_its_errors_are_not(dataset, tmp_path):
    from spread.scene import SceneFormatError

    data = dataset
    library = readonce.asset_library(data / "assets")
    assert readonce.asset_library(data / "assets") is library
    path = sorted((data / "train").glob("*.npz"))[0]
    first = readonce.scene(path, library)
    assert readonce.scene(path, library) is first
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    for _ in range(2):
        with pytest.raises(SceneFormatError, match="bad.npz"):
            readonce.scene(bad, library)
    assert readonce.counts()["scene"]["hits"] == 1


# ---- one spread-sample run -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("rodata"), rooms=12)


@pytest.fixture(scope="module")
def ckpt(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rorun") / "run"
    train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=2",
                     *SMALL_MODEL, *FAST_TRAIN)
    return out / "checkpoints" / "last.ckpt"


@pytest.fixture
def readers(monkeypatch):
    """Counting wrappers around every reader a sampling run could use: checkpoint loads, sha256 of files,
    scene reads (by path), asset-library loads and model builds."""
    import spread.methods
    import spread.io
    import spread.safe_load
    import spread.scene
    from spread.assets.library import AssetLibrary

    counts = {"ckpt": Counter(), "sha256": Counter(), "scene": Counter(), "library": Counter(), "model": Counter()}

    def counting(table, real, key=lambda *a, **k: str(Path(a[0]).resolve())):
        def wrapper(*a, **k):
            table[key(*a, **k)] += 1
            return real(*a, **k)
        return wrapper

    monkeypatch.setattr(spread.safe_load, "load_checkpoint", counting(counts["ckpt"], spread.safe_load.load_checkpoint))
    monkeypatch.setattr(spread.io, "file_sha256", counting(counts["sha256"], spread.io.file_sha256))
    monkeypatch.setattr(spread.scene, "read_scene", counting(counts["scene"], spread.scene.read_scene))
    real_load = AssetLibrary.load.__func__
    monkeypatch.setattr(AssetLibrary, "load", classmethod(
        lambda cls, root: counts["library"].update([str(Path(root).resolve())]) or real_load(cls, root)))
    monkeypatch.setattr(spread.methods, "module_from_checkpoint",
                        counting(counts["model"], spread.methods.module_from_checkpoint, key=lambda *a, **k: "model"))
    return counts


def run_args(dataset, ckpt, out, *more):
    return (f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=2", "figures=1",
            "figure_kinds=[card]", *more)


def test_one_in_process_run_reads_checkpoint_graphs_and_library_once(dataset, ckpt, tmp_path, readers):
    result = sample_in_process(*run_args(dataset, ckpt, tmp_path / "one"))
    graphs = sorted(str(p.resolve()) for p in (dataset / "test").glob("*.npz"))
    assert result.manifest["runner"]["mode"] == "in-process" and len(result.written) == len(graphs)
    assert result.manifest["renders"] and result.manifest["figures"], "the renders read the graphs too"
    assert dict(readers["ckpt"]) == {str(ckpt.resolve()): 1}, "one load: the check, the hyperparameters, the model"
    hashed = dict(readers["sha256"])  # the checkpoint, and the data content the fingerprint holds: each once
    assert hashed[str(ckpt.resolve())] == 1 and set(hashed.values()) == {1}
    assert set(graphs) <= set(hashed), "the split's content is part of the sampling fingerprint"
    assert dict(readers["library"]) == {str((dataset / "assets").resolve()): 1}
    assert {p: readers["scene"][p] for p in graphs} == {p: 1 for p in graphs}, "each graph read once"
    assert readers["model"]["model"] == 1
    assert result.manifest["fingerprint"]["ckpt_sha256"] == readonce.file_sha256(ckpt)


def test_a_second_run_in_the_same_process_reads_nothing_again_and_samples_the_same(dataset, ckpt, tmp_path, readers):
    first = sample_in_process(*run_args(dataset, ckpt, tmp_path / "a"))
    before = {k: Counter(v) for k, v in readers.items()}
    second = sample_in_process(*run_args(dataset, ckpt, tmp_path / "b"))
    graphs = {str(p.resolve()) for p in (dataset / "test").glob("*.npz")}
    for kind in ("ckpt", "sha256", "library", "model"):
        assert readers[kind] == before[kind], f"{kind} read again by the second run"
    assert not any(readers["scene"][p] - before["scene"][p] for p in graphs), "a graph read again"
    for a, b in zip(first.files, second.files):
        assert a.read_bytes() == b.read_bytes(), "a warm run writes the same scenes as a cold one"


def test_a_checkpoint_rewritten_on_disk_is_read_and_built_again(dataset, ckpt, tmp_path, readers):
    import shutil

    copy = tmp_path / "model.ckpt"
    shutil.copy(ckpt, copy)
    sample_in_process(*run_args(dataset, copy, tmp_path / "a"), "renders=0", "figures=0")
    os.utime(copy, ns=(time.time_ns(), time.time_ns() + 10 ** 9))  # touched: another mtime, so another file
    sample_in_process(*run_args(dataset, copy, tmp_path / "b"), "renders=0", "figures=0")
    assert readers["ckpt"][str(copy.resolve())] == 2 and readers["sha256"][str(copy.resolve())] == 2
    assert readers["model"]["model"] == 2


def test_ray_workers_get_the_typed_sampling_config(dataset, ckpt, tmp_path):
    """The config travels to the worker as the dataclass it is: a worker built from it samples exactly what
    the in-process run wrote (same sampler, seed, guidance, EMA and graph scale)."""
    import pickle

    from spread.sampling.plan import plan_batches
    from spread.sampling.run import SamplingConfig, list_graphs
    from spread.sampling.worker import SampleWorker

    from helpers import FAST_SAMPLE, compose, to_object

    cfg = to_object(compose("sample", *FAST_SAMPLE, *run_args(dataset, ckpt, tmp_path / "typed"), "renders=0",
                            "figures=0", "guidance=refine", "guidance.iterations=2"))
    assert isinstance(cfg, SamplingConfig)
    shipped = pickle.loads(pickle.dumps(cfg))  # what Ray does with an actor's arguments
    assert shipped.guidance == cfg.guidance and shipped.sampler == cfg.sampler
    result = sample_in_process(*run_args(dataset, ckpt, tmp_path / "typed"), "renders=0", "figures=0",
                               "guidance=refine", "guidance.iterations=2")
    worker = SampleWorker(shipped, tmp_path / "again")
    assert worker.pipeline.guidance == cfg.guidance and worker.pipeline.sampler == cfg.sampler
    batch = plan_batches(list_graphs(dataset, "test"), 1, cfg.batch_size, cfg.seed)[0]
    for scene in worker.sample(batch):
        from spread.scene import read_scene

        written = read_scene(result.out_dir / "scenes" / f"{scene.scene_id}.npz")
        np.testing.assert_array_equal(scene.translation, written.translation)
        assert str(scene.extras["source"]) == str(written.extras["source"])


def test_a_ray_sampling_actor_reads_checkpoint_library_and_each_graph_once(dataset, ckpt, tmp_path):
    """workers ≥ 1: the actor gets the SamplingConfig as it is and, over all the run's batches, loads the
    checkpoint once, builds one model, loads the library once and reads each graph of the split once."""
    import ray

    from spread.configs import to_object
    from spread.sampling.plan import plan_batches
    from spread.sampling.run import list_graphs
    from spread.sampling.worker import SampleWorker

    from helpers import FAST_SAMPLE, compose

    cfg = to_object(compose("sample", *FAST_SAMPLE, *run_args(dataset, ckpt, tmp_path / "ray"), "batch_size=1",
                            "samples_per_graph=2"))
    graphs = list_graphs(dataset, "test")
    batches = plan_batches(graphs, cfg.samples_per_graph, cfg.batch_size, cfg.seed)
    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)  # never a cluster another test started
    try:
        actor = ray.remote(SampleWorker).options(num_cpus=1).remote(cfg, tmp_path / "ray" / "scenes")
        results = ray.get([actor.run.remote(b) for b in batches])
        reads = ray.get(actor.reads.remote())
    finally:
        ray.shutdown()
    assert sum(len(r["written"]) for r in results) == 2 * len(graphs)
    assert reads["checkpoint"]["reads"] == 1 and reads["model"]["reads"] == 1 and reads["library"]["reads"] == 1
    assert reads["scene"]["reads"] == len(graphs), "each graph of the split read once (then kept)"
    assert reads["scene"]["hits"] >= len(batches), "every batch's graph came from the table"


class ColourStats:
    """A stand-in FID backbone: per image, the mean and sd of each colour channel."""

    feature_dim = 6

    def __call__(self, images):
        x = np.asarray(images, np.float64).reshape(len(images), -1, 3)
        return np.concatenate([x.mean(1), x.std(1)], 1)


def test_reference_fid_features_are_kept_per_process_until_a_reference_file_changes(dataset, monkeypatch):
    """The next sweep trial's evaluation in a warm worker renders the reference set again only when one of
    its files changed."""
    import spread.metrics
    from spread.evaluation.protocol import FIDConfig
    from spread.evaluation.work import reference_fid_state

    renders = Counter()
    real = spread.metrics.fid_render
    monkeypatch.setattr(spread.metrics, "fid_render", lambda scene, lib: renders.update([scene.scene_id]) or real(scene, lib))
    paths = [str(p) for p in sorted((dataset / "test").glob("*.npz"))]
    fid = FIDConfig(extractor=f"{__name__}:ColourStats", feature_model="colour_stats")
    first = reference_fid_state(paths, str(dataset / "assets"), fid, 0)
    again = reference_fid_state(paths, str(dataset / "assets"), fid, 0)
    assert again is first and sum(renders.values()) == len(paths), "the second evaluation rendered nothing"
    other_seed = reference_fid_state(paths, str(dataset / "assets"), fid, 1)
    assert other_seed is not first
    os.utime(paths[0], ns=(time.time_ns(), time.time_ns() + 10 ** 9))  # a reference file touched
    reference_fid_state(paths, str(dataset / "assets"), fid, 0)
    assert sum(renders.values()) == 3 * len(paths)


@pytest.mark.slow
def test_sweep_trials_in_one_trial_process_load_the_model_once(dataset, ckpt, tmp_path):
    """spread-sweep, two points one after another: both trials run in one re-used Ray Tune trial process, and
    the second one loads no checkpoint, builds no model and reads no graph (its sampling.json counts)."""
    import json

    from spread.commands.in_process import InProcessCommands
    from spread.experiments.sweep import parse_arguments, run_sweep

    out = tmp_path / "sweep"
    plan = parse_arguments([f"ckpt={ckpt}", f"data.root={dataset}", "guidance=refine", "guidance.collision=0.0,0.0075",
                            "guidance.iterations=2", "sampler.steps=4", "batch_size=2", "renders=0", "logger=none",
                            "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false", "max_concurrent=1",
                            "num_cpus=2", f"out_dir={out}"])
    result = run_sweep(plan, InProcessCommands())
    assert len(result.rows) == 2 and all(r["status"] == "ok" for r in result.rows)
    assert len({r["trial_pid"] for r in result.rows}) == 1, "the trial process is re-used"
    manifests = sorted((json.loads(p.read_text()) for p in out.glob("points/*/sampling.json")),
                       key=lambda m: m["process_reads"]["scene"]["hits"])
    first, second = (m["process_reads"] for m in manifests)
    graphs = manifests[0]["graphs"]
    for kind in ("checkpoint", "model", "library", "dataset"):
        assert first[kind]["reads"] == second[kind]["reads"] == 1, kind
    assert first["scene"]["reads"] == second["scene"]["reads"] == graphs
    assert second["scene"]["hits"] > first["scene"]["hits"]
