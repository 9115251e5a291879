"""The model: geometry features, shapes, masking, training, checkpoints, samplers, Lightning."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from spread.configs import model_config
from spread.data import matrix_to_rot6d, rot6d_to_matrix
from spread.model import ModelConfig, Sampler, SceneDenoiser, graph_recall, signed_chamfer_features
from spread.model.diffusion import reverse_process

BOUNDS = [-3.0, 0.0, -3.0, 3.0, 2.5, 3.0]


M = 48  # points per object in these tests


def tiny(**overrides) -> ModelConfig:
    """The tiny preset, shrunk further so each test runs in a second or two."""
    return model_config("tiny", **{"depth": 2, "dim": 64, "dim_head": 16, "edge_dim": 32, "num_latents": 8,
                               "shape_tokens": 4, "shape_dim": 16, "tokenizer_width": 32, "tokenizer_points": M,
                               "index_dim": 16, "num_points": M, **overrides})


def random_batch(sizes=(3, 5), n_max=None, m=M, seed=0, shape_tokens=None):
    """Random scenes of the given sizes, collated like ``collate_scenes`` (pads, mask)."""
    g = torch.Generator().manual_seed(seed)
    B, N = len(sizes), n_max or max(sizes)
    mask = torch.arange(N)[None, :] < torch.tensor(sizes)[:, None]
    pair = mask[:, :, None] & mask[:, None, :]
    R = rot6d_to_matrix(torch.randn(B, N, 6, generator=g))
    x = torch.cat([torch.rand(B, N, 3, generator=g) * 2 - 1, matrix_to_rot6d(R)], -1) * mask[..., None]
    spatial = torch.randint(0, 7, (B, N, N), generator=g).masked_fill(~pair, 7)
    physical = torch.randint(0, 3, (B, N, N), generator=g).masked_fill(~pair, 3)
    points = (torch.rand(B, N, m, 3, generator=g) - 0.5) * 0.6 * mask[..., None, None]
    normals = torch.nn.functional.normalize(torch.randn(B, N, m, 3, generator=g), dim=-1) * mask[..., None, None]
    batch = dict(x=x, mask=mask, spatial=spatial, physical=physical, points=points, normals=normals)
    if shape_tokens:
        batch["shape_tokens"] = torch.randn(B, N, *shape_tokens, generator=g) * mask[..., None, None]
    return batch


def pad_with_junk(batch, extra=2, seed=1):
    """The same scenes with ``extra`` more padding slots filled with random junk (mask False)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, v in batch.items():
        if key == "mask":
            out[key] = torch.cat([v, torch.zeros(v.shape[0], extra, dtype=torch.bool)], 1)
        elif key in ("spatial", "physical"):
            B, N, _ = v.shape
            big = torch.randint(0, 7 if key == "spatial" else 3, (B, N + extra, N + extra), generator=g)
            big[:, :N, :N] = v
            out[key] = big
        else:
            junk = torch.randn((v.shape[0], extra) + v.shape[2:], generator=g) * 5
            out[key] = torch.cat([v, junk.to(v.dtype)], 1)
    # junk also inside the original padding slots
    pad = ~out["mask"]
    out["x"] = torch.where(pad[..., None], torch.randn(out["x"].shape, generator=g), out["x"])
    out["points"] = torch.where(pad[..., None, None], torch.randn(out["points"].shape, generator=g), out["points"])
    return out


# ---- signed chamfer features ------------------------------------------------------------------------

