"""The relation-aware training term (spread.model.spatial_term): violations by known answers, agreement with the
spatial codes GRecall counts, the excess over the training scene, and its place in SceneDiffusion's loss."""

import math

import pytest
import torch

from spread.box_geometry import box_size
from spread.model.spatial_term import spatial_excess, spatial_violation
from spread.relations import spatial_codes
from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF,
)
from test_penetration import _batch, _tiny_model, yaw

SIX = (SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_FRONT, SPATIAL_BEHIND, SPATIAL_ABOVE, SPATIAL_BELOW)


def two(t_i, t_j, h_i=(0.4, 0.4, 0.4), h_j=(0.4, 0.4, 0.4)):
    t = torch.tensor([t_i, t_j], dtype=torch.float64)[None]
    r = torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3)
    return t, r, torch.tensor([h_i, h_j], dtype=torch.float64)[None]


def violation_of(code, t, r, e):
    spatial = torch.full((1, 2, 2), SPATIAL_SELF)
    spatial[0, 0, 1] = code
    return spatial_violation(t, r, e, spatial)[0, 0, 1].item()


def test_a_pair_due_east_is_right_of_at_no_cost_and_every_other_sector_costs_its_distance_to_the_sectors_edge_line():
    t, r, e = two((2.0, 0.2, 0.0), (0.0, 0.2, 0.0))  # d = t_i − t_j = (2, 0, 0): θ = 0, "right of"
    assert violation_of(SPATIAL_RIGHT, t, r, e) == 0.0
    assert violation_of(SPATIAL_FRONT, t, r, e) == pytest.approx(2 / math.sqrt(2))
    assert violation_of(SPATIAL_BEHIND, t, r, e) == pytest.approx(2 / math.sqrt(2))
    # the opposite sector: the distance to its edge lines' extension through the apex, not to the apex
    assert violation_of(SPATIAL_LEFT, t, r, e) == pytest.approx(2 / math.sqrt(2))
    # side by side on the floor: "above" costs the xz distance of the nearer centre outside the other's footprint
    # (2 − 0.2) plus the height i's bottom (0) must rise to j's top less the tolerance (0.4 − 0.005)
    assert violation_of(SPATIAL_ABOVE, t, r, e) == pytest.approx(1.8 + 0.395)
    # d = (1, 0, 3): θ = 71.6°, "in front of"; the right sector's edge line x = z is (3 − 1)/√2 away
    t, r, e = two((1.0, 0.2, 3.0), (0.0, 0.2, 0.0))
    assert violation_of(SPATIAL_FRONT, t, r, e) == 0.0
    assert violation_of(SPATIAL_RIGHT, t, r, e) == pytest.approx(2 / math.sqrt(2))


def test_a_box_sunk_into_the_one_it_should_stand_on_costs_its_depth_beyond_the_tolerance():
    table = (1.0, 0.8, 1.0)
    on_top = two((0.1, 0.9, 0.0), (0.0, 0.4, 0.0), h_i=(0.2, 0.2, 0.2), h_j=table)  # bottom 0.8 = the top
    assert violation_of(SPATIAL_ABOVE, *on_top) == 0.0
    sunk = two((0.1, 0.8, 0.0), (0.0, 0.4, 0.0), h_i=(0.2, 0.2, 0.2), h_j=table)  # bottom 0.7: 10 cm in
    assert violation_of(SPATIAL_ABOVE, *sunk) == pytest.approx(0.1 - 0.005)
    # beside the table at its top's height: 0.2 m of xz centre distance outside the footprint (centre at x 0.7)
    beside = two((0.7, 0.9, 0.0), (0.0, 0.4, 0.0), h_i=(0.2, 0.2, 0.2), h_j=table)
    assert violation_of(SPATIAL_ABOVE, *beside) == pytest.approx(0.2)
    # the table is below the book: the same pair seen the other way round
    t, r, e = sunk
    spatial = torch.full((1, 2, 2), SPATIAL_SELF)
    spatial[0, 1, 0] = SPATIAL_BELOW
    assert spatial_violation(t, r, e, spatial)[0, 1, 0].item() == pytest.approx(0.1 - 0.005)


def test_box_size_of_boxes_turned_about_y_spans_the_world_aabb_of_their_corners():
    """The world AABB the term reads (spread.box_geometry.box_size, shared with the baselines' boxes)."""
    g = torch.Generator().manual_seed(0)
    extents = torch.rand(5, 3, generator=g, dtype=torch.float64) + 0.1
    rotation = torch.stack([yaw(a) for a in torch.rand(5, generator=g).tolist()])
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
    corners = torch.einsum("nij,nkj->nki", rotation, signs[None] * extents[:, None] / 2)
    assert torch.allclose(box_size(extents, rotation) / 2, corners.amax(1), atol=1e-12)


