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