def brute_force_features(points, normals, t, R, mask):
    """Explicit loops over scenes, objects, points and candidate points: the definition."""
    B, N, m, _ = points.shape
    out = torch.zeros(B, N, m, 4, dtype=torch.float64)
    P, Nw = points.double(), normals.double()
    for b in range(B):
        world = [R[b, i].double() @ P[b, i].T + t[b, i].double()[:, None] for i in range(N)]  # (3, m)
        normal = [R[b, i].double() @ Nw[b, i].T for i in range(N)]
        for i in range(N):
            if not mask[b, i]:
                continue
            others = [j for j in range(N) if j != i and mask[b, j]]
            for k in range(m):
                p = world[i][:, k]
                best, sign = None, 1.0
                for j in others:
                    for q in range(m):
                        d = torch.linalg.norm(p - world[j][:, q])
                        if best is None or d < best:
                            best, sign = d, (1.0 if (p - world[j][:, q]) @ normal[j][:, q] >= 0 else -1.0)
                out[b, i, k, :3] = P[b, i, k]
                out[b, i, k, 3] = 10.0 if best is None else sign * best
    return out


def random_poses(B, N, seed, spread=1.5):
    g = torch.Generator().manual_seed(seed)
    t = (torch.rand(B, N, 3, generator=g) - 0.5) * 2 * spread
    R = torch.from_numpy(Rotation.random(B * N, random_state=seed).as_matrix()).float().reshape(B, N, 3, 3)
    return t, R


def test_signed_chamfer_matches_brute_force_with_padding():
    b = random_batch(sizes=(3, 4, 1), m=20, seed=3)
    t, R = random_poses(3, 4, seed=3, spread=0.5)  # close objects: plenty of penetrating points
    expected = brute_force_features(b["points"], b["normals"], t, R, b["mask"])
    for kwargs in ({}, {"prune": False}, {"chunk": 7}, {"max_elements": 50}):
        got = signed_chamfer_features(b["points"], b["normals"], t, R, b["mask"], **kwargs)
        assert got.shape == (3, 4, 20, 4)
        assert torch.allclose(got.double(), expected, atol=1e-5), kwargs
    assert (expected[..., 3] < 0).any() and (expected[..., 3] > 0).any(), "both signs occur"
    assert (got[~b["mask"]] == 0).all() and (got[2, 0, :, 3] == 10.0).all(), "padding zero; lone object far"


def test_signed_chamfer_pruning_is_exact_on_larger_scenes():
    g = torch.Generator().manual_seed(5)
    B, N, m = 2, 12, 300
    points = (torch.rand(B, N, m, 3, generator=g) - 0.5) * 0.8
    normals = torch.nn.functional.normalize(torch.randn(B, N, m, 3, generator=g), dim=-1)
    t, R = random_poses(B, N, seed=5, spread=2.0)
    mask = torch.ones(B, N, dtype=torch.bool)
    mask[1, 9:] = False
    fast = signed_chamfer_features(points, normals, t, R, mask)
    full = signed_chamfer_features(points, normals, t, R, mask, prune=False)
    assert torch.allclose(fast, full, atol=1e-6)


def test_signed_chamfer_rigid_motion_invariance():
    b = random_batch(sizes=(5, 3), m=40, seed=7)
    t, R = random_poses(2, 5, seed=7)
    Q = torch.from_numpy(Rotation.random(random_state=1).as_matrix()).float()
    shift = torch.tensor([4.0, -1.0, 2.5])
    before = signed_chamfer_features(b["points"], b["normals"], t, R, b["mask"])
    after = signed_chamfer_features(b["points"], b["normals"], t @ Q.T + shift, Q @ R, b["mask"])
    assert torch.allclose(before, after, atol=1e-5), "local xyz and signed distance are invariant"


def test_signed_chamfer_padding_invariance_and_gradients():
    b = random_batch(sizes=(4, 2), m=30, seed=9)
    t, R = random_poses(2, 4, seed=9)
    ref = signed_chamfer_features(b["points"], b["normals"], t, R, b["mask"])
    padded = pad_with_junk(b, extra=3)
    t2 = torch.cat([t, torch.full((2, 3, 3), float("nan"))], 1)
    R2 = torch.cat([R, torch.randn(2, 3, 3, 3)], 1)
    got = signed_chamfer_features(padded["points"], padded["normals"], t2, R2, padded["mask"])
    assert torch.allclose(got[:, :4], ref, atol=1e-6) and (got[~padded["mask"]] == 0).all()
    tt = t.clone().requires_grad_(True)
    signed_chamfer_features(b["points"], b["normals"], tt, R, b["mask"])[..., 3].sum().backward()
    assert torch.isfinite(tt.grad).all() and tt.grad.abs().sum() > 0


