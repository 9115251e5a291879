"""The penetration-aware training term (spread.model.penetration): box depths by known answers and invariances,
the excess over the training scene, and its place in SceneDiffusion's loss."""

import math

import pytest
import torch

from spread.model.diffusion import PREDICTIONS, prediction_target, x0_from_prediction
from spread.model.penetration import box_depths, penetration_excess


def yaw(theta: float) -> torch.Tensor:
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def scene(translations, rotations, extents):
    t = torch.tensor(translations, dtype=torch.float64)[None]
    r = torch.stack(rotations)[None]
    e = torch.tensor(extents, dtype=torch.float64)[None]
    return t, r, e


def test_axis_aligned_boxes_overlap_by_the_interval_overlap_and_apart_boxes_by_minus_the_gap():
    eye = torch.eye(3, dtype=torch.float64)
    t, r, e = scene([[0, 0, 0], [0.8, 0.1, 0]], [eye, eye], [[1, 1, 1], [1, 1, 1]])
    assert box_depths(t, r, e)[0, 0, 1].item() == pytest.approx(0.2)  # x: 1 − 0.8 beats y: 1 − 0.1
    t, r, e = scene([[0, 0, 0], [1.3, 0, 0]], [eye, eye], [[1, 1, 1], [1, 1, 1]])
    assert box_depths(t, r, e)[0, 0, 1].item() == pytest.approx(-0.3)
    # a book resting 2 cm into a 1 m table top: depth = the sinking
    t, r, e = scene([[0, 0.5, 0], [0.1, 1.03 - 0.02, 0]], [eye, eye], [[1.2, 1.0, 0.8], [0.2, 0.06, 0.3]])
    assert box_depths(t, r, e)[0, 0, 1].item() == pytest.approx(0.02)


def test_a_box_turned_by_45_degrees_meets_its_known_answer():
    """Unit cube at the origin, another turned 45° about y at x = 1.1: the world x axis separates least,
    overlap 0.5 + 0.5√2 − 1.1."""
    eye = torch.eye(3, dtype=torch.float64)
    t, r, e = scene([[0, 0, 0], [1.1, 0, 0]], [eye, yaw(math.pi / 4)], [[1, 1, 1], [1, 1, 1]])
    depth = box_depths(t, r, e)
    assert depth[0, 0, 1].item() == pytest.approx(0.5 + 0.5 * math.sqrt(2) - 1.1)
    assert torch.allclose(depth[0, 0, 1], depth[0, 1, 0])  # symmetric


def test_depths_do_not_change_when_the_whole_room_moves_and_turns():
    g = torch.Generator().manual_seed(0)
    t = torch.rand(1, 5, 3, generator=g, dtype=torch.float64) * 2
    r = torch.stack([yaw(float(a)) for a in torch.rand(5, generator=g) * 6])[None]
    tilt = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.1], [0.3, 0, -0.2], [-0.1, 0.2, 0]], dtype=torch.float64))
    r = tilt @ r  # general rotations, not only yaw
    e = 0.3 + torch.rand(1, 5, 3, generator=g, dtype=torch.float64)
    q = yaw(1.234) @ torch.linalg.matrix_exp(torch.tensor([[0, 0, 0.4], [0, 0, 0], [-0.4, 0, 0]], dtype=torch.float64))
    moved = torch.einsum("ij,bnj->bni", q, t) + torch.tensor([3.0, -1.0, 2.0], dtype=torch.float64)
    before, after = box_depths(t, r, e), box_depths(moved, q @ r, e)
    off = ~torch.eye(5, dtype=torch.bool)
    assert torch.allclose(before[0][off], after[0][off], atol=1e-12)
    assert (before[0][off] > 0).any() and (before[0][off] < 0).any()  # both overlapping and apart pairs seen


