"""spread-train and spread-sample: configs compose, fast_dev_run, resume, DDP on CPU, sampling end to end
(scene-file validation, spread-evaluate), sampler swap by config, determinism and resume of sampling.

One small generated dataset (12 rooms of at most 8 objects: 7 train, 2 val, 3 test) and one checkpoint
of a shrunken tiny model (a few steps) serve the whole module; torch runs on one thread.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from spread.configs import conf_dir
from spread.scene import list_scene_files, read_scene

from helpers import (FAST_SAMPLE, FAST_TRAIN, QUIET, SMALL_MODEL, compose, make_dataset, run_script,
                     sample_in_process, train_in_process)

EXPERIMENTS = sorted(p.stem for p in (Path(conf_dir()) / "experiment").glob("*.yaml"))


# ---- fixtures ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = make_dataset(tmp_path_factory.mktemp("tsdata"))
    assert len(list_scene_files(out / "test")) == 3
    return out


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory) -> Path:
    """A run folder after 4 training steps (checkpoints/last.ckpt) and a frozen copy, model.ckpt."""
    out = tmp_path_factory.mktemp("tsrun") / "run"
    summary = train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null",
                               "trainer.max_steps=4", "trainer.check_val_every_n_epoch=1", *SMALL_MODEL, *FAST_TRAIN)
    assert summary["global_step"] == 4
    shutil.copy(out / "checkpoints" / "last.ckpt", out / "model.ckpt")
    return out


@pytest.fixture(scope="module")
def sampled(dataset, trained, tmp_path_factory) -> Path:
    """spread-sample through the console script with 2 Ray workers, 2 samples per graph."""
    out = tmp_path_factory.mktemp("tssample") / "ray"
    run_script("spread-sample", f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
               "samples_per_graph=2", "seed=3", *[a for a in FAST_SAMPLE if a != "workers=0"], "workers=2",
               "ray.num_cpus=2")
    return out


# ---- configs ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes_and_its_targets_resolve(experiment):
    from hydra.utils import get_class

    cfg = compose("train", f"experiment={experiment}", "data.root=/nowhere")
    assert cfg.experiment_name == experiment
    for node in (cfg.data, cfg.model, cfg.trainer, cfg.checkpoint):
        get_class(node._target_)
    assert cfg.data.num_points == cfg.model.config.num_points
    if "method" in cfg.model:  # a Table 1 baseline (spread.methods); tests/test_baselines.py covers them
        assert list(cfg.tags) == [cfg.model.method]
    else:
        assert cfg.model.variant in ("base", "geometry") and list(cfg.tags) == [cfg.model.variant]
    assert str(cfg.out_dir).startswith(f"runs/train/{experiment}/")


def test_model_groups_extend_model_config_and_compose():
    from spread.model import ModelConfig

    paper = compose("train", "model=paper").model.config
    assert dict(paper) == ModelConfig().to_dict()  # the paper's network is ModelConfig's defaults, one source
    tiny = dict(compose("train", "model=tiny").model.config)
    assert tiny["name"] == "tiny" and (tiny["dim"], tiny["depth"], tiny["num_points"]) == (128, 3, 256)
    assert tiny["cond_dim"] == paper.cond_dim  # what tiny.yaml does not name comes from the paper's base
    assert dict(compose("train", "model=tiny", "model.config.depth=4").model.config)["depth"] == 4
    assert compose("train", "experiment=paper_base").model.variant == "base"
    assert compose("train", "experiment=paper_geometry").model.config.name == "paper"
    quick = compose("train", "experiment=quick")
    assert quick.model.config.name == "tiny" and quick.trainer.max_time and quick.trainer.accelerator == "cpu"
    assert compose("train", "trainer=gpu").trainer.accelerator == "gpu"
    assert compose("train", "trainer=ddp").trainer.strategy == "ddp"
    assert compose("train").logger.name == "wandb" and compose("train").logger.project == "spread"
    assert [compose("train", f"logger={n}").logger.name for n in ("csv", "none")] == ["csv", "none"]


def test_quick_model_instantiates_from_config():
    from hydra.utils import instantiate

    from spread.model.module import SceneDiffusion

    model = instantiate(compose("train", "experiment=quick").model)
    assert isinstance(model, SceneDiffusion) and model.variant == "geometry" and model.config.name == "tiny"
    assert model.hparams.lr == 5e-4


@pytest.mark.parametrize("choice, kind, steps", [("ddpm", "ddpm", 1000), ("ddim50", "ddim", 50),
                                                 ("ddim100", "ddim", 100), ("dpmsolver20", "dpmsolver++", 20)])
def test_sampler_group(choice, kind, steps):
    from spread.configs import to_object
    from spread.model import Sampler
    from spread.sampling import SamplingConfig

    cfg = to_object(compose("sample", f"sampler={choice}", "ckpt=x", "data.root=y", "out_dir=z"))
    assert isinstance(cfg, SamplingConfig) and isinstance(cfg.sampler, Sampler)
    assert (cfg.sampler.kind, cfg.sampler.num_steps) == (kind, steps)
    ddpm_k = to_object(compose("sample", "sampler=ddpm", "sampler.steps=100", "ckpt=x", "data.root=y", "out_dir=z"))
    assert ddpm_k.sampler.num_steps == 100


# ---- training ---------------------------------------------------------------------------------------

def test_fast_dev_run_with_wandb_logger(dataset, tmp_path):
    out = tmp_path / "fdr"
    summary = train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.fast_dev_run=true",
                               "model.sample_every_n_epochs=1", "model.val_sampler=ddim-2", *SMALL_MODEL, *QUIET,
                               "logger=wandb")
    assert summary["global_step"] == 1 and json.loads((out / "metrics.json").read_text()) == summary
    assert {"train/loss", "val/loss", "val/grecall"} <= set(summary["metrics"])
    assert all(np.isfinite(v) for v in summary["metrics"].values())


@pytest.mark.filterwarnings("ignore:You're resuming from a checkpoint")
def test_training_resumes_step_optimizer_and_ema(dataset, trained):
    out = trained
    first = torch.load(out / "model.ckpt", map_location="cpu", weights_only=False)
    assert first["global_step"] == 4 and int(first["state_dict"]["ema.num_updates"]) == 4
    assert list(first["hyper_parameters"]["bounds"]) == json.loads((dataset / "stats.json").read_text())[
        "bounds_translations"]
    summary = train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null",
                               "trainer.max_steps=7", "ckpt_path=last", *SMALL_MODEL, *FAST_TRAIN)
    assert summary["resumed_from"] == str(out / "checkpoints" / "last.ckpt") and summary["global_step"] == 7
    resumed = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 7 and int(resumed["state_dict"]["ema.num_updates"]) == 7
    adam = resumed["optimizer_states"][0]["state"][0]
    assert int(adam["step"]) == 7, "AdamW moments continued from the checkpoint (a fresh optimizer would say 3)"
    first_adam = first["optimizer_states"][0]["state"][0]
    assert not torch.equal(adam["exp_avg"], first_adam["exp_avg"])
    assert len(list((out / "csv").glob("version_*/metrics.csv"))) == 2, "a resumed launch keeps the first's CSV"
    before = (out / "checkpoints" / "last.ckpt").read_bytes()
    again = train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null",
                             "trainer.max_steps=7", "ckpt_path=last", *SMALL_MODEL, *FAST_TRAIN)
    assert again["global_step"] == 7
    assert (out / "checkpoints" / "last.ckpt").read_bytes() == before, "no step taken: checkpoint untouched"


def test_ckpt_path_last_starts_fresh_without_a_checkpoint_and_rejects_missing_files(tmp_path):
    from spread.training.checkpoints import resolve_ckpt_path

    cfg = compose("train", "ckpt_path=last", f"paths.runs_dir={tmp_path}", "experiment_name=x")
    assert resolve_ckpt_path(cfg, tmp_path / "run") is None
    older = tmp_path / "train" / "x" / "a" / "checkpoints" / "last.ckpt"
    older.parent.mkdir(parents=True)
    older.write_bytes(b"")
    assert resolve_ckpt_path(cfg, tmp_path / "run") == older
    with pytest.raises(SystemExit, match="no such checkpoint"):
        resolve_ckpt_path(compose("train", f"ckpt_path={tmp_path / 'nope.ckpt'}"), tmp_path / "run")


def test_train_script_ddp_two_cpu_processes(dataset, tmp_path):
    """The console script under Lightning DDP: 2 processes, gloo, the run folder shared (~30 s)."""
    out = tmp_path / "ddp"
    run_script("spread-train", "experiment=quick", f"data.root={dataset}", f"out_dir={out}", "trainer=ddp",
               "trainer.accelerator=cpu", "trainer.devices=2", "trainer.max_time=null", "trainer.max_steps=3",
               "data.batch_size=2", *SMALL_MODEL, *QUIET, "logger=csv")
    summary = json.loads((out / "metrics.json").read_text())
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert summary["global_step"] == 3 and ckpt["global_step"] == 3
    assert int(ckpt["state_dict"]["ema.num_updates"]) == 3
    assert (out / ".hydra" / "config.yaml").exists()


# ---- sampling ---------------------------------------------------------------------------------------

def test_sample_plan_seeds_and_batches():
    from spread.sampling import Graph, plan_batches, sample_seed

    graphs = [Graph(f"g{i}", f"/x/g{i}.npz", n) for i, n in enumerate([5, 3, 9, 3, 7])]
    assert sample_seed(0, "g1", 0) == sample_seed(0, "g1", 0)
    assert len({sample_seed(s, g, k) for s in (0, 1) for g in ("g0", "g1") for k in (0, 1)}) == 8
    plan = plan_batches(graphs, samples_per_graph=2, batch_size=2, seed=0)
    assert [b.names() for b in plan[:3]] == [["g1_k0", "g3_k0"], ["g0_k0", "g4_k0"], ["g2_k0"]], "by size, per k"
    assert plan == plan_batches(graphs[::-1], 2, 2, 0), "input order does not matter"
    assert plan_batches(graphs, 3, 2, 0)[:len(plan)] == plan, "more samples per graph only add batches"
    assert len({b.seed for b in plan}) == len(plan)


def test_degenerate_sampled_rotations_are_repaired():
    from scipy.spatial.transform import Rotation

    from spread.data import rot6d_to_matrix
    from spread.sampling.pipeline import repair_rotations

    good = Rotation.random(3, random_state=0).as_matrix().astype(np.float32)
    clipped = rot6d_to_matrix(np.array([[1, -1, 1, -1, 1, -1], [1, 1, 1, 1, 1, 1]], np.float32))  # parallel columns
    fixed, count = repair_rotations(np.concatenate([good, clipped]))
    assert count == 2 and np.array_equal(fixed[:3], good), "proper rotations are left bit for bit"
    assert np.allclose(fixed[3:].transpose(0, 2, 1) @ fixed[3:], np.eye(3), atol=1e-5)
    assert np.allclose(np.linalg.det(fixed[3:]), 1.0, atol=1e-5)


def test_sample_script_with_ray_writes_valid_scenes(dataset, sampled):
    from spread.assets import AssetLibrary

    library = AssetLibrary.load(dataset / "assets")
    sources = {p.stem: read_scene(p, assets=library) for p in list_scene_files(dataset / "test")}
    files = list_scene_files(sampled / "scenes")
    assert sorted(p.stem for p in files) == sorted(f"{s}_k{k}" for s in sources for k in (0, 1))
    for path in files:
        scene = read_scene(path, assets=library)  # the library's validation: shapes, rotations, assets
        src = sources[str(scene.extras["conditioned_on"])]
        assert scene.scene_id == path.stem
        for key in ("asset_id", "category", "spatial", "physical", "room"):
            assert np.array_equal(getattr(scene, key), getattr(src, key)), key
        assert not np.allclose(scene.translation, src.translation)
        source = str(scene.extras["source"])
        k = path.stem.rsplit("_k", 1)[1]
        assert "model.ckpt" in source and "sampler=ddim-4" in source and "seed=3" in source
        assert source.endswith(f"graph={src.scene_id} k={k}")
    manifest = json.loads((sampled / "sampling.json").read_text())
    assert manifest["runner"]["mode"] == "ray" and manifest["runner"]["workers"] == 2
    assert manifest["samples"] == 6 and manifest["written_this_run"] == 6
    assert len(list((sampled / "renders").glob("*.png"))) == 2


def test_same_seed_same_files_in_process_as_on_ray(dataset, trained, sampled, tmp_path):
    out = tmp_path / "local"
    result = sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                               "samples_per_graph=2", "seed=3")
    assert result.manifest["runner"]["mode"] == "in-process"
    for path in list_scene_files(sampled / "scenes"):
        assert (out / "scenes" / path.name).read_bytes() == path.read_bytes(), path.name
    other = sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={tmp_path / 's4'}",
                              "seed=4")
    a, b = (read_scene(p / "scenes" / f"{other.files[0].stem}.npz") for p in (out, tmp_path / "s4"))
    assert not np.allclose(a.translation, b.translation), "another seed, other scenes"


def test_resume_skips_done_graphs_and_redoes_other_settings_from_scratch(dataset, trained, tmp_path):
    out = tmp_path / "resume"
    args = (f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}", "seed=5")
    first = sample_in_process(*args)
    files = sorted(first.files)
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in files}
    files[1].unlink()
    again = sample_in_process(*args)
    assert again.written == [files[1].stem] and again.manifest["resumed"] == len(files) - 1
    for p in files:
        assert p.read_bytes() == before[p.name][0], "a resampled batch gives the same scenes"
        if p != files[1]:
            assert p.stat().st_mtime_ns == before[p.name][1], "done files are not rewritten"
    identical = sample_in_process(*args)
    assert identical.written == [] and identical.manifest["redone_because"] is None
    other = sample_in_process(*args[:-1], "seed=6")  # another seed: every file made anew, and the record says why
    assert sorted(other.written) == sorted(p.stem for p in files)
    assert other.manifest["redone_because"] == "changed: sampling.seed" and other.manifest["resumed"] == 0
    assert other.manifest["fingerprint"]["sampling"]["seed"] == 6
    assert any(p.read_bytes() != before[p.name][0] for p in files), "another seed, other scenes"
    sampler = sample_in_process(*args[:-1], "seed=6", "sampler.steps=3")
    assert sampler.manifest["redone_because"] == "changed: sampling.sampler.steps"
    assert len(sampler.written) == len(files)
    assert sample_in_process(*args[:-1], "seed=6", "sampler.steps=3").written == [], "identical: resumed"


def test_a_folder_sampled_from_other_data_content_is_redone(dataset, trained, tmp_path):
    """Same data.root, same settings, but the split's scene files changed: the old scenes are not kept."""
    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    out = tmp_path / "s"
    args = (f"ckpt={trained / 'model.ckpt'}", f"data.root={data}", f"out_dir={out}", "renders=0")
    first = sample_in_process(*args)
    gone = list_scene_files(data / "test")[0]
    gone.unlink()
    again = sample_in_process(*args)
    assert again.manifest["redone_because"] == "changed: data"
    assert again.manifest["samples"] == len(first.files) - 1 and len(again.written) == len(first.files) - 1
    assert not list((out / "scenes").glob(f"{gone.stem}_k*.npz")), "no scene of the removed graph stays"


