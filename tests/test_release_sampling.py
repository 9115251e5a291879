"""The authors' checkpoint through the platform's commands: ``spread-release-ckpt out=`` converts a ``ckpt.pth``
(here the reduced-size fixture weights of tests/data/release_network_fixture.npz in the release's format) into a
platform checkpoint; ``spread-sample`` samples it on a dataset imported from the release layout (with the
file's shape tokens and surface points), ``guidance=paper`` adding the authors' 100 refinement iterations, and
``spread-evaluate`` scores the samples."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import realdata
from helpers import run_script
from test_release_checkpoint import fixture, release_ckpt  # noqa: F401  (the module fixture)

from spread.importers.run import ImportConfig, import_dataset
from spread.safe_load import load_checkpoint
from spread.scene import read_scene

FAST = dict(processes=1, progress=False, renders=0, decomposition="hull", fidelity_samples=200)
POINTS = 16  # the file's xyz / normal per object (the release stores >= 1000)
TOKENS = 8  # miche_feature tokens per object (the release's 256)


def network_overrides(config) -> list[str]:
    """``model.config.*`` overrides that size experiment=release as the fixture's network."""
    fields = ("attn_dim", "t_dim", "n_heads", "n_layers", "context_dim", "num_freq_bands", "perceiver_depth",
              "num_latents", "cross_heads", "cross_dim_head", "latent_heads", "latent_dim_head", "num_classes",
              "self_per_cross")
    return [f"model.config.{f}={getattr(config, f)}" for f in fields] + [f"model.config.num_points={POINTS}"]