# ---- network ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["base", "geometry"])
def test_shapes_and_padding_never_change_real_outputs(variant):
    torch.manual_seed(0)
    net = SceneDenoiser(tiny(), variant, BOUNDS).eval()
    b = random_batch(sizes=(3, 5), seed=11)
    t = torch.tensor([10, 900])
    x_t = b["x"] + 0.3 * torch.randn_like(b["x"]) * b["mask"][..., None]
    with torch.no_grad():
        eps = net(x_t, t, net.condition(b))
        assert eps.shape == (2, 5, 9) and torch.isfinite(eps).all()
        assert (eps[~b["mask"]] == 0).all()
        padded = pad_with_junk(b, extra=3)
        x_junk = torch.cat([x_t, torch.randn(2, 3, 9) * 3], 1)
        x_junk[0, 3:5] = torch.randn(2, 9) * 3  # scene 0's own padding slots hold junk too
        eps2 = net(x_junk, t, net.condition(padded))
    assert torch.allclose(eps2[:, :5][b["mask"]], eps[b["mask"]], atol=1e-5)
    assert (eps2[~padded["mask"]] == 0).all()


def test_precomputed_shape_tokens():
    net = SceneDenoiser(tiny(shape_encoder="precomputed", shape_tokens=6, shape_dim=12), "base", BOUNDS).eval()
    b = random_batch(shape_tokens=(6, 12))
    with torch.no_grad():
        eps = net(b["x"], torch.tensor([5, 50]), net.condition(b))
    assert eps.shape == (2, 5, 9)
    b.pop("shape_tokens")
    with pytest.raises(KeyError, match="shape_tokens"):
        net.condition(b)


def test_tokenizer_is_a_function_of_the_asset_only():
    net = SceneDenoiser(tiny(), "base", BOUNDS).eval()
    b = random_batch(seed=2)
    moved = dict(b, x=torch.randn_like(b["x"]))  # poses do not enter shape tokens
    with torch.no_grad():
        a, c = net.shape_encoder(b), net.shape_encoder(moved)
    assert torch.equal(a, c) and a.shape == (2, 5, 4, 16) and (a[0, 3:] == 0).all()


def test_tokenizer_encodes_each_shared_point_set_once_with_the_same_result():
    torch.manual_seed(0)
    net = SceneDenoiser(tiny(), "base", BOUNDS)
    b = random_batch(sizes=(4, 3), seed=6)
    # object 2 of scene 1 carries the points of object 0 of scene 0; index 9 is another set
    b["points"][1, 2], b["normals"][1, 2] = b["points"][0, 0], b["normals"][0, 0]
    b["shape_index"] = torch.tensor([[5, 1, 2, 3], [9, 4, 5, -1]])
    calls = []
    original = net.shape_encoder.encode
    net.shape_encoder.encode = lambda p, n: calls.append(len(p)) or original(p, n)
    shared = net.shape_encoder(b)
    separate = net.shape_encoder({k: v for k, v in b.items() if k != "shape_index"})
    assert calls == [6, 7], "6 distinct point sets among 7 real objects"
    assert torch.allclose(shared, separate, atol=1e-6) and torch.equal(shared[1, 2], shared[0, 0])
    # gradients of the shared encoding equal those of encoding every object
    grads = []
    for batch in (b, {k: v for k, v in b.items() if k != "shape_index"}):
        net.zero_grad()
        (net.shape_encoder(batch) * torch.linspace(-1, 1, 16)).sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.shape_encoder.parameters()]))
    assert torch.allclose(grads[0], grads[1], atol=1e-5)