def test_excess_is_zero_on_the_training_scene_and_counts_only_overlap_beyond_it():
    eye = torch.eye(3, dtype=torch.float64)
    # a chair (0, 1) tucked under a table: the boxes overlap by 0.1 m in the real room, and a far object (2)
    ref_t = torch.tensor([[[0, 0.4, 0], [0.6, 0.3, 0], [5, 0.5, 5]]], dtype=torch.float64)
    rot = torch.stack([eye, eye, eye])[None]
    ext = torch.tensor([[[1.0, 0.8, 1.0], [0.4, 0.6, 0.4], [1, 1, 1]]], dtype=torch.float64)
    mask = torch.ones(1, 3, dtype=torch.bool)
    assert penetration_excess(ref_t, rot, ref_t, rot, ext, mask).item() == 0.0
    # the chair pushed 0.05 m further in along x: only the 0.05 beyond the room's overlap counts, / 3 objects
    pushed = ref_t.clone()
    pushed[0, 1, 0] -= 0.05
    assert penetration_excess(pushed, rot, ref_t, rot, ext, mask).item() == pytest.approx(0.05 / 3)
    # pulled out: no cost; a padding object on top of everything: no cost
    pulled = ref_t.clone()
    pulled[0, 1, 0] += 0.2
    assert penetration_excess(pulled, rot, ref_t, rot, ext, mask).item() == 0.0
    assert penetration_excess(pushed, rot, ref_t, rot, ext, torch.tensor([[True, False, True]])).item() == 0.0


def test_a_supported_object_costs_alpha_times_its_gap_when_it_floats_and_its_sinking_when_it_sinks():
    eye = torch.eye(3, dtype=torch.float64)
    rot = torch.stack([eye, eye])[None]
    ext = torch.tensor([[[1.2, 1.0, 0.8], [0.2, 0.06, 0.3]]], dtype=torch.float64)  # table, book
    mask = torch.ones(1, 2, dtype=torch.bool)
    resting = torch.tensor([[[0, 0.5, 0], [0.1, 1.03, 0]]], dtype=torch.float64)
    supports = torch.tensor([[[False, True], [False, False]]])  # the table (0) supports the book (1)
    for lift, cost in ((0.04, 0.25 * 0.04), (-0.02, 0.02), (0.0, 0.0)):  # α = 0.25 of a gap, all of a sinking
        moved = resting.clone()
        moved[0, 1, 1] += lift
        got = penetration_excess(moved, rot, resting, rot, ext, mask, supports, gap_weight=0.25).item()
        assert got == pytest.approx(cost / 2), lift  # / 2 objects
    # α = 0, or without the relation, a floating book costs nothing (only overlap beyond the room's counts)
    floating = resting.clone()
    floating[0, 1, 1] += 0.04
    assert penetration_excess(floating, rot, resting, rot, ext, mask).item() == 0.0
    assert penetration_excess(floating, rot, resting, rot, ext, mask, supports).item() == 0.0
    # the relation counts whichever way round it is written
    assert penetration_excess(floating, rot, resting, rot, ext, mask, supports.transpose(1, 2),
                              gap_weight=1.0).item() == pytest.approx(0.02)


def test_a_gradient_step_on_the_excess_moves_the_boxes_apart():
    eye = torch.eye(3, dtype=torch.float64)
    ref = torch.tensor([[[0, 0, 0], [2, 0, 0]]], dtype=torch.float64)
    t = torch.tensor([[[0, 0, 0], [0.7, 0.05, 0.02]]], dtype=torch.float64, requires_grad=True)
    rot = torch.stack([eye, eye])[None]
    ext = torch.ones(1, 2, 3, dtype=torch.float64)
    mask = torch.ones(1, 2, dtype=torch.bool)
    loss = penetration_excess(t, rot, ref, rot, ext, mask).sum()
    loss.backward()
    assert t.grad[0, 1, 0] < 0 < t.grad[0, 0, 0]  # descending the loss moves object 1 along +x, object 0 along −x
    after = penetration_excess(t.detach() - 0.1 * t.grad, rot, ref, rot, ext, mask)
    assert after.item() < loss.item()