@pytest.mark.parametrize("sampler", ["ddpm", "dpmsolver20"])
def test_sampler_swap_by_config(dataset, trained, tmp_path, sampler):
    out = tmp_path / sampler
    result = sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                               f"sampler={sampler}", "renders=0")
    assert len(result.written) == 3
    label = {"ddpm": "ddpm-4", "dpmsolver20": "dpmsolver++-4"}[sampler]
    assert f"sampler={label}" in str(read_scene(result.files[0]).extras["source"])


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_evaluate_accepts_generated_scenes(dataset, sampled, tmp_path):
    out = tmp_path / "eval"
    run_script("spread-evaluate", f"scenes={sampled / 'scenes'}", f"reference={dataset}", f"out_dir={out}",
               "protocol.stability_runs=1", "ray.num_cpus=2", "progress=false", "renders=0", "logger=none",
               "fid.enabled=false")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_scenes"] == 6 and metrics["n_failed"] == 0
    assert 0.0 <= metrics["grecall"] <= 1.0 and 0.0 <= metrics["col_mesh"] <= 1.0


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_sample_with_evaluate_true_writes_metrics_beside_the_scenes(dataset, trained, tmp_path):
    """``evaluate=true``: one run folder holds the scenes and their metrics (a sweep point); the protocol comes
    from the shared ``conf/protocol`` group; a second call resumes both (nothing resampled, nothing re-measured)."""
    out = tmp_path / "sample_eval"
    args = [f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}", *FAST_SAMPLE, "logger=none",
            "evaluate=true", "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false"]
    run_script("spread-sample", *args)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_scenes"] == 3 and metrics["n_evaluated"] == 3 and metrics["n_failed"] == 0
    assert metrics["protocol"]["stability_runs"] == 1
    # the intervals: the run's seed drew them, over its 3 scenes, and they hold the reported value
    assert metrics["bootstrap"]["seed"] == metrics["protocol"]["seed"] and metrics["bootstrap"]["n_scenes"] == 3
    assert metrics["grecall_lo"] <= metrics["grecall"] <= metrics["grecall_hi"]
    lines = (out / "per_scene.jsonl").read_text().splitlines()
    assert len(lines) == 3
    stamp = (out / "metrics.json").stat().st_mtime_ns
    again = run_script("spread-sample", *args)
    assert "finished earlier" in again.stdout  # a finished sweep point is skipped whole
    assert (out / "metrics.json").stat().st_mtime_ns == stamp
    (out / "metrics.json").unlink()  # interrupted after sampling: scenes resume, the evaluation completes
    again = run_script("spread-sample", *args)
    assert "0 written now, 3 already there" in again.stdout
    assert (out / "per_scene.jsonl").read_text().splitlines() == lines
    assert json.loads((out / "metrics.json").read_text())["n_evaluated"] == 3