# ---- training ---------------------------------------------------------------------------------------

def test_one_batch_overfit_tiny_model():
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", model_config("tiny", tokenizer_points=M, num_points=M), bounds=BOUNDS)
    b = random_batch(sizes=(4, 3), seed=4)
    noise, t = torch.randn(2, 4, 9), torch.tensor([40, 400])
    opt = torch.optim.AdamW(model.network.parameters(), lr=2e-3)
    losses = []
    for _ in range(150):
        loss = model.training_loss(b, noise, t)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if losses[-1] < losses[0] / 10:
            break
    assert losses[-1] < losses[0] / 10, f"loss {losses[0]:.3f} → {losses[-1]:.3f} in {len(losses)} steps"


@pytest.mark.parametrize("prediction", ["epsilon", "sample", "v_prediction"])
def test_every_prediction_target_gives_back_the_noise(prediction):
    from spread.model.diffusion import epsilon_from_prediction, prediction_target, training_scheduler

    g = torch.Generator().manual_seed(1)
    x0, noise = torch.rand(3, 5, 9, generator=g) * 2 - 1, torch.randn(3, 5, 9, generator=g)
    alpha_bar = training_scheduler().alphas_cumprod[torch.tensor([0, 500, 999])].double()
    a = alpha_bar.float()[:, None, None]
    x_t = a.sqrt() * x0 + (1 - a).sqrt() * noise
    target = prediction_target(prediction, x0, noise, alpha_bar)
    assert torch.allclose(epsilon_from_prediction(prediction, target, x_t, alpha_bar), noise, atol=2e-3)
    expected = {"epsilon": noise, "sample": x0, "v_prediction": a.sqrt() * noise - (1 - a).sqrt() * x0}[prediction]
    assert torch.allclose(target, expected)
    with pytest.raises(ValueError, match="unknown prediction"):
        prediction_target("x0", x0, noise, alpha_bar)


def test_min_snr_weights_and_learning_rate_schedule_known_values():
    from spread.model.diffusion import loss_weights
    from spread.model.module import lr_factor

    alpha_bar = torch.tensor([10 / 11, 0.5], dtype=torch.float64)  # SNR 10 and 1
    assert torch.allclose(loss_weights("min_snr", "epsilon", alpha_bar, 5.0), torch.tensor([0.5, 1.0]).double())
    assert torch.allclose(loss_weights("min_snr", "sample", alpha_bar, 5.0), torch.tensor([5.0, 1.0]).double())
    assert torch.allclose(loss_weights("min_snr", "v_prediction", alpha_bar, 5.0), torch.tensor([5 / 11, 0.5]).double())
    assert torch.equal(loss_weights("none", "sample", alpha_bar), torch.ones(2).double())
    assert [lr_factor(s, 4, 104, "cosine", 0.1) for s in (0, 3, 4, 54, 104, 200)] == pytest.approx(
        [0.25, 1.0, 1.0, 0.55, 0.1, 0.1])
    assert lr_factor(50, 0, None, "constant", 0.1) == 1.0


def test_a_prediction_other_than_epsilon_trains_and_samples():
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    model = SceneDiffusion("base", tiny(), bounds=BOUNDS, prediction="sample", loss_weighting="min_snr")
    b = random_batch(sizes=(4, 3), seed=4)
    x0 = b["x"]
    # an ideal x0-predictor (its output is the clean state) gives zero loss, and ε̂ = the true noise
    noise, t = torch.randn(2, 4, 9) * b["mask"][..., None], torch.tensor([40, 700])
    x_t = model.noise_schedule.add_noise(x0, noise, t)
    assert torch.allclose(model.epsilon(x0, x_t, t), noise, atol=1e-3)
    loss = model.training_loss(b, noise, t)
    loss.backward()
    assert torch.isfinite(loss) and loss > 0
    poses = model.sample(b, "ddim-3", torch.Generator().manual_seed(0))
    assert torch.isfinite(poses.translation).all()


