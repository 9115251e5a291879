"""Classifier-free guidance on the geometry features (``geometry_scale``): the geometry-blind reading, the mix it
makes (1 is the model as trained, 0 the blind branch, 2 doubles the difference, in ε whatever the network predicts),
a clear refusal for models without geometry, its own place in the sampling identity and the ablation's rows, and
the command line as users type it."""

from __future__ import annotations

import json

import pytest
import torch

from spread.model.geometry import blind_distances, state_distances
from spread.model.module import SceneDiffusion
from spread.model.parts_distance import PARTS_RANGE

from helpers import FAST_SAMPLE, FAST_TRAIN, SMALL_MODEL, make_dataset, run_script, train_in_process, user_error
from test_geometry_pairs import _with_parts
from test_model import BOUNDS, random_batch, tiny


def _geometry_model(prediction="v_prediction", **config) -> SceneDiffusion:
    torch.manual_seed(0)
    model = SceneDiffusion("geometry", tiny(geometry_distance="parts", geometry_summary=True, **config),
                           bounds=BOUNDS, prediction=prediction).eval()
    with torch.no_grad():  # zero at initialisation: every output (so every mix) 0, and the geometry read by nothing
        for layer in (model.network.denoiser.head[-1], model.network.denoiser.geometry_mod, model.network.summary_in):
            layer.weight.normal_(std=0.1)
    return model


def _close_scenes(seed=4):
    b = _with_parts(random_batch(sizes=(3, 5), seed=seed))
    b["x"][:, :, :3] *= 0.1  # objects near the room's centre: some lie within each other's 10 cm range
    return b


def test_blind_distances_are_what_a_scene_of_objects_far_apart_reads():
    b = _with_parts(random_batch(sizes=(3, 5), seed=2))
    model = _geometry_model()
    cond = model.network.condition(b)
    far = b["x"].clone()
    far[0, :3, :3] = torch.tensor([[-0.9, 0.0, -0.9], [0.9, 0.0, -0.9], [0.0, 0.0, 0.9]])  # metres apart
    far[1, :5, :3] = torch.tensor([[-0.9, 0.0, -0.9], [0.9, 0.0, -0.9], [0.0, 0.0, 0.9], [-0.9, 0.9, 0.9],
                                   [0.9, 0.9, 0.9]])
    measured = state_distances(cond.cloud, far, cond.pose_offset, cond.pose_scale)
    blind = blind_distances(cond.cloud)
    assert torch.equal(blind, measured)  # nothing within reach: the search reads exactly the blind distances
    assert (blind[b["mask"]] == PARTS_RANGE).all() and (blind[~b["mask"]] == 0).all()
    close = state_distances(cond.cloud, _close_scenes()["x"], cond.pose_offset, cond.pose_scale)
    assert (close[b["mask"]] < PARTS_RANGE).any()  # ... which a scene with close objects does not


def test_geometry_scale_one_is_the_model_as_trained_zero_the_blind_branch_and_two_doubles_the_difference():
    model = _geometry_model(prediction="v_prediction", geometry_at="x0_hat")
    b = _close_scenes()
    # at low noise x̂_0 ≈ x_t: the scene is posed with its objects close, so the geometry reads something
    x_t = (b["x"] + 0.01 * torch.randn_like(b["x"])) * b["mask"][..., None]
    t = torch.tensor([0, 3])
    eps = {s: model.denoiser(b, use_ema=False, geometry_scale=s)[0](x_t, t) for s in (0.0, 1.0, 2.0)}
    plain = model.denoiser(b, use_ema=False)[0](x_t, t)
    assert torch.equal(eps[1.0], plain)
    # the blind branch, computed by hand: the second pass at the same x̂_0 pose, reading nothing near anything
    network, cond = model.network, model.network.condition(b)
    with torch.no_grad():
        first = network(x_t, t, cond)
        from spread.model.diffusion import x0_from_prediction

        pose = x0_from_prediction("v_prediction", first, x_t, model.alpha_bar(t)).clamp(-1, 1) * b["mask"][..., None]
        blind = model.epsilon(network(x_t, t, cond, pose=pose, blind=True), x_t, t)
    assert torch.allclose(eps[0.0], blind, atol=1e-6)
    assert not torch.allclose(blind, plain, atol=1e-3)  # the geometry changes the prediction here
    # the mix is made on v; ε is affine in v at fixed x_t and t, so it is the same mix of ε
    assert torch.allclose(eps[2.0], blind + 2.0 * (plain - blind), atol=1e-5)
    assert (eps[2.0][~b["mask"]] == 0).all()


