"""The penetration-aware training term (spread.model.penetration): box depths by known answers and invariances,
the excess over the training scene, and its place in SceneDiffusion's loss."""

import math

import pytest
import torch

from spread.model.diffusion import PREDICTIONS, prediction_target, x0_from_prediction
from spread.model.penetration import box_depths, penetration_excess, support_error, upper_depths


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


def test_the_upper_pairs_are_the_matrix_above_its_diagonal_and_the_matrix_is_symmetric():
    from spread.data.rotation import rot6d_to_matrix

    g = torch.Generator().manual_seed(0)
    t = torch.randn(2, 6, 3, generator=g, dtype=torch.float64)
    r = rot6d_to_matrix(torch.randn(2, 6, 6, generator=g, dtype=torch.float64))
    e = torch.rand(2, 6, 3, generator=g, dtype=torch.float64) + 0.2
    full = box_depths(t, r, e)
    i, j = torch.triu_indices(6, 6, 1)
    assert torch.equal(upper_depths(t, r, e), full[:, i, j])
    assert torch.allclose(full, full.transpose(1, 2))


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


def _table_and_book():
    eye = torch.eye(3, dtype=torch.float64)
    rot = torch.stack([eye, eye])[None]
    ext = torch.tensor([[[1.2, 1.0, 0.8], [0.2, 0.06, 0.3]]], dtype=torch.float64)  # table, book
    mask = torch.ones(1, 2, dtype=torch.bool)
    resting = torch.tensor([[[0, 0.5, 0], [0.1, 1.03, 0]]], dtype=torch.float64)
    supports = torch.tensor([[[False, True], [False, False]]])  # the table (0) supports the book (1)
    return rot, ext, mask, resting, supports


def test_a_supported_object_pays_its_rest_height_error_both_ways_and_its_overhang():
    rot, ext, mask, resting, supports = _table_and_book()
    for lift, cost in ((0.04, 0.04), (-0.02, 0.02), (0.0, 0.0)):  # floating and sinking alike, metres
        moved = resting.clone()
        moved[0, 1, 1] += lift
        assert support_error(moved, rot, resting, rot, ext, mask, supports).item() == pytest.approx(cost / 2), lift
    # sliding along the table costs nothing until the book's centre leaves the table's footprint (half x 0.6 m)
    slid = resting.clone()
    slid[0, 1, 0] = 0.55
    assert support_error(slid, rot, resting, rot, ext, mask, supports).item() == 0.0
    slid[0, 1, 0] = 0.75
    assert support_error(slid, rot, resting, rot, ext, mask, supports).item() == pytest.approx(0.15 / 2)
    # the same footprint in the table's own frame: turned 90° its x half extent lies along world z (0.6 m)
    turned = torch.stack([torch.eye(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)])[None].clone()
    turned[0, 0] = yaw(math.pi / 2).double()
    along_z = resting.clone()
    along_z[0, 1, 0], along_z[0, 1, 2] = 0.0, 0.55
    assert support_error(along_z, turned, along_z, turned, ext, mask, supports).item() == 0.0
    along_z_out = along_z.clone()
    along_z_out[0, 1, 2] = 0.75
    assert support_error(along_z_out, turned, along_z, turned, ext, mask, supports).item() == pytest.approx(0.15 / 2)
    # no relation, or the book padding: nothing
    floating = resting.clone()
    floating[0, 1, 1] += 0.04
    assert support_error(floating, rot, resting, rot, ext, mask, torch.zeros_like(supports)).item() == 0.0
    assert support_error(floating, rot, resting, rot, ext, torch.tensor([[True, False]]), supports).item() == 0.0


def test_a_book_on_a_shelf_board_inside_a_tall_case_is_held_at_its_own_board():
    """The rest height is measured from the supporter's centre against the training room's, so a book on the
    lower board of a 2 m bookcase (inside the case's box) is neither lifted to the top nor pulled down."""
    eye = torch.eye(3, dtype=torch.float64)
    rot = torch.stack([eye, eye])[None]
    ext = torch.tensor([[[0.8, 2.0, 0.35], [0.2, 0.3, 0.25]]], dtype=torch.float64)
    mask = torch.ones(1, 2, dtype=torch.bool)
    on_board = torch.tensor([[[0, 1.0, 0], [0, 0.55, 0.05]]], dtype=torch.float64)  # board at 0.40 m, book 0.40–0.70
    supports = torch.tensor([[[False, True], [False, False]]])
    assert support_error(on_board, rot, on_board, rot, ext, mask, supports).item() == 0.0
    lifted = on_board.clone()
    lifted[0, 1, 1] = 1.85  # out of the top of the case: box overlap would be 0 here, the support term is not
    assert support_error(lifted, rot, on_board, rot, ext, mask, supports).item() == pytest.approx(1.3 / 2)
    # the box-overlap term alone rewards that lift (less overlap than the room's): why the support term is there
    assert penetration_excess(lifted, rot, on_board, rot, ext, mask).item() == 0.0
    pushed_in = on_board.clone()
    pushed_in[0, 1, 2] = 0.0  # pushed 5 cm deeper into the case, at its board's height: the box term charges it
    assert support_error(pushed_in, rot, on_board, rot, ext, mask, supports).item() == 0.0
    assert penetration_excess(pushed_in, rot, on_board, rot, ext, mask).item() == pytest.approx(0.05 / 2)