def test_geometry_model_started_from_a_base_checkpoint_predicts_what_the_base_predicts(tmp_path):
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    base = SceneDiffusion("base", tiny(), bounds=BOUNDS)
    with torch.no_grad():  # a "trained" EMA: different from the training weights
        for p in base.ema.module.parameters():
            p.add_(0.05 * torch.randn_like(p))
    torch.save({"state_dict": base.state_dict()}, tmp_path / "base.ckpt")
    geometry = SceneDiffusion("geometry", tiny(), bounds=BOUNDS, init_from=str(tmp_path / "base.ckpt"))
    fresh = geometry.initialise_from(str(tmp_path / "base.ckpt"))
    assert fresh and all(k.startswith(("perceiver.", "denoiser.geometry_")) or ".geometry_attn." in k for k in fresh)
    b = random_batch(seed=8)
    t = torch.tensor([30, 600])
    x_t = b["x"] + 0.2 * torch.randn_like(b["x"]) * b["mask"][..., None]
    base_net, geo_net = base.ema.module.eval(), geometry.network.eval()
    with torch.no_grad():
        expected = base_net(x_t, t, base_net.condition(b))
        assert torch.allclose(geo_net(x_t, t, geo_net.condition(b)), expected, atol=1e-5)
        assert torch.allclose(geometry.ema.module.eval()(x_t, t, geometry.ema.module.condition(b)), expected, atol=1e-5)
    wider = SceneDiffusion("geometry", tiny(dim=96), bounds=BOUNDS)
    with pytest.raises(ValueError, match="shape"):
        wider.initialise_from(str(tmp_path / "base.ckpt"))
    with pytest.raises(FileNotFoundError, match="init_from"):
        wider.initialise_from(str(tmp_path / "missing.ckpt"))


# ---- samplers ---------------------------------------------------------------------------------------

def test_ddpm_1000_loop_is_seeded_and_finite():
    mask = torch.tensor([[True, True, False], [True, True, True]])
    sampler = Sampler.from_config("ddpm")
    assert sampler.num_steps == 1000

    def eps_fn(x, t):  # a stand-in model: the loop itself is what is tested here
        return 0.5 * x

    runs = [reverse_process(sampler, eps_fn, mask, generator=torch.Generator().manual_seed(s)) for s in (0, 0, 1)]
    assert runs[0].shape == (2, 3, 9) and torch.isfinite(runs[0]).all() and (runs[0][0, 2] == 0).all()
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])


def test_sampler_swap_and_seeding():
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", tiny(depth=1), bounds=BOUNDS)
    b = random_batch(sizes=(2, 4), m=16, seed=6)
    for sampler in ("ddpm-10", "ddim-4", "dpmsolver++-4", Sampler("ddim", 3, eta=1.0)):
        runs = [model.sample(b, sampler, generator=torch.Generator().manual_seed(s)) for s in (0, 0, 1)]
        t, R = runs[0]
        assert t.shape == (2, 4, 3) and R.shape == (2, 4, 3, 3) and torch.isfinite(t).all() and torch.isfinite(R).all()
        assert torch.equal(runs[0].translation, runs[1].translation), f"{sampler}: same seed, same sample"
        assert not torch.equal(runs[0].translation, runs[2].translation)
        assert (t[0, 2:] == 0).all() and torch.equal(R[0, 2:], torch.eye(3).expand(2, 3, 3)), "padding: t=0, R=I"