def test_the_codes_of_a_room_of_boxes_cost_nothing_and_every_other_code_costs_something():
    """The codes spread.relations gives a room of boxes (world AABBs of their corners), stacked ones included, cost
    nothing; every other code costs, but for a directional code asked of a stacked pair (the term's known blind spot:
    a sector does not ask the pair to unstack)."""
    g = torch.Generator().manual_seed(4)
    N = 9
    extents = torch.rand(N, 3, generator=g, dtype=torch.float64) * 0.6 + 0.2
    rotation = torch.stack([yaw(a) for a in (torch.rand(N, generator=g) * 6.28).tolist()])
    translation = torch.rand(N, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 0.0, 4.0]) - 2.0
    translation[:, 1] = extents[:, 1] / 2  # on the floor
    for top, bottom in ((1, 0), (2, 1), (4, 3)):  # three stacks: a box resting on another's centre
        translation[top, [0, 2]] = translation[bottom, [0, 2]] + torch.tensor([0.03, 0.01], dtype=torch.float64)
        translation[top, 1] = translation[bottom, 1] + (box_size(extents, rotation) / 2)[bottom, 1] + \
            (box_size(extents, rotation) / 2)[top, 1]
    half = (box_size(extents, rotation) / 2)
    codes = spatial_codes(translation - half, translation + half).long()
    t, r, e = translation[None], rotation[None], extents[None]
    off = ~torch.eye(N, dtype=torch.bool)
    above, below = (codes[off] == SPATIAL_ABOVE).sum().item(), (codes[off] == SPATIAL_BELOW).sum().item()
    assert above == below >= 3  # the stacks (2 on 1 on 0: 2 is above 0 too)
    assert spatial_violation(t, r, e, codes[None])[0][off].abs().max().item() < 1e-12
    for other in SIX:
        wrong = torch.full_like(codes, other)
        differs = off & (codes != other)
        if other not in (SPATIAL_ABOVE, SPATIAL_BELOW):
            differs &= (codes != SPATIAL_ABOVE) & (codes != SPATIAL_BELOW)
        assert (spatial_violation(t, r, e, wrong[None])[0][differs] > 1e-9).all(), other


def test_the_excess_is_zero_on_the_training_scene_and_a_gradient_step_turns_a_wrong_pair_right():
    t_true, r, e = two((2.0, 0.2, 0.0), (0.0, 0.2, 0.0))
    spatial = torch.tensor([[[SPATIAL_SELF, SPATIAL_RIGHT], [SPATIAL_LEFT, SPATIAL_SELF]]])
    mask = torch.ones(1, 2, dtype=torch.bool)
    assert spatial_excess(t_true, r, t_true, r, e, mask, spatial).item() == 0.0
    guess = torch.tensor([[[-0.3, 0.2, 0.4], [0.0, 0.2, 0.0]]], dtype=torch.float64, requires_grad=True)
    for _ in range(50):
        cost = spatial_excess(guess, r, t_true, r, e, mask, spatial)
        if cost.item() == 0:
            break
        (grad,) = torch.autograd.grad(cost, guess)
        guess = (guess - 0.5 * grad).detach().requires_grad_(True)
    half = (box_size(e, r) / 2)[0]
    codes = spatial_codes((guess[0] - half).detach(), (guess[0] + half).detach())
    assert codes[0, 1] == SPATIAL_RIGHT and codes[1, 0] == SPATIAL_LEFT
    # padding pairs cost nothing: object 1 masked out
    assert spatial_excess(guess.detach() * 0, r, t_true, r, e, torch.tensor([[True, False]]), spatial).item() == 0.0


def test_the_spatial_term_joins_the_loss_with_its_weight_and_is_off_by_default():
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    batch = _batch()
    batch["spatial"][:] = SPATIAL_SELF
    batch["spatial"][:, 0, 1], batch["spatial"][:, 1, 0] = SPATIAL_LEFT, SPATIAL_RIGHT  # 0 at x 0, 1 at x 0.6: wrong
    noise, t = torch.randn(2, 3, 9), torch.tensor([10, 400])
    model = _tiny_model(0.0)
    on = SceneDiffusion("base", model.config, bounds=[-3, 0, -3, 3, 2.5, 3], prediction="v_prediction",
                        spatial_weight=0.7)
    on.network.load_state_dict(model.network.state_dict())
    terms = on.training_terms(batch, noise, t)
    assert set(terms) == {"mse", "spatial"} and terms["spatial"].item() > 0
    assert on.training_loss(batch, noise, t).item() == pytest.approx(
        terms["mse"].item() + 0.7 * terms["spatial"].item(), rel=1e-5)
    assert on.hparams["spatial_weight"] == 0.7 and model.hparams["spatial_weight"] == 0.0
    assert set(model.training_terms(batch, noise, t)) == {"mse"}
    with pytest.raises(ValueError, match="spatial_weight"):
        SceneDiffusion("base", model.config, spatial_weight=-0.1)
