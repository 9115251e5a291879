"""The parts term (spread.model.parts_term): known depths of a box sunk into a board, zero on the training room,
only what a prediction adds, a gradient step that lifts a sunk object, and the term in the training loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from spread.data.parts import asset_part_planes
from spread.model.parts_distance import PartPlanes
from spread.model.parts_term import pair_part_depths, parts_excess


def _board_and_box():
    """Object 0: a board 1 × 0.1 × 1 m (its top at y = 0.05 in its frame); object 1: a 0.2 m cube, sampled at its
    8 corners and 6 face centres. Part planes of both, their canonical points (1, 2, 14, 3), mask."""
    meshes = [trimesh.creation.box(extents=(1.0, 0.1, 1.0)), trimesh.creation.box(extents=(0.2, 0.2, 0.2))]
    arrays = [asset_part_planes([m]) for m in meshes]
    planes, boxes, valid = (torch.from_numpy(np.stack(a))[None] for a in zip(*arrays))
    mask = torch.ones(1, 2, dtype=torch.bool)
    parts = PartPlanes.from_batch({"part_planes": planes, "part_boxes": boxes, "part_valid": valid}, mask)
    corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float32)
    faces = torch.cat([torch.eye(3), -torch.eye(3)])
    cube = torch.cat([corners, faces]) * 0.1
    board = cube * torch.tensor([5.0, 0.5, 5.0])
    return parts, torch.stack([board, cube])[None], mask


def _poses(lift: float):
    """The board at the origin, the cube resting on it raised by ``lift`` metres (negative: sunk)."""
    t = torch.tensor([[[0.0, 0.0, 0.0], [0.1, 0.05 + 0.1 + lift, -0.2]]])
    return t, torch.eye(3).expand(1, 2, 3, 3).clone()


@pytest.mark.parametrize("lift, depth", [(0.0, 0.0), (0.02, 0.0), (-0.03, 0.03), (-0.045, 0.045),
                                         (-0.08, 0.02)])
def test_a_cube_sunk_into_a_board_reads_its_depth_and_resting_or_above_reads_zero(lift, depth):
    # the cube's bottom points sink |lift| into the 10 cm board; the depth is the easiest way out, so a cube sunk
    # 8 cm reads 2 cm (its bottom is 2 cm above the board's underside). The board's points stay outside the cube
    # (the cube stands off the board's centre and edges), so D[board, cube] is 0
    parts, points, mask = _board_and_box()
    t, R = _poses(lift)
    D = pair_part_depths(parts, points, t, R, mask)
    assert D[0, 1, 0].item() == pytest.approx(depth, abs=1e-5)
    assert D[0, 0, 1].item() == 0.0
    assert D[0, 0, 0].item() == 0.0 and D[0, 1, 1].item() == 0.0


def test_the_training_room_costs_nothing_and_a_prediction_pays_only_what_it_adds():
    parts, points, mask = _board_and_box()
    t_true, R = _poses(-0.01)  # the training room itself has the cube 1 cm in
    assert parts_excess(parts, points, t_true, R, t_true, R, mask).item() == 0.0
    t_pred, _ = _poses(-0.04)
    # 3 cm more than the room's 1 cm, over 2 objects
    assert parts_excess(parts, points, t_pred, R, t_true, R, mask).item() == pytest.approx(0.03 / 2, abs=1e-5)
    t_up, _ = _poses(0.05)
    assert parts_excess(parts, points, t_up, R, t_true, R, mask).item() == 0.0


def test_a_gradient_step_on_the_term_lifts_the_sunk_cube_and_leaves_the_board():
    parts, points, mask = _board_and_box()
    t_true, R = _poses(0.0)
    t, _ = _poses(-0.03)  # (at 5 cm, the board's mid-plane, both ways out tie and their gradients cancel)
    t = t.clone().requires_grad_(True)
    parts_excess(parts, points, t, R, t_true, R, mask).sum().backward()
    # descent moves the cube up (−grad_y > 0) and pushes the board down by the same, nothing sideways
    assert t.grad[0, 1, 1].item() < 0 and t.grad[0, 0, 1].item() > 0
    assert torch.allclose(t.grad[0, :, [0, 2]], torch.zeros(2, 2), atol=1e-6)
    R = R.clone().requires_grad_(True)
    parts_excess(parts, points, t.detach(), R, t_true, R.detach(), mask).sum().backward()
    assert torch.isfinite(R.grad).all()


def test_padding_objects_and_pairs_apart_read_zero_with_a_gradient_graph_kept():
    parts, points, mask = _board_and_box()
    t, R = _poses(0.3)
    t = t.requires_grad_(True)
    D = pair_part_depths(parts, points, t, R, mask)
    assert (D == 0).all()
    D.sum().backward()  # nothing inside: still differentiable, a zero gradient
    assert (t.grad == 0).all()
    t2, _ = _poses(-0.05)
    assert (pair_part_depths(parts, points, t2, R, torch.tensor([[True, False]])) == 0).all()


def test_the_parts_term_joins_the_training_loss_with_its_weight_and_needs_the_part_planes():
    from spread.model.module import SceneDiffusion
    from spread.model.poses import poses_from_state

    from test_penetration import _batch, _tiny_model

    torch.manual_seed(0)
    batch = _batch()
    parts = [trimesh.creation.box(extents=e.tolist()) for e in batch["extents"][0]]
    arrays = [asset_part_planes([m]) for m in parts]
    planes, boxes, valid = (torch.from_numpy(np.stack(a))[None].expand(2, *np.stack(a).shape).clone()
                            for a in zip(*arrays))
    batch.update(part_planes=planes, part_boxes=boxes, part_valid=valid)
    noise, t = torch.randn(2, 3, 9) * batch["mask"][..., None], torch.tensor([10, 400])
    base = _tiny_model(0.0)
    model = SceneDiffusion("base", base.config, bounds=[-3, 0, -3, 3, 2.5, 3], prediction="v_prediction",
                           parts_weight=3.0)
    # a network whose x̂_0 is the training room with object 1 pushed 30 cm (0.1 in normalised x) into object 0
    x0, keep = batch["x"], batch["mask"][..., None].float()
    target = x0.clone()
    target[:, 1, 0] -= 0.1
    a = model.alpha_bar(t).float()[:, None, None]
    x_t = a.sqrt() * x0 + (1 - a).sqrt() * noise
    v = (a.sqrt() * x_t - target) / (1 - a).sqrt() * keep  # v-prediction: x̂_0 = √ᾱ x_t − √(1 − ᾱ) v
    model.network.forward = lambda *args, **kwargs: v
    terms = model.training_terms(batch, noise, t)
    assert set(terms) == {"mse", "parts"}
    bounds = torch.tensor([-3, 0, -3, 3, 2.5, 3.0])
    per_scene = parts_excess(PartPlanes.from_batch(batch, batch["mask"]), batch["points"],
                             *poses_from_state(target, bounds), *poses_from_state(x0, bounds), batch["mask"])
    assert (per_scene > 0.01).all()
    assert terms["parts"].item() == pytest.approx((per_scene * a[:, 0, 0]).mean().item(), rel=1e-4)
    total = model.training_loss(batch, noise, t)
    assert total.item() == pytest.approx((terms["mse"] + 3.0 * terms["parts"]).item(), rel=1e-5)
    # off by default; refused below zero by name; a batch without the part planes is refused, naming the setting
    assert set(base.training_terms(batch, noise, t)) == {"mse"}
    with pytest.raises(ValueError, match="parts_weight"):
        SceneDiffusion("base", base.config, parts_weight=-1.0)
    del batch["part_planes"]
    with pytest.raises(ValueError, match=r"geometry_distance=parts: the batch has no \['part_planes'"):
        model.training_terms(batch, noise, t)