@pytest.mark.parametrize("sampler", ["ddim-4", "dpmsolver++-4"])
def test_per_scene_generators_make_a_sample_independent_of_its_batch(sampler):
    """One generator per scene: with a deterministic sampler a scene sampled in a batch equals the same scene
    sampled alone (and unpadded) with its own generator, up to float rounding; a wrong count fails."""
    from spread.model.module import SceneDiffusion, slice_batch

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", tiny(depth=1), bounds=BOUNDS)
    b = random_batch(sizes=(4, 3), m=16, seed=6)
    both = model.sample(b, sampler, generator=[torch.Generator().manual_seed(s) for s in (11, 12)])
    second = {k: v[1:] for k, v in b.items()}
    second = {k: v[:, :3] if k in ("x", "mask", "points", "normals") else v[:, :3, :3] if k in ("spatial", "physical")
              else v for k, v in second.items()}  # alone, without the padding its batch needed
    alone = model.sample(second, sampler, generator=[torch.Generator().manual_seed(12)])
    first = model.sample(slice_batch(b, 1), sampler, generator=[torch.Generator().manual_seed(11)])
    assert torch.allclose(both.translation[1, :3], alone.translation[0], atol=1e-4)
    assert torch.allclose(both.translation[0], first.translation[0], atol=1e-4)
    other = model.sample(second, sampler, generator=[torch.Generator().manual_seed(13)])
    assert not torch.allclose(other.translation, alone.translation, atol=1e-3)
    with pytest.raises(ValueError, match="2 generators for a batch of 1"):
        model.sample(second, sampler, generator=[torch.Generator(), torch.Generator()])


def test_sampler_hooks_and_graph_guidance():
    from spread.model.module import SceneDiffusion

    model = SceneDiffusion("base", tiny(depth=1), bounds=BOUNDS)
    b = random_batch(sizes=(2, 3), m=16)
    calls = []

    def x0_hook(x0, ctx):
        calls.append((ctx.index, ctx.timestep))
        assert x0.shape == (2, 3, 9) and x0.abs().max() <= 1.0
        return x0

    gen = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    plain = model.sample_states(b, "ddim-5", generator=gen())
    hooked = model.sample_states(b, "ddim-5", generator=gen(), x0_hook=x0_hook,
                                 sample_hook=lambda x, ctx: x)
    assert torch.equal(plain, hooked) and [c[0] for c in calls] == list(range(5)) and calls[0][1] == 999
    pinned = model.sample_states(b, "ddim-5", generator=gen(), x0_hook=lambda x0, ctx: torch.zeros_like(x0))
    assert pinned.abs().max() < 1e-5, "a hook on x̂0 steers the sample"
    guided = model.sample_states(b, "ddim-3", generator=gen(), graph_scale=2.0)
    assert torch.isfinite(guided).all() and (guided[0, 2] == 0).all()
    assert Sampler.from_config("dpmsolver++-20") == Sampler("dpmsolver++", 20)
    assert Sampler.from_config({"kind": "ddpm"}).num_steps == 1000
    with pytest.raises(ValueError, match="unknown sampler"):
        Sampler.from_config("euler-5")


# ---- Lightning: dataset, fast_dev_run, checkpoints ------------------------------------------------------

def _scene(lib, rng, scene_id):
    from helpers import scene_of

    def yaw(a):
        return Rotation.from_rotvec([0.0, a, 0.0]).as_matrix()

    tx, tz = rng.uniform(-1.5, 1.5, 2)
    ids, t, R = ["table"], [[tx, 0.375, tz]], [yaw(rng.uniform(0, np.pi))]
    for _ in range(rng.integers(1, 3)):
        ids.append("mug"), t.append([tx + rng.uniform(-0.2, 0.2), 0.80, tz + rng.uniform(-0.1, 0.1)])
        R.append(yaw(rng.uniform(0, 2 * np.pi)))
    for _ in range(rng.integers(1, 3)):
        ids.append("chair"), t.append([rng.uniform(-2.5, 2.5), 0.45, rng.uniform(-2.5, 2.5)])
        R.append(yaw(rng.uniform(0, 2 * np.pi)))
    physical = np.zeros((len(ids),) * 2, np.int8)
    physical[0, [k for k, a in enumerate(ids) if a == "mug"]] = 1
    return scene_of(ids, t, R, library=lib, posed_codes=True, physical=physical, scene_id=scene_id)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    from spread.assets.assemble import box_asset, library_from_specs
    from spread.data import compute_stats, save_stats
    from spread.scene import write_scene

    root = tmp_path_factory.mktemp("model_data")
    lib = library_from_specs(root / "assets", [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("mug", (0.08, 0.1, 0.08), category="mug"),
        box_asset("chair", (0.45, 0.9, 0.45), category="chair", role="furniture"),
    ])
    rng = np.random.default_rng(0)
    scenes = {split: [_scene(lib, rng, f"{split}_{k}") for k in range(n)] for split, n in (("train", 4), ("val", 2))}
    for split, items in scenes.items():
        for s in items:
            write_scene(s, root / split / f"{s.scene_id}.npz")
    save_stats(root / "stats.json", compute_stats(scenes["train"]))
    (root / "manifest.json").write_text(json.dumps({"categories": ["dining_table", "mug", "chair"]}))
    return root