def test_sample_draws_3d_figures_of_the_first_samples(dataset, trained, tmp_path):
    """``figures=1``: the first sample as a 3D scene card (view + relation matrix) and before | after physics,
    listed in sampling.json; ``figure_kinds`` picks which; an unknown kind is refused by name."""
    from PIL import Image

    out = tmp_path / "figs"
    result = sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                               "renders=0", "figures=1")
    first = result.files[0].stem
    expected = [out / "renders" / f"{first}_3d.png", out / "renders" / f"{first}_physics.png"]
    assert result.manifest["figures"] == [str(p) for p in expected]
    assert sorted((out / "renders").glob("*.png")) == sorted(expected)
    for path in expected:
        image = np.asarray(Image.open(path).convert("RGB"))
        assert image.shape[0] > 400 and image.shape[1] > 1000 and image.std() > 10
    # on wandb each kind is a key of its own, one picture size per key (a list of mixed sizes shows wrongly)
    from spread.tracking.sampling_wandb import image_groups

    groups = image_groups(result.manifest)
    assert groups == {"figures/3d": [str(expected[0])], "figures/physics": [str(expected[1])]}
    assert Image.open(expected[0]).size != Image.open(expected[1]).size
    only = sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                             "renders=0", "figures=1", "figure_kinds=[card]")
    assert only.manifest["figures"] == [str(expected[0])]
    with pytest.raises(Exception, match="figure_kinds: unknown \\['movie'\\]"):
        sample_in_process(f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                          "figure_kinds=[movie]")