def release_src_with_features(root: Path) -> Path:
    """The known-answer release layout whose boxes.npz also carry miche_feature, xyz and normal."""
    src = realdata.release_layout(root)
    rng = np.random.default_rng(0)
    for boxes in sorted(src.glob("*/boxes.npz")):
        with np.load(boxes, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        n1 = len(arrays["obj_names"])
        normal = rng.normal(size=(n1, POINTS, 3))
        arrays.update(miche_feature=rng.normal(size=(n1, TOKENS, 64)).astype(np.float32),
                      xyz=rng.uniform(-0.05, 0.05, size=(n1, POINTS, 3)).astype(np.float32),
                      normal=(normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32))
        np.savez(boxes, **arrays)
    return src


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = tmp_path_factory.mktemp("release_sampling")
    src = release_src_with_features(root / "src")
    import_dataset(ImportConfig("spread_release", str(src), str(root / "data"), **FAST))
    return root / "data"


def test_the_import_keeps_what_the_release_network_reads(imported):
    scene = read_scene(next(iter(sorted((imported / "test").glob("*.npz")))))
    n = scene.num_objects
    assert scene.extras["shape_tokens"].shape == (n, TOKENS, 64)
    assert scene.extras["surface_points"].shape == scene.extras["surface_normals"].shape == (n, POINTS, 3)
    assert scene.extras["release_regions"].shape == (n + 1, n + 1)
    assert scene.extras["release_relations"].tolist() == [[1, 1, 2], [1, 1, 3], [0, 1, 1]]


def test_a_converted_checkpoint_loads_by_its_method_and_samples_through_the_sampling_library(fixture, imported,
                                                                                             tmp_path):
    """In process (fast): convert, load by the saved method, sample with the spread-sample library path."""
    from helpers import sample_in_process

    from spread.methods import load_module
    from spread.cli.release_ckpt import convert
    from spread.methods.release import ReleaseDiffusion

    config, weights, keys, _ = fixture
    out = tmp_path / "release.ckpt"
    convert(str(release_ckpt(tmp_path / "ckpt.pth", weights, keys)), str(out), use_ema=False,
            overrides=network_overrides(config))
    module = load_module(out)
    assert isinstance(module, ReleaseDiffusion) and module.hparams.weights == "raw"
    assert not torch.equal(module.network.state_dict()["proj_out.1.bias"], weights["proj_out.1.bias"])  # raw ≠ EMA
    result = sample_in_process(f"ckpt={out}", f"data.root={imported}", f"out_dir={tmp_path / 's'}", "sampler=ddpm",
                               "sampler.steps=3", "logger=none", "renders=0")
    assert len(result.files) == 2
    # guidance=paper on the authors' network: their refinement after the sampler (here 3 iterations per batch)
    guided = sample_in_process(f"ckpt={out}", f"data.root={imported}", f"out_dir={tmp_path / 'g'}", "sampler=ddpm",
                               "sampler.steps=3", "logger=none", "renders=0", "guidance=paper", "guidance.iterations=3")
    totals, batches = guided.manifest["guidance_totals"], guided.manifest["batches_run"]
    assert totals["iterations"] == totals["network_calls"] == 3 * batches and totals["steps"] == 3 * batches
    for a, b in zip(result.files, guided.files):  # same seed, same sampler: guidance moved the objects
        assert not np.allclose(read_scene(a).translation, read_scene(b).translation)
    # what the network runs for guidance=paper is guidance=release: one run, whichever way it is spelled
    assert guided.manifest["guidance"]["mode"] == "release" and guided.manifest["guidance_label"].startswith("release(")
    again = sample_in_process(f"ckpt={out}", f"data.root={imported}", f"out_dir={tmp_path / 'g'}", "sampler=ddpm",
                              "sampler.steps=3", "logger=none", "renders=0", "guidance=release", "guidance.iterations=3")
    assert again.manifest["written_this_run"] == 0 and again.manifest["resumed"] == len(guided.files)
    assert again.manifest["guidance"] == guided.manifest["guidance"]
    with pytest.raises(ValueError, match="cuda_graph=false"):  # its point features read the mask on the host
        sample_in_process(f"ckpt={out}", f"data.root={imported}", f"out_dir={tmp_path / 'c'}", "cuda_graph=true",
                          "logger=none", "renders=0")
    with pytest.raises(ValueError, match="graph_scale"):  # the release has no classifier-free graph guidance
        sample_in_process(f"ckpt={out}", f"data.root={imported}", f"out_dir={tmp_path / 'c'}", "graph_scale=2",
                          "logger=none", "renders=0")
    with pytest.raises(RuntimeError, match="ships no training code"):  # spread-train experiment=release
        module.setup("fit")


@pytest.mark.slow
def test_a_converted_release_ckpt_samples_with_spread_sample_and_scores_with_spread_evaluate(fixture, imported,
                                                                                           tmp_path):
    config, weights, keys, _ = fixture
    ckpt = release_ckpt(tmp_path / "ckpt.pth", weights, keys)
    out = tmp_path / "release.ckpt"
    proc = run_script("spread-release-ckpt", f"ckpt={ckpt}", f"out={out}", *network_overrides(config))
    assert "no missing or unexpected keys" in proc.stdout and out.is_file()

    converted = load_checkpoint(out)  # weights_only: plain data and tensors
    hp = converted["hyper_parameters"]
    assert hp["method"] == "release" and hp["weights"] == "ema" and hp["config"]["attn_dim"] == config.attn_dim
    for k in keys:  # the EMA (fixture) weights, not the raw ones
        assert torch.equal(converted["state_dict"][f"network.{k}"], weights[k]), k

    samples = tmp_path / "samples"
    run_script("spread-sample", f"ckpt={out}", f"data.root={imported}", f"out_dir={samples}", "sampler=ddpm",
               "sampler.steps=5", "workers=0", "batch_size=2", "renders=0", "figures=0", "progress=false",
               "logger=none")
    files = sorted((samples / "scenes").glob("*.npz"))
    sources = {read_scene(f).scene_id: read_scene(f) for f in sorted((imported / "test").glob("*.npz"))}
    assert len(files) == len(sources) == 2
    for f in files:
        scene = read_scene(f)
        source = sources[str(scene.extras["conditioned_on"])]
        assert list(scene.asset_id) == list(source.asset_id)
        assert np.isfinite(scene.translation).all() and not np.allclose(scene.translation, source.translation)
        R = scene.rotation.astype(np.float64)
        assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-4

    run_script("spread-evaluate", f"scenes={samples / 'scenes'}", f"reference={imported}",
               f"out_dir={tmp_path / 'eval'}", "protocol.stability_runs=1", "ray.num_cpus=1", "progress=false",
               "renders=0", "logger=none", "fid.enabled=false")
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["n_evaluated"] == 2 and metrics["n_failed"] == 0
    assert 0.0 <= metrics["grecall"] <= 1.0


def test_spread_sample_guidance_paper_runs_the_authors_pipeline_on_a_converted_checkpoint(fixture, imported, tmp_path):
    """The console script as a user types it: the release's DDPM (strided here) then its 100 refinement iterations
    with its own terms (mode ``release``: spread.guidance.release), the placeholder never guided, poses valid."""
    from spread.cli.release_ckpt import convert

    config, weights, keys, _ = fixture
    out = tmp_path / "release.ckpt"
    convert(str(release_ckpt(tmp_path / "ckpt.pth", weights, keys)), str(out), use_ema=True,
            overrides=network_overrides(config))
    samples = tmp_path / "samples"
    proc = run_script("spread-sample", f"ckpt={out}", f"data.root={imported}", f"out_dir={samples}", "sampler=ddpm",
                      "sampler.steps=3", "guidance=paper", "workers=0", "batch_size=2", "renders=0", "figures=0",
                      "progress=false", "logger=none")
    manifest = json.loads((samples / "sampling.json").read_text())
    assert manifest["guidance"]["mode"] == "release" and manifest["guidance"]["iterations"] == 100  # what ran
    totals = manifest["guidance_totals"]
    assert totals["iterations"] == totals["network_calls"] == 100 and totals["steps"] == 100  # one batch
    files = sorted((samples / "scenes").glob("*.npz"))
    assert len(files) == 2, proc.stdout
    for f in files:
        scene = read_scene(f)
        assert np.isfinite(scene.translation).all()
        R = scene.rotation.astype(np.float64)
        assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-4


def test_the_samples_depend_on_the_shape_tokens_and_the_file_frame(fixture, imported):
    """scene_inputs reads the file's tokens (the network sees them) and decodes poses in the library's frame."""
    from spread.assets.library import AssetLibrary
    from spread.methods.release import ReleaseDiffusion
    from spread.sampling.pipeline import ScenePipeline
    from spread.data import SceneDataset

    config, weights, keys, _ = fixture
    model = ReleaseDiffusion(config=config.to_dict(), num_points=POINTS)
    model.network.load_state_dict(weights)
    dataset = SceneDataset(imported, "test", num_points=POINTS)
    sources = [read_scene(f, assets=dataset.library) for f in dataset.files]  # copies: edited below
    pipe = ScenePipeline(model, dataset, "ddpm-3")
    gens = lambda: [torch.Generator().manual_seed(i) for i in range(len(sources))]  # noqa: E731
    a = pipe(sources, gens())
    b = pipe(sources, gens())
    assert all(np.array_equal(x.translation, y.translation) for x, y in zip(a, b))  # seeded
    for s in sources:
        s.extras["shape_tokens"] = np.zeros_like(s.extras["shape_tokens"])
    c = pipe(sources, gens())
    assert not all(np.allclose(x.translation, y.translation) for x, y in zip(a, c))
    inputs = model.scene_inputs(sources, AssetLibrary.load(imported / "assets"))["release"]
    assert inputs["edges"][0, 1, 2] == 1 and inputs["edges"][0, 0, 1] == 1 and inputs["edges"][0, 2, 1] == 3
    table = dataset.library[str(sources[0].asset_id[0])].source["canonical_offset"]
    assert np.allclose(inputs["shift"][0, 0].numpy(), np.asarray(table) - realdata.TABLE_OFFSET, atol=1e-5)
