"""The geometry summary (``model.config.geometry_summary``): each object's own geometric state read from its points'
signed distances, known answers, and a node input that starts at zero and then carries the geometry."""

from __future__ import annotations

import pytest
import torch

from spread.model import SceneDenoiser
from spread.model.perceiver import DISTANCE_SCALES, SUMMARY_DIM, object_summary

from test_model import BOUNDS, pad_with_junk, random_batch, tiny


def test_the_summary_reads_the_deepest_point_the_shares_and_where_an_object_penetrates_and_touches():
    # one object of 4 points: two inside another object (3 cm and 1 cm deep) at its bottom, one 5 mm off (in
    # contact), one far (the 10 cm range)
    points = torch.tensor([[[[0.0, -0.5, 0.0], [0.2, -0.5, 0.0], [0.0, 0.5, 0.3], [0.0, 0.5, -0.3]]]])
    d = torch.tensor([[[-0.03, -0.01, 0.005, 0.1]]])
    s = object_summary(d, points)[0, 0]
    assert s.shape == (SUMMARY_DIM,)
    assert s[0].item() == pytest.approx(-0.03) and s[1].item() == 1.0
    assert torch.allclose(s[2:2 + len(DISTANCE_SCALES)], torch.tanh(-0.03 / torch.tensor(DISTANCE_SCALES)))
    k = 2 + len(DISTANCE_SCALES)
    assert s[k].item() == pytest.approx(0.5) and s[k + 1].item() == pytest.approx(0.75)  # inside; within 1 cm
    # depth-weighted: (3 × (0, −0.5, 0) + 1 × (0.2, −0.5, 0)) / 4 — it penetrates at its bottom, toward +x a little
    assert torch.allclose(s[k + 2:k + 5], torch.tensor([0.05, -0.5, 0.0]), atol=1e-6)
    w = torch.exp(-torch.tensor([0.0, 0.0, 0.005, 0.1]) / 0.02)
    assert torch.allclose(s[k + 5:k + 8], (w[:, None] * points[0, 0]).sum(0) / w.sum(), atol=1e-6)
    # nothing inside: the penetration's position is 0, not NaN; the deepest point is clipped at 25 cm
    apart = object_summary(torch.full((1, 1, 4), 0.1), points)[0, 0]
    assert torch.isfinite(apart).all() and (apart[k + 2:k + 5] == 0).all() and apart[1].item() == 0.0
    assert object_summary(torch.full((1, 1, 4), -0.4), points)[0, 0, 0].item() == pytest.approx(-0.25)


def test_a_summary_model_starts_as_the_model_without_it_and_then_reads_the_geometry():
    torch.manual_seed(0)
    plain = SceneDenoiser(tiny(), "geometry", BOUNDS).eval()
    summary = SceneDenoiser(tiny(geometry_summary=True), "geometry", BOUNDS).eval()
    assert set(summary.state_dict()) - set(plain.state_dict()) == {"summary_in.weight", "summary_in.bias"}
    with torch.no_grad():
        plain.denoiser.head[-1].weight.normal_()  # zero at initialisation: every output would be 0
    summary.load_state_dict({**summary.state_dict(), **plain.state_dict()})
    b = random_batch(sizes=(3, 5), seed=4)
    t = torch.tensor([10, 300])
    x_t = b["x"] + 0.05 * torch.randn_like(b["x"]) * b["mask"][..., None]
    with torch.no_grad():
        assert torch.equal(summary(x_t, t, summary.condition(b)), plain(x_t, t, plain.condition(b)))
        summary.summary_in.weight.normal_()
        eps = summary(x_t, t, summary.condition(b))
        assert not torch.allclose(eps, plain(x_t, t, plain.condition(b)), atol=1e-4)
        # padding still never changes the real objects' outputs
        padded = pad_with_junk(b, extra=2)
        x_junk = torch.cat([x_t, torch.randn(2, 2, 9) * 3], 1)
        eps2 = summary(x_junk, t, summary.condition(padded))
    assert torch.allclose(eps2[:, :5][b["mask"]], eps[b["mask"]], atol=1e-5)
    with pytest.raises(TypeError):
        tiny(geometry_summary=True, no_such_field=1)


def test_self_conditioned_geometry_poses_the_scene_at_the_networks_clean_estimate():
    """``geometry_at=x0_hat``: the output is the network's second pass with the geometry of the scene posed at its
    own first-pass x̂_0 (clipped to ±1, zero at padding); the first pass carries no gradient; sampling does the same
    at every step. A bad value is named."""
    from spread.model import SceneDiffusion
    from spread.model.diffusion import x0_from_prediction

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", tiny(geometry_at="x0_hat", geometry_summary=True), bounds=BOUNDS).eval()
    with torch.no_grad():
        model.network.denoiser.head[-1].weight.normal_()
        model.network.summary_in.weight.normal_()
    net = model.network
    b = random_batch(sizes=(3, 5), seed=4)
    t = torch.tensor([10, 300])
    x_t = b["x"] + 0.05 * torch.randn_like(b["x"]) * b["mask"][..., None]
    cond = net.condition(b)
    with torch.no_grad():
        first = net(x_t, t, cond)
        pose = x0_from_prediction("epsilon", first, x_t, model.alpha_bar(t)).clamp(-1, 1) * b["mask"][..., None]
        expected = net(x_t, t, cond, pose=pose)
        got = model.network_output(net, x_t, t, cond)
        at_x_t = net(x_t, t, cond)
    assert torch.allclose(got, expected, atol=1e-6) and not torch.allclose(got, at_x_t, atol=1e-4)
    # the same weights with the release's x_t: the one-pass output
    plain = SceneDiffusion("geometry", tiny(geometry_summary=True), bounds=BOUNDS).eval()
    plain.network.load_state_dict(net.state_dict())
    with torch.no_grad():
        assert torch.allclose(plain.network_output(plain.network, x_t, t, plain.network.condition(b)), at_x_t, atol=1e-6)
    # training: a gradient through the second pass only, and a finite loss
    model.train()
    calls = []
    hook = net.perceiver.register_forward_hook(lambda m, i, o: calls.append(torch.is_grad_enabled()))
    loss = model.training_loss({**b, "extents": torch.ones(2, 5, 3) * 0.3}, timesteps=t, pose_terms=False)
    hook.remove()
    loss.backward()
    assert calls == [False, True] and torch.isfinite(loss)
    assert net.summary_in.weight.grad is not None and net.summary_in.weight.grad.abs().sum() > 0
    # sampling: two passes a step
    model.eval()
    calls.clear()
    sampled = model.ema.module if model.ema is not None else net  # sampling reads the EMA weights
    hook = sampled.perceiver.register_forward_hook(lambda m, i, o: calls.append(1))
    model.sample_states(b, {"kind": "ddim", "steps": 3})
    hook.remove()
    assert len(calls) == 2 * 3
    with pytest.raises(ValueError, match=r"model\.config\.geometry_at='x_0'"):
        SceneDenoiser(tiny(geometry_at="x_0"), "geometry", BOUNDS)