def test_geometry_scale_inside_graph_guidance_mixes_each_branch():
    model = _geometry_model(prediction="epsilon")
    b = _close_scenes(seed=6)
    x_t = (b["x"] + 0.01 * torch.randn_like(b["x"])) * b["mask"][..., None]
    t = torch.tensor([10, 900])
    both = model.denoiser(b, use_ema=False, graph_scale=3.0, geometry_scale=2.0)[0](x_t, t)
    network = model.network
    cond = network.condition(b)
    null = network.null_condition(cond)
    with torch.no_grad():
        mixed = {c: 2.0 * network(x_t, t, k) - network(x_t, t, k, blind=True) for c, k in (("G", cond), ("0", null))}
    assert torch.allclose(both, mixed["0"] + 3.0 * (mixed["G"] - mixed["0"]), atol=1e-5)


def test_the_blind_features_are_made_once_per_sample_and_change_no_state(monkeypatch):
    import spread.model.network as network_module
    from spread.model.diffusion import denoise

    model = _geometry_model(prediction="epsilon")
    b = _close_scenes(seed=7)
    calls = []
    model.network.perceiver.register_forward_hook(lambda *_: calls.append(1))

    def run(graph_scale):
        calls.clear()
        with torch.no_grad():
            problem = model.denoising(b, use_ema=False, graph_scale=graph_scale, geometry_scale=2.0)
            states = denoise(problem, "ddim-4", torch.Generator().manual_seed(3))
        return states, len(calls)

    once, n_once = run(1.0)
    cfg_once, n_cfg = run(3.0)
    # a posed pass per step, which graph guidance's two branches share (sharing_geometry); one blind pass in all
    assert (n_once, n_cfg) == (4 + 1, 4 + 1)
    monkeypatch.setattr(network_module, "reusable", lambda: False)  # made again at every step, as before
    every, n_every = run(1.0)
    cfg_every, n_cfg_every = run(3.0)
    assert (n_every, n_cfg_every) == (2 * 4, 4 * 4)
    assert torch.equal(once, every) and torch.equal(cfg_once, cfg_every)
    # with gradients (training) nothing is kept: the blind pass builds its own graph every call
    cond = model.network.condition(b)
    x_t, t = b["x"] * b["mask"][..., None], torch.tensor([5, 6])
    model.network(x_t, t, cond, blind=True).sum().backward()
    assert cond.blind == {} and model.network.perceiver.latents.grad is not None


def test_a_model_without_geometry_refuses_a_geometry_scale():
    from spread.sampling.pipeline import ScenePipeline

    base = SceneDiffusion("base", tiny(depth=1), bounds=BOUNDS).eval()
    b = random_batch(sizes=(2, 3), m=16)
    assert not base.has_geometry and _geometry_model().has_geometry
    with pytest.raises(ValueError, match=r"geometry_scale=2.0: a model without geometry features"):
        base.denoising(b, geometry_scale=2.0)
    with pytest.raises(ValueError, match="blind=True reads no geometry"):
        base.network(b["x"], torch.tensor([1, 2]), base.network.condition(b), blind=True)
    with pytest.raises(ValueError, match=r"geometry_scale=1.5: this model \(.*variant base\) has no geometry features"):
        ScenePipeline(base, None, "ddim-3", geometry_scale=1.5)
    with pytest.raises(ValueError, match="geometry_scale=nan: a finite number"):
        ScenePipeline(_geometry_model(), None, "ddim-3", geometry_scale=float("nan"))
    assert torch.isfinite(base.denoising(b, geometry_scale=1.0).eps_fn(b["x"], torch.tensor([3, 4]))).all()