def test_a_gradient_step_on_the_support_error_brings_a_floating_object_down():
    rot, ext, mask, resting, supports = _table_and_book()
    t = resting.clone()
    t[0, 1, 1] += 0.05
    t.requires_grad_(True)
    r = rot.clone().requires_grad_(True)
    support_error(t, r, resting, rot, ext, mask, supports).sum().backward()
    assert t.grad[0, 1, 1] > 0  # descending: the book moves down
    assert torch.all(t.grad[0, 0] == 0)  # and the table is not moved by what it supports
    assert r.grad is None or torch.all(r.grad == 0)  # nor is the book tipped over to lower its lowest point


def test_the_support_quantile_weighs_sinking_against_floating():
    rot, ext, mask, resting, supports = _table_and_book()
    for lift, q, cost in ((0.04, 0.8, 0.4 * 0.04), (-0.02, 0.8, 1.6 * 0.02), (0.04, 0.5, 0.04), (-0.02, 0.2, 0.4 * 0.02)):
        moved = resting.clone()
        moved[0, 1, 1] += lift
        got = support_error(moved, rot, resting, rot, ext, mask, supports, quantile=q).item()
        assert got == pytest.approx(cost / 2), (lift, q)
    with pytest.raises(ValueError, match="quantile"):
        support_error(resting, rot, resting, rot, ext, mask, supports, quantile=1.0)


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


def _tiny_model(weight: float, root=None, support: float = 0.0):
    from spread.model.module import SceneDiffusion

    cfg = {"dim": 32, "depth": 1, "heads": 2, "dim_head": 8, "edge_dim": 16, "cond_dim": 32, "index_dim": 8,
           "shape_tokens": 4, "shape_dim": 16, "tokenizer_width": 16, "tokenizer_points": 32, "num_points": 32,
           "num_latents": 4}
    return SceneDiffusion("base", cfg, bounds=[-3, 0, -3, 3, 2.5, 3], prediction="v_prediction",
                          penetration_weight=weight, support_weight=support)


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
    assert model.training_loss(batch, noise, t, pose_terms=False).item() == pytest.approx(terms["mse"].item(), rel=1e-6)
    total.backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.network.parameters())
    # off by default: the paper's loss is the MSE alone
    assert set(_tiny_model(0.0).training_terms(batch, noise, t)) == {"mse"}


def test_the_support_term_joins_the_loss_with_its_weight_beside_the_penetration_term():
    torch.manual_seed(0)
    batch = _batch()
    batch["physical"][:, 0, 1] = 1  # object 0 supports object 1 (physical code 1)
    noise = torch.randn(2, 3, 9)
    t = torch.tensor([10, 400])
    both = _tiny_model(2.0, support=0.5)
    terms = both.training_terms(batch, noise, t)
    assert set(terms) == {"mse", "penetration", "support"} and terms["support"].item() > 0
    total = both.training_loss(batch, noise, t)
    expected = terms["mse"] + 2.0 * terms["penetration"] + 0.5 * terms["support"]
    assert total.item() == pytest.approx(expected.item(), rel=1e-5)
    # the same network with the support term off: the same MSE and penetration, no support term
    alone = _tiny_model(2.0)
    alone.network.load_state_dict(both.network.state_dict())
    only = alone.training_terms(batch, noise, t)
    assert set(only) == {"mse", "penetration"}
    assert only["mse"].item() == pytest.approx(terms["mse"].item(), rel=1e-6)
    assert only["penetration"].item() == pytest.approx(terms["penetration"].item(), rel=1e-6)
    # and without the relation, the support term is zero
    batch["physical"][:, 0, 1] = 0
    assert both.training_terms(batch, noise, t)["support"].item() == 0.0


def test_a_checkpoint_saved_with_the_retired_support_gap_weight_still_loads():
    from spread.model.module import SceneDiffusion

    model = _tiny_model(0.3)
    hparams = {**dict(model.hparams), "support_gap_weight": 0.0}
    loaded = SceneDiffusion.from_checkpoint({"hyper_parameters": hparams, "state_dict": model.state_dict()})
    assert "support_gap_weight" not in loaded.hparams and loaded.hparams["support_weight"] == 0.0
    with pytest.warns(UserWarning, match="support_gap_weight=1.0 is retired"):
        SceneDiffusion.from_checkpoint({"hyper_parameters": {**hparams, "support_gap_weight": 1.0},
                                        "state_dict": model.state_dict()})


def test_a_negative_penetration_weight_is_refused_by_name():
    from spread.model.module import SceneDiffusion

    with pytest.raises(ValueError, match="penetration_weight"):
        _tiny_model(-1.0)
    with pytest.raises(ValueError, match="support_weight"):
        SceneDiffusion("base", _tiny_model(0.0).config, support_weight=-0.5)
    with pytest.raises(ValueError, match="support_quantile"):
        SceneDiffusion("base", _tiny_model(0.0).config, support_quantile=0.0)