def test_sample_rejects_an_unknown_guidance_mode(dataset, trained, tmp_path):
    proc = run_script("spread-sample", f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}",
                      f"out_dir={tmp_path / 'bad'}", *FAST_SAMPLE, "logger=none", "guidance.mode=strong", ok=False)
    assert proc.returncode != 0 and "strong" in proc.stderr


def test_guided_sampling_by_config_records_guidance(dataset, trained, tmp_path):
    """``guidance=refine``: files name the guidance in their source, sampling.json pins the full config and the
    guidance timings, and the scenes differ from unguided ones of the same seed; ``guidance=none`` records no
    guidance (its weights change nothing)."""
    args = [f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", "renders=0"]
    plain = sample_in_process(*args, f"out_dir={tmp_path / 'plain'}", "guidance=none")
    guided = sample_in_process(*args, f"out_dir={tmp_path / 'guided'}", "guidance=refine",
                               "guidance.iterations=3", "guidance.collision=0.05")
    assert plain.manifest["fingerprint"]["guidance"] is None and plain.manifest["guidance_label"] == "none"
    assert guided.manifest["fingerprint"]["guidance"]["mode"] == "refine"
    assert guided.manifest["fingerprint"]["guidance"]["iterations"] == 3
    assert guided.manifest["guidance_totals"]["iterations"] == 3 * guided.manifest["batches"]
    assert "guidance=refine(collision=0.05,gravity=0.001,relation=0.001,iterations=3)" in \
        str(read_scene(guided.files[0]).extras["source"])
    moved = [np.abs(read_scene(a).translation - read_scene(b).translation).max()
             for a, b in zip(plain.files, guided.files)]
    assert max(moved) > 0


def test_guidance_record_every_keeps_the_timeline_in_each_sample(dataset, trained, tmp_path):
    """``guidance.record_every=2`` with 4 refine iterations keeps the states after iterations 0, 2 and 4 in every
    file (``trajectory_*``, what spread-view plays); the last is the sample itself, the first differs from it."""
    from spread.render.viewer import scene_timeline

    args = [f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", "renders=0", "guidance=refine",
            "guidance.iterations=4", "guidance.collision=0.05", "guidance.record_every=2"]
    run = sample_in_process(*args, f"out_dir={tmp_path / 'timeline'}")
    for path in run.files:
        scene = read_scene(path)
        t, R = scene.extras["trajectory_translation"], scene.extras["trajectory_rotation"]
        assert t.shape == (3, scene.num_objects, 3) and R.shape == (3, scene.num_objects, 3, 3)
        np.testing.assert_allclose(t[-1], scene.translation, atol=1e-6)
        assert len(scene_timeline(scene)) == 3
    assert np.abs(read_scene(run.files[0]).extras["trajectory_translation"][0] - read_scene(run.files[0]).translation).max() > 0
    plain = sample_in_process(*args[:-1], f"out_dir={tmp_path / 'none'}")
    assert "trajectory_translation" not in read_scene(plain.files[0]).extras


def test_batch_size_does_not_change_the_samples(dataset, trained, tmp_path):
    """Each sample has its own noise, seeded by (seed, graph, k): with the (deterministic) DDIM sampler, batches of
    1 and of 3 give the same scenes up to float rounding (different padding shapes)."""
    args = [f"ckpt={trained / 'model.ckpt'}", f"data.root={dataset}", "renders=0", "seed=4"]
    one = sample_in_process(*args, f"out_dir={tmp_path / 'b1'}", "batch_size=1")
    three = sample_in_process(*args, f"out_dir={tmp_path / 'b3'}", "batch_size=3")
    assert one.manifest["batches"] == 3 and three.manifest["batches"] == 1
    for a, b in zip(sorted(one.files), sorted(three.files)):
        assert a.name == b.name
        np.testing.assert_allclose(read_scene(a).translation, read_scene(b).translation, atol=1e-4)