def test_the_sampling_identity_spells_geometry_scale_only_when_it_acts_and_tables_see_it_differ():
    from spread.runtime.fingerprint import config_identity, differing, settings

    recorded = {"ckpt": "a.ckpt", "seed": 0, "graph_scale": 2.0, "use_ema": True}
    old = config_identity(recorded)  # a run recorded before the setting existed
    assert config_identity({**recorded, "geometry_scale": 1}) == old  # the default is not spelled: same identity
    guided = config_identity({**recorded, "geometry_scale": 2.0})
    assert guided != old and guided["sampling"]["geometry_scale"] == 2.0
    assert settings(old)["geometry_scale"] == 1.0 and settings(guided)["geometry_scale"] == 2.0
    assert differing([settings(old), settings(guided)]) == ["geometry_scale"]
    assert config_identity({**recorded, "precision": "bf16"})["sampling"]["precision"] == "bf16"


def test_the_ablation_samples_the_geometry_checkpoints_rows_with_their_own_list(tmp_path):
    from spread.experiments.ablation import Ablation, AblationSpec

    from test_ablate_seeds import ALL, FakeCommands, fake_spec

    ablation = Ablation(fake_spec(tmp_path, sample_variant={"geometry": ["geometry_scale=2.0"]}), FakeCommands())
    assert ablation.sample_lists("base") == ablation.sample_lists("base_time") == ["seed=0"]
    assert ablation.sample_lists("geometry") == ["seed=0", "geometry_scale=2.0"]
    assert ablation.sample_lists("guidance") == ["seed=0", "geometry_scale=2.0", "guidance=refine",
                                                 "guidance.gravity=4.0e-3"]
    assert ablation.sample_lists("guidance_collision")[:2] == ["seed=0", "geometry_scale=2.0"]
    with pytest.raises(ValueError, match="sample.guidance: only the trained checkpoints' rows"):
        AblationSpec(out_dir=tmp_path / "x", variants=ALL, sample_variant={"guidance": ["geometry_scale=2.0"]})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("geometry_scale_data"))


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory, dataset):
    """A 2-step +Geometry (`parts`) and base checkpoint of the tests' dataset."""
    out = tmp_path_factory.mktemp("geometry_scale")
    for variant in ("geometry", "base"):
        train_in_process(out / variant, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null",
                         "trainer.max_steps=2", f"model.variant={variant}", "model.config.geometry_distance=parts",
                         *SMALL_MODEL, *FAST_TRAIN)
    return {v: out / v / "checkpoints" / "last.ckpt" for v in ("geometry", "base")}


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_spread_sample_with_geometry_scale_records_it_redoes_other_settings_and_refuses_a_base_model(
        checkpoints, dataset, tmp_path):
    scenes = tmp_path / "samples"
    common = [f"data.root={dataset}", f"out_dir={scenes}", *FAST_SAMPLE]
    run_script("spread-sample", f"ckpt={checkpoints['geometry']}", *common, "geometry_scale=2.0")
    manifest = json.loads((scenes / "sampling.json").read_text())
    assert manifest["fingerprint"]["sampling"]["geometry_scale"] == 2.0 and manifest["written_this_run"] == 3
    run_script("spread-sample", f"ckpt={checkpoints['geometry']}", *common, "geometry_scale=2")  # the same setting
    assert json.loads((scenes / "sampling.json").read_text())["written_this_run"] == 0
    run_script("spread-sample", f"ckpt={checkpoints['geometry']}", *common)  # at the default: other scenes
    manifest = json.loads((scenes / "sampling.json").read_text())
    assert "geometry_scale" not in manifest["fingerprint"]["sampling"] and manifest["written_this_run"] == 3
    line, _ = user_error("spread-sample", f"ckpt={checkpoints['base']}", f"data.root={dataset}",
                         f"out_dir={tmp_path / 'base'}", *FAST_SAMPLE, "geometry_scale=2.0")
    assert "geometry_scale=2.0: this model (" in line and "variant base) has no geometry features to guide" in line
    assert not (tmp_path / "base" / "scenes").exists() or not list((tmp_path / "base" / "scenes").iterdir())