def _trainer(tmp_path, **kwargs):
    import lightning as L

    defaults = dict(accelerator="cpu", devices=1, logger=False, enable_progress_bar=False, enable_model_summary=False,
                    default_root_dir=tmp_path)
    return L.Trainer(**{**defaults, **kwargs})


def test_graph_recall_of_ground_truth_poses(root):
    from spread.data import SceneDataModule, denormalize_translation, load_stats

    dm = SceneDataModule(root, batch_size=4, num_points=256)
    batch = next(iter(dm.train_dataloader()))
    stats = load_stats(root / "stats.json")
    t = denormalize_translation(batch["x"][..., :3], stats)
    R = rot6d_to_matrix(batch["x"][..., 3:])
    correct, pairs = graph_recall(t, R, batch["points"], batch["spatial"], batch["mask"])
    n = batch["num_objects"]
    assert torch.equal(pairs, n * (n - 1)) and torch.equal(correct, pairs), "ground truth poses: recall 1"
    shuffled = graph_recall(t.flip(1), R, batch["points"], batch["spatial"], batch["mask"])[0]
    assert shuffled.sum() < correct.sum()


def test_fast_dev_run_with_datamodule_and_grecall(root, tmp_path):
    from spread.data import SceneDataModule
    from spread.model.module import SceneDiffusion

    dm = SceneDataModule(root, batch_size=2, num_points=M)
    model = SceneDiffusion("geometry", model_config("tiny"), graph_dropout=0.5, sample_every_n_epochs=1, val_sampler="ddim-2",
                           val_sample_scenes=2)
    trainer = _trainer(tmp_path, fast_dev_run=True)
    trainer.fit(model, datamodule=dm)
    metrics = trainer.callback_metrics
    assert {"train/loss", "val/loss", "val/grecall"} <= set(metrics)
    assert all(torch.isfinite(metrics[k]) for k in ("train/loss", "val/loss", "val/grecall"))
    assert model.hparams.bounds == pytest.approx(json.loads((root / "stats.json").read_text())["bounds_translations"])
    assert int(model.ema.num_updates) == 1