@pytest.mark.parametrize("prediction", PREDICTIONS)
def test_x0_from_each_prediction_gives_back_the_clean_state(prediction):
    g = torch.Generator().manual_seed(1)
    x0, noise = torch.randn(3, 4, 9, generator=g), torch.randn(3, 4, 9, generator=g)
    alpha_bar = torch.tensor([0.9, 0.5, 0.02], dtype=torch.float64)
    a = alpha_bar.float()[:, None, None]
    x_t = a.sqrt() * x0 + (1 - a).sqrt() * noise
    output = prediction_target(prediction, x0, noise, alpha_bar)
    assert torch.allclose(x0_from_prediction(prediction, output, x_t, alpha_bar), x0, atol=1e-4)


def _tiny_model(weight: float, root=None):
    from spread.model.module import SceneDiffusion

    cfg = {"dim": 32, "depth": 1, "heads": 2, "dim_head": 8, "edge_dim": 16, "cond_dim": 32, "index_dim": 8,
           "shape_tokens": 4, "shape_dim": 16, "tokenizer_width": 16, "tokenizer_points": 32, "num_points": 32,
           "num_latents": 4}
    return SceneDiffusion("base", cfg, bounds=[-3, 0, -3, 3, 2.5, 3], prediction="v_prediction",
                          penetration_weight=weight)


def _batch():
    """Two scenes of 3 boxes, the second with padding; object states from real poses."""
    from spread.data.rotation import matrix_to_rot6d

    g = torch.Generator().manual_seed(3)
    rot = torch.stack([yaw(a) for a in (0.0, 0.5, 1.0)]).float()
    trans = torch.tensor([[0.0, 0.4, 0.0], [0.6, 0.3, 0.0], [-1.0, 0.5, 1.0]])
    normalised = trans / 3.0  # x, z in [−3, 3] m
    normalised[:, 1] = trans[:, 1] / 2.5 * 2 - 1  # y in [0, 2.5] m
    x = torch.cat([normalised, matrix_to_rot6d(rot)], -1)
    mask = torch.tensor([[True, True, True], [True, True, False]])
    return {"x": torch.stack([x, x * mask[1, :, None]]), "mask": mask,
            "spatial": torch.zeros(2, 3, 3, dtype=torch.long), "physical": torch.zeros(2, 3, 3, dtype=torch.long),
            "mount": torch.zeros(2, 3, dtype=torch.long), "asset_index": torch.zeros(2, 3, dtype=torch.long),
            "shape_index": torch.zeros(2, 3, dtype=torch.long), "category_index": torch.zeros(2, 3, dtype=torch.long),
            "points": torch.randn(2, 3, 32, 3, generator=g) * 0.2, "normals": torch.randn(2, 3, 32, 3, generator=g),
            "extents": torch.tensor([[[1.0, 0.8, 1.0], [0.4, 0.6, 0.4], [0.5, 0.5, 0.5]]]).expand(2, 3, 3).clone()}


def test_the_training_loss_adds_the_weighted_penetration_term_and_val_loss_stays_the_mse():
    torch.manual_seed(0)
    model = _tiny_model(2.0)
    batch = _batch()
    noise = torch.randn(2, 3, 9)
    t = torch.tensor([10, 400])
    terms = model.training_terms(batch, noise, t)
    assert set(terms) == {"mse", "penetration"} and terms["penetration"].item() >= 0
    total = model.training_loss(batch, noise, t)
    assert total.item() == pytest.approx(terms["mse"].item() + 2.0 * terms["penetration"].item(), rel=1e-5)
    assert model.training_loss(batch, noise, t, penetration=False).item() == pytest.approx(terms["mse"].item(), rel=1e-6)
    total.backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.network.parameters())
    # off by default: the paper's loss is the MSE alone
    assert set(_tiny_model(0.0).training_terms(batch, noise, t)) == {"mse"}


def test_a_negative_penetration_weight_is_refused_by_name():
    from spread.model.module import SceneDiffusion

    with pytest.raises(ValueError, match="penetration_weight"):
        _tiny_model(-1.0)
    with pytest.raises(ValueError, match="support_gap_weight"):
        SceneDiffusion("base", _tiny_model(0.0).config, support_gap_weight=-0.5)