@pytest.mark.filterwarnings("ignore:You're resuming from a checkpoint")
def test_checkpoint_round_trip_restores_ema(root, tmp_path):
    from spread.data import SceneDataModule
    from spread.model.module import SceneDiffusion

    dm = SceneDataModule(root, batch_size=2, num_points=M)
    model = SceneDiffusion("geometry", tiny(), lr=1e-3, ema_decay=0.9)
    trainer = _trainer(tmp_path, max_steps=3, limit_val_batches=0, enable_checkpointing=False)
    trainer.fit(model, datamodule=dm)
    path = tmp_path / "model.ckpt"
    trainer.save_checkpoint(path)
    loaded = SceneDiffusion.load_from_checkpoint(path)
    assert int(loaded.ema.num_updates) == 3 and loaded.hparams.config == model.hparams.config
    batch = next(iter(dm.val_dataloader()))
    noise, t = torch.randn(batch["x"].shape), torch.tensor([100, 700])
    model.eval(), loaded.eval()
    with torch.no_grad():
        for name in ("network", "ema"):
            net_a = model.network if name == "network" else model.ema.module
            net_b = loaded.network if name == "network" else loaded.ema.module
            a = model.training_loss(batch, noise, t, network=net_a)
            b = loaded.training_loss(batch, noise, t, network=net_b)
            assert torch.equal(a, b), name
        assert not torch.equal(model.training_loss(batch, noise, t, network=model.network),
                               model.training_loss(batch, noise, t, network=model.ema.module)), "EMA is its own copy"
    same = [model.sample(batch, "ddim-2", generator=torch.Generator().manual_seed(0)).translation,
            loaded.sample(batch, "ddim-2", generator=torch.Generator().manual_seed(0)).translation]
    assert torch.equal(*same)
    # resume: the EMA continues from the checkpoint
    resumed = SceneDiffusion("geometry", tiny(), lr=1e-3, ema_decay=0.9)
    _trainer(tmp_path, max_steps=4, limit_val_batches=0, enable_checkpointing=False).fit(
        resumed, datamodule=dm, ckpt_path=path)
    assert int(resumed.ema.num_updates) == 4


def test_import_needs_no_heavy_optional_modules():
    code = ("import sys, spread.model; spread.model.SceneDiffusion; "
            "print(sorted(m for m in ('pybullet', 'ray', 'wandb', 'trimesh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("heads,queries,bias", [(2, 1, True), (4, 3, True), (1, 2, False)])
def test_attention_over_a_projected_context_never_forms_keys_and_values_and_is_the_same_function(heads, queries, bias):
    """With ``context_proj`` the queries are carried into the raw context's space (Attention.absorbed): in float64
    the output, a key mask's effect and every gradient equal attention over ``to_kv(proj(context))`` formed in full
    (the projection's bias included); and the full keys/values (B, Nk, 2·heads·dim_head) are never made."""
    from torch import nn

    from spread.model.layers import Attention

    torch.manual_seed(0)
    attn, proj = Attention(32, heads=heads, dim_head=8).double(), nn.Linear(6, 32, bias=bias).double()
    with torch.no_grad():
        if bias:
            proj.bias.normal_()
    x, ctx = torch.randn(3, queries, 32, dtype=torch.float64), torch.randn(3, 5, 6, dtype=torch.float64)
    keys = torch.tensor([[1, 1, 1, 1, 1], [1, 0, 1, 0, 0], [0, 0, 0, 0, 1]], dtype=torch.bool)
    for mask in (None, keys):
        fast = attn(x, ctx, key_mask=mask, context_proj=proj)
        grads_fast = torch.autograd.grad(fast.square().sum(), [*attn.parameters(), *proj.parameters()])
        full = attn(x, proj(ctx), key_mask=mask)
        grads_full = torch.autograd.grad(full.square().sum(), [*attn.parameters(), *proj.parameters()])
        assert torch.allclose(fast, full, atol=1e-12, rtol=0)
        for a, b in zip(grads_fast, grads_full):
            assert torch.allclose(a, b, atol=1e-11, rtol=0)
    masked = attn(x, ctx, key_mask=keys, context_proj=proj)  # the mask does something: the last scene sees one key
    assert not torch.allclose(masked[2], attn(x, ctx, context_proj=proj)[2])
    from torch.utils._python_dispatch import TorchDispatchMode

    widest = []  # the channels of every (B, Nk, ·) tensor the call makes

    class Widest(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if isinstance(out, torch.Tensor) and out.dim() == 3 and out.shape[:2] == (3, 5):
                widest.append(out.shape[-1])
            return out

    with torch.no_grad(), Widest():
        attn(x, ctx, context_proj=proj)
    assert max(widest, default=0) < 2 * heads * 8  # no (B, Nk, 2·heads·dim_head) keys/values
