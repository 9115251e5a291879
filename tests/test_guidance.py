"""Guidance: config, finite-difference gradients, known directions, resting scenes, guided sampling."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from spread.assets.assemble import box_asset, library_from_specs
from spread.data import matrix_to_rot6d
from spread.guidance import GuidanceConfig, SceneGuidance
from spread.guidance.collision import cone_frames, conical_field
from spread.configs import model_config
from spread.model import Sampler
from spread.model.diffusion import reverse_process

BOUNDS = torch.tensor([-3.0, 0.0, -3.0, 3.0, 2.5, 3.0])
GAP, TOL = 5e-4, 2e-3
REST = GAP + TOL / 2  # a resting object's gap: inside the gravity band
SIZES = {"table": (1.0, 0.75, 0.7), "cup": (0.08, 0.1, 0.08), "crate": (0.4, 0.3, 0.4), "block": (0.3, 0.2, 0.3),
         "phone": (0.07, 0.01, 0.15)}


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    root = tmp_path_factory.mktemp("guidance_lib")
    return library_from_specs(root, [box_asset(name, size) for name, size in SIZES.items()])


def state(translations, rotations=None) -> torch.Tensor:
    """Normalised states (N, 9) float64 of poses (metres; rotations scipy or None = identity)."""
    t = torch.tensor(np.asarray(translations, float))
    R = torch.eye(3, dtype=torch.float64).expand(len(t), 3, 3) if rotations is None else \
        torch.tensor(np.stack([r.as_matrix() for r in rotations]))
    lo, hi = BOUNDS[:3].double(), BOUNDS[3:].double()
    return torch.cat([2 * (t - lo) / (hi - lo) - 1, matrix_to_rot6d(R)], -1)


def metres(x: torch.Tensor) -> torch.Tensor:
    """Translations (…, 3) in metres of normalised states."""
    lo, hi = BOUNDS[:3].to(x), BOUNDS[3:].to(x)
    return (x[..., :3] + 1) / 2 * (hi - lo) + lo


def guide(lib, ids, physical=None, config="refine", **kw):
    n = len(ids)
    phys = torch.zeros(1, n, n, dtype=torch.long)
    for i, j in physical or []:
        phys[0, i, j] = 1
    return SceneGuidance(config, lib, [ids], phys, torch.ones(1, n, dtype=torch.bool), BOUNDS, **kw)


def y_on(name, surface=0.0, gap=REST):
    return surface + gap + SIZES[name][1] / 2


TABLE_TOP = y_on("table") + SIZES["table"][1] / 2


def finite_difference(fn, x, entries, eps=1e-6):
    """(autograd, central differences) of scalar fn at x over the given index tuples."""
    xg = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(fn(xg), xg)
    auto, fd = [], []
    for idx in entries:
        xp, xm = x.clone(), x.clone()
        xp[idx] += eps
        xm[idx] -= eps
        fd.append(float((fn(xp) - fn(xm)) / (2 * eps)))
        auto.append(float(grad[idx]))
    return np.array(auto), np.array(fd)


# ---- config -----------------------------------------------------------------------------------------

def test_config_parsing_and_errors():
    assert GuidanceConfig.from_config(None).mode == "none" and not GuidanceConfig.from_config("none").active
    cfg = GuidanceConfig.from_config({"mode": "refine", "iterations": 10.0, "collision": 0})
    assert cfg.iterations == 10 and cfg.active and cfg.collision == 0.0
    assert GuidanceConfig.from_config(cfg.to_dict()) == cfg and GuidanceConfig.from_config(cfg) is cfg
    assert (cfg.collision, GuidanceConfig().gravity, GuidanceConfig().relation) == (0.0, 1e-3, 1e-3)
    assert GuidanceConfig("paper").collision == 7.5e-3
    assert not GuidanceConfig("paper", collision=0, gravity=0, relation=0).active
    with pytest.raises(ValueError, match="'mode'.*'sideways'"):
        GuidanceConfig.from_config("sideways")
    with pytest.raises(ValueError, match="'gravity'.*-1"):
        GuidanceConfig.from_config({"mode": "paper", "gravity": -1.0})
    with pytest.raises(ValueError, match="unknown key 'lr'"):
        GuidanceConfig.from_config({"lr": 1e-3})
    with pytest.raises(ValueError, match="'start'"):
        GuidanceConfig(start=1.5)
    with pytest.raises(ValueError, match="'iterations'"):
        GuidanceConfig(iterations=-1)


def test_bad_inputs_are_named(lib):
    with pytest.raises(KeyError, match="unknown asset 'sofa_99'"):
        guide(lib, ["table", "sofa_99"])
    with pytest.raises(ValueError, match="3 asset ids but 2 real objects"):
        SceneGuidance("paper", lib, [["table", "cup", "crate"]], torch.zeros(1, 2, 2, dtype=torch.long),
                      torch.ones(1, 2, dtype=torch.bool), BOUNDS)
    g = guide(lib, ["table", "cup"])
    with pytest.raises(ValueError, match=r"\(B, N, 9\)"):
        g.losses(torch.zeros(1, 3, 9))


# ---- gradients ----------------------------------------------------------------------------------------

def test_codf_profile_and_gradcheck():
    tri = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 0, -1]]], dtype=torch.float64)  # normal +y
    n, c, r = cone_frames(tri)
    assert torch.allclose(n, torch.tensor([[0.0, 1, 0]], dtype=torch.float64))
    assert torch.allclose(c, torch.tensor([[0.5, 0, -0.5]], dtype=torch.float64)) and math.isclose(float(r), 0.5 ** 0.5)
    heights = torch.tensor([-0.3, 0.0, 0.2, 0.6], dtype=torch.float64)[None, :, None]
    axis = c[:, None, :] + torch.tensor([0.0, 1, 0], dtype=torch.float64) * heights
    psi = conical_field(axis, n, c, r, 0.5)[0]
    assert torch.allclose(psi, torch.tensor([0.8 ** 2, 0.5 ** 2, 0.3 ** 2, 0.0], dtype=torch.float64))  # φ = 0.5 − l
    far = c[:, None, :] + torch.tensor([[[2.0, 0.05, 0.0]]], dtype=torch.float64)
    assert float(conical_field(far, n, c, r, 0.5)) == 0.0  # outside the cone
    g = torch.Generator().manual_seed(0)
    pts = (c[:, None, :] + 0.2 * torch.randn(1, 5, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    tri = (tri + 0.05 * torch.randn(tri.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, t: conical_field(p, *cone_frames(t), 0.5), (pts, tri))


def test_collision_gradient_matches_finite_differences(lib):
    g = guide(lib, ["crate", "block"], detach_cones=False)
    rot = [Rotation.from_rotvec([0.1, 0.3, -0.05]), Rotation.from_rotvec([-0.2, 0.7, 0.15])]
    x = state([[0.0, 0.2, 0.0], [0.25, 0.3, 0.1]], rot)[None]
    assert g.losses(x)["collision"] > 0
    auto, fd = finite_difference(lambda s: g.losses(s)["collision"], x, [(0, i, c) for i in range(2) for c in range(9)])
    assert np.abs(auto).max() > 1e-3
    np.testing.assert_allclose(auto, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_gravity_gradient_matches_finite_differences(lib):
    g = guide(lib, ["table", "cup", "crate"], physical=[(0, 1)])
    tilt = Rotation.from_rotvec([0.05, 0.4, -0.03])
    x = state([[0.0, y_on("table"), 0.0], [0.1, TABLE_TOP + 0.04, 0.05], [2.0, 0.3, 0.0]],
              [Rotation.identity(), tilt, tilt])[None]
    entries = [(0, i, c) for i in (1, 2) for c in range(9)]  # the floating cup and crate; the table is fixed
    auto, fd = finite_difference(lambda s: g.losses(s)["gravity"], x, entries)
    assert abs(auto[1]) > 0.1 and abs(auto[10]) > 0.1  # y channels
    np.testing.assert_allclose(auto, fd, rtol=1e-5, atol=1e-8)


def test_relation_gradient_matches_finite_differences(lib):
    g = guide(lib, ["table", "cup"], physical=[(0, 1)])
    x = state([[0.0, y_on("table"), 0.0], [0.49, y_on("cup", TABLE_TOP), 0.33]],
              [Rotation.from_rotvec([0.0, 0.2, 0.0]), Rotation.from_rotvec([0.1, 0.5, 0.05])])[None]
    assert g.losses(x)["relation"] > 0
    auto, fd = finite_difference(lambda s: g.losses(s)["relation"], x, [(0, 1, c) for c in range(9)])
    assert np.abs(auto[[0, 2]]).min() > 0.1
    np.testing.assert_allclose(auto, fd, rtol=1e-5, atol=1e-8)


# ---- known directions ---------------------------------------------------------------------------------

def run_steps(g, x, steps):
    for _ in range(steps):
        x = g.step(x)
    return x


def test_penetrating_boxes_separate(lib):
    g = guide(lib, ["crate", "block"], config=GuidanceConfig("refine", gravity=0, relation=0))
    x0 = state([[0.0, 0.25, 0.0], [0.3, 0.3, 0.05]],
               [Rotation.identity(), Rotation.from_rotvec([0, 0.1, 0])])[None].float()
    assert g.losses(x0)["collision"] > 0
    x = run_steps(g, x0, 60)
    assert float(g.losses(x)["collision"]) == 0.0, "the boxes no longer intersect"
    moved = metres(x)[0] - metres(x0)[0]
    assert moved[0, 0] < -1e-3 and moved[1, 0] > 1e-3, "pushed apart along x"
    assert g.stats["steps"] == 60 and g.stats["colliding_pairs"] > 0 and g.stats["bvh_s"] > 0


def test_floating_cup_descends_to_its_table(lib):
    g = guide(lib, ["table", "cup"], physical=[(0, 1)])
    x0 = state([[0.0, y_on("table"), 0.0], [0.2, TABLE_TOP + 0.05 + SIZES["cup"][1] / 2, 0.1]])[None].float()
    x = run_steps(g, x0, 80)
    bottom = metres(x)[0, 1, 1] - SIZES["cup"][1] / 2 - TABLE_TOP
    assert GAP - 1e-4 <= bottom <= GAP + TOL + 1e-4, f"cup rests on its table, gap {bottom:.4f} m"
    assert torch.equal(x[0, 0], x0[0, 0]), "the table does not move"
    assert torch.allclose(x[0, 1, [0, 2]], x0[0, 1, [0, 2]]), "gravity moves y only"
    assert torch.equal(x[0, 1, 3:], x0[0, 1, 3:])


def settled(lib, weight, ids=("table", "cup", "crate"), physical=((0, 1),)):
    return guide(lib, list(ids), physical=list(physical),
                 config=GuidanceConfig("refine", collision=0, gravity=0, relation=0, terms={"settle": weight}))


def test_settle_closes_the_fraction_lambda_of_each_gap_per_step_and_then_rests(lib):
    """G_S: a cup 30 cm above its table and a crate 20 cm above the floor close half their gaps in one step of
    λ = 0.5 (G_H would move both by the same λ·s_y², whatever their gaps), rest within the gravity band after
    twenty, and only their heights change."""
    g = settled(lib, 0.5)
    cup_gap, crate_gap = 0.30, 0.20
    x0 = state([[0.0, y_on("table"), 0.0], [0.2, y_on("cup", TABLE_TOP, cup_gap), 0.1],
                [2.0, y_on("crate", 0.0, crate_gap), 0.0]])[None]

    def gaps(x):
        y = metres(x)[0, :, 1]
        return float(y[1] - SIZES["cup"][1] / 2 - TABLE_TOP), float(y[2] - SIZES["crate"][1] / 2)

    x1 = g.step(x0)
    np.testing.assert_allclose(gaps(x1), [GAP + 0.5 * (cup_gap - GAP), GAP + 0.5 * (crate_gap - GAP)], atol=1e-9)
    x = run_steps(g, x1, 19)
    for gap in gaps(x):
        assert GAP - 1e-9 <= gap <= GAP + TOL + 1e-9, gap
    assert float(g.losses(x, which=["settle"])["settle"]) == 0.0
    assert torch.equal(x[0, 0], x0[0, 0]), "the table does not move"
    assert torch.allclose(x[0, 1:, [0, 2]], x0[0, 1:, [0, 2]]) and torch.equal(x[0, 1:, 3:], x0[0, 1:, 3:])
    sunk = state([[0.0, y_on("table"), 0.0], [0.2, y_on("cup", TABLE_TOP, -0.03), 0.1]])[None]
    up = settled(lib, 0.5, ids=("table", "cup")).step(sunk)
    assert math.isclose(float(metres(up)[0, 1, 1] - metres(sunk)[0, 1, 1]), 0.5 * (0.03 + GAP), abs_tol=1e-7)  # float32 meshes


@pytest.mark.parametrize("sink", [0.03, 0.12])
def test_settle_lifts_a_phone_sunk_past_its_centre_into_its_table_in_one_step_of_weight_one(lib, sink):
    """A phone sunk 3 or 12 cm into its table (its centre below the top) still sees the top: its rays start
    ``settle_reach`` (0.15 m) above its lowest point, not at its centre, where they would see nothing of the table."""
    reach = GuidanceConfig().settle_reach
    assert SIZES["phone"][1] / 2 < sink < reach
    x = state([[0.0, y_on("table"), 0.0], [0.2, y_on("phone", TABLE_TOP, -sink), 0.1]])[None]
    up = settled(lib, 1.0, ids=("table", "phone")).step(x)
    assert math.isclose(float(metres(up)[0, 1, 1] - metres(x)[0, 1, 1]), sink + GAP, abs_tol=1e-7)


def test_settle_leaves_an_object_sunk_deeper_than_its_reach_where_it_is(lib):
    """With ``settle_reach`` 0.05 m a phone sunk 12 cm sees no face of its table above its rays' start: it counts as
    beside its supporter, and settle leaves it (the setting's default reaches it: the test above)."""
    g = guide(lib, ["table", "phone"], physical=[(0, 1)],
              config=GuidanceConfig("refine", collision=0, gravity=0, relation=0, terms={"settle": 1.0},
                                    settle_reach=0.05))
    x = state([[0.0, y_on("table"), 0.0], [0.2, y_on("phone", TABLE_TOP, -0.12), 0.1]])[None]
    assert float(g.losses(x, which=["settle"])["settle"]) == 0.0 and torch.equal(g.step(x), x)
    with pytest.raises(ValueError, match="settle_reach"):
        GuidanceConfig(settle_reach=-0.1)


def test_settle_leaves_a_cup_beside_its_table_where_gravity_lifts_it_to_the_tables_top(lib):
    g = settled(lib, 0.5, ids=("table", "cup"))
    x = state([[0.0, y_on("table"), 0.0], [0.9, y_on("cup", 0.3), 0.0]])[None]  # beside the table, below its top
    assert float(g.losses(x, which=["settle"])["settle"]) == 0.0 and torch.equal(g.step(x), x)
    assert float(g.losses(x, which=["gravity"])["gravity"]) > 0.3  # G_H: the gap to the top of the table's box


def test_settle_gradient_matches_finite_differences(lib):
    g = settled(lib, 1.0)
    tilt = Rotation.from_rotvec([0.05, 0.4, -0.03])
    x = state([[0.0, y_on("table"), 0.0], [0.1, TABLE_TOP + 0.04, 0.05], [2.0, 0.3, 0.0]],
              [Rotation.identity(), tilt, tilt])[None]
    entries = [(0, i, c) for i in (1, 2) for c in range(9)]
    auto, fd = finite_difference(lambda s: g.losses(s, which=["settle"])["settle"], x, entries)
    assert abs(auto[1]) > 1e-3 and abs(auto[10]) > 1e-3  # y channels
    np.testing.assert_allclose(auto, fd, rtol=1e-5, atol=1e-8)


def test_over_moves_a_cup_off_its_tables_edge_by_the_fraction_lambda_of_its_mean_outside_distance(lib):
    """G_O: a cup wholly beyond the table's +x edge (every vertex outside, the edge straight) moves in x by
    λ times the mean distance of its vertices to the table's footprint, in one step, and nothing else moves."""
    g = guide(lib, ["table", "cup"], physical=[(0, 1)],
              config=GuidanceConfig("refine", collision=0, gravity=0, relation=0, terms={"over": 0.5}))
    edge, beyond = SIZES["table"][0] / 2, 0.1
    x0 = state([[0.0, y_on("table"), 0.0], [edge + beyond + SIZES["cup"][0] / 2, y_on("cup", TABLE_TOP), 0.1]])[None]
    mean_outside = beyond + SIZES["cup"][0] / 2  # the cup's vertices lie at beyond and beyond + its width, as many
    x = g.step(x0)
    moved = metres(x)[0] - metres(x0)[0]
    assert math.isclose(float(moved[1, 0]), -0.5 * mean_outside, abs_tol=1e-7), float(moved[1, 0])
    assert abs(float(moved[1, 1])) < 1e-12 and abs(float(moved[1, 2])) < 1e-7
    assert torch.equal(x[0, 0], x0[0, 0]) and torch.allclose(x[0, 1, 3:], x0[0, 1, 3:], atol=1e-9)
    inside = run_steps(g, x, 40)
    assert float(g.losses(inside, which=["over"])["over"]) < 1e-10
    assert metres(inside)[0, 1, 0] <= edge - SIZES["cup"][0] / 2 + 1e-3


def homed(lib, weight):
    return guide(lib, ["table", "cup"], physical=[(0, 1)],
                 config=GuidanceConfig("refine", collision=0, gravity=0, relation=0, terms={"home": weight}))


def test_home_moves_a_cup_beside_and_below_its_table_by_lambda_along_the_way_in_and_up_whatever_its_distance(lib):
    """G_home: a cup wholly beyond the table's +x edge and 30 cm below its top moves, in one step of weight λ, by λ
    normalised units towards the table (λ·3 m in x here) and λ up (λ·1.25 m in y): the same step 20 cm and 1 m
    away (G_O's step is a fraction of the distance); nothing else moves."""
    g = homed(lib, 0.01)
    edge = SIZES["table"][0] / 2
    for beyond in (0.2, 1.0):
        x0 = state([[0.0, y_on("table"), 0.0],
                    [edge + beyond + SIZES["cup"][0] / 2, y_on("cup", TABLE_TOP - 0.3), 0.1]])[None]
        moved = metres(g.step(x0))[0] - metres(x0)[0]
        half = (BOUNDS[3:] - BOUNDS[:3]).double() / 2
        assert math.isclose(float(moved[1, 0]), -0.01 * float(half[0]), abs_tol=1e-7), float(moved[1, 0])
        assert math.isclose(float(moved[1, 1]), 0.01 * float(half[1]), abs_tol=1e-7), float(moved[1, 1])
        assert abs(float(moved[1, 2])) < 1e-7 and float(moved[0].abs().max()) == 0.0


def test_home_stops_once_every_vertex_is_over_the_footprint_and_lifts_only_an_object_wholly_beside(lib):
    g = homed(lib, 0.01)
    edge = SIZES["table"][0] / 2
    x = state([[0.0, y_on("table"), 0.0], [edge + 0.6, y_on("cup", TABLE_TOP), 0.1]])[None]
    for _ in range(40):
        x = g.step(x)
    assert float(g.losses(x, which=["home"])["home"]) == 0.0
    cup = metres(x)[0, 1]
    assert edge - SIZES["cup"][0] / 2 - 0.04 < float(cup[0]) <= edge - SIZES["cup"][0] / 2 + 1e-6, "just over the edge"
    assert float(cup[1]) >= y_on("cup", TABLE_TOP) - 1e-9, "never lowered"
    assert torch.equal(g.step(x), x), "at rest over its table"
    overhang = state([[0.0, y_on("table"), 0.0], [edge, y_on("cup", TABLE_TOP - 0.05), 0.1]])[None]
    moved = metres(g.step(overhang))[0, 1] - metres(overhang)[0, 1]
    assert float(moved[0]) < -1e-4 and abs(float(moved[1])) < 1e-12, "half over: drawn in, not lifted"


def test_home_gradient_matches_finite_differences(lib):
    g = homed(lib, 1.0)
    tilt = Rotation.from_rotvec([0.05, 0.4, -0.03])
    x = state([[0.0, y_on("table"), 0.0], [0.9, TABLE_TOP - 0.2, 0.3]], [Rotation.identity(), tilt])[None]
    entries = [(0, 1, c) for c in range(9)]
    auto, fd = finite_difference(lambda s: g.losses(s, which=["home"])["home"], x, entries)
    assert abs(auto[0]) > 0.1 and abs(auto[1]) > 0.1  # x and y channels
    np.testing.assert_allclose(auto, fd, rtol=1e-5, atol=1e-8)


def test_cup_off_centre_is_held_by_its_table_not_the_floor(lib):
    """The release's centre ray misses a table that is not under the cup's centre; the mesh gap does not."""
    g = guide(lib, ["table", "cup"], physical=[(0, 1)])
    x = state([[0.0, y_on("table"), 0.0], [0.52, y_on("cup", TABLE_TOP), 0.0]])[None]  # centre off the edge
    assert float(g.losses(x)["gravity"]) == 0.0


def test_overhanging_cup_moves_inward(lib):
    g = guide(lib, ["table", "cup"], physical=[(0, 1)], config=GuidanceConfig("refine", gravity=0, collision=0))
    x0 = state([[0.0, y_on("table"), 0.0], [0.5, y_on("cup", TABLE_TOP), 0.0]])[None].float()
    assert g.losses(x0)["relation"] > 0
    x = run_steps(g, x0, 60)
    assert float(g.losses(x)["relation"]) == 0.0
    assert metres(x)[0, 1, 0] <= 0.5 - SIZES["cup"][0] / 2 + 1e-3 and metres(x)[0, 1, 0] > 0.4
    assert torch.equal(x[0, 0], x0[0, 0])


@pytest.mark.parametrize("supported", [True, False])
def test_supporter_stays_put(lib, supported):
    g = guide(lib, ["table", "cup"], physical=[(0, 1)] if supported else [])
    x0 = state([[0.0, y_on("table"), 0.0], [0.1, TABLE_TOP + SIZES["cup"][1] / 2 - 0.01, 0.1]],
               [Rotation.identity(), Rotation.from_rotvec([0, 0.3, 0])])[None].float()  # cup sunk 1 cm
    assert g.losses(x0)["collision"] > 0
    x = run_steps(g, x0, 30)
    assert metres(x)[0, 1, 1] > metres(x0)[0, 1, 1], "the cup comes up"
    if supported:
        assert torch.equal(x[0, 0], x0[0, 0]), "a supporter is not pushed by what it supports"
    else:
        assert not torch.equal(x[0, 0], x0[0, 0])


def test_resting_scene_has_zero_losses_and_does_not_move(lib):
    g = guide(lib, ["table", "cup", "crate", "block"], physical=[(0, 1), (2, 3)])
    x = state([[0.0, y_on("table"), 0.0], [0.3, y_on("cup", TABLE_TOP), -0.2], [1.5, y_on("crate"), 1.0],
               [1.51, y_on("block", y_on("crate") + 0.15), 1.01]],
              [Rotation.from_rotvec([0, 0.4, 0]), Rotation.from_rotvec([0, 1.0, 0]), Rotation.identity(),
               Rotation.from_rotvec([0, 0.2, 0])])[None]
    assert {k: float(v) for k, v in g.losses(x).items()} == {"collision": 0.0, "gravity": 0.0, "relation": 0.0}
    assert torch.equal(g.step(x), x)
    # exactly touching is inside the ε band's lower side: gravity lifts it by ε
    touching = x.clone()
    touching[0, 1, 1] -= 2 * REST / 2.5
    assert float(g.losses(touching)["gravity"]) > 0


def test_batched_scenes_are_independent(lib):
    """A scene's step is the same alone and batched with another (padded) scene."""
    a = state([[0.0, 0.25, 0.0], [0.3, 0.3, 0.05], [0.1, 0.9, 0.0]])
    b = state([[0.0, y_on("table"), 0.0], [0.5, y_on("cup", TABLE_TOP) + 0.03, 0.0]])
    phys = torch.full((2, 3, 3), 3, dtype=torch.long)
    phys[0] = 0
    phys[1, :2, :2] = torch.tensor([[0, 1], [0, 0]])
    mask = torch.tensor([[True, True, True], [True, True, False]])
    both = torch.stack([a, torch.cat([b, torch.zeros(1, 9, dtype=b.dtype)])]).float()
    g = SceneGuidance("refine", lib, [["crate", "block", "cup"], ["table", "cup"]], phys, mask, BOUNDS)
    out = g.step(both)
    alone_a = guide(lib, ["crate", "block", "cup"]).step(both[:1])
    alone_b = guide(lib, ["table", "cup"], physical=[(0, 1)]).step(both[1:, :2])
    assert torch.allclose(out[0], alone_a[0], atol=1e-7) and torch.allclose(out[1, :2], alone_b[0], atol=1e-7)
    assert torch.equal(out[1, 2], both[1, 2]), "padding does not move"
    per_scene = g.losses(both, reduce=False)
    assert per_scene["collision"].shape == (2,) and per_scene["collision"][1] == 0 and per_scene["relation"][1] > 0


def test_refine_lowers_collision(lib):
    g = guide(lib, ["crate", "block"], config=GuidanceConfig("refine", iterations=30))
    x0 = state([[0.0, y_on("crate"), 0.0], [0.3, y_on("block"), 0.05]],
               [Rotation.identity(), Rotation.from_rotvec([0, 0.1, 0])])[None].float()
    calls = []

    def eps_fn(x, t):
        calls.append(int(t[0]))
        return torch.zeros_like(x)

    x = g.refine(x0, eps_fn)
    assert calls == [0] * 30 and g.stats["network_calls"] == 30 and g.stats["steps"] == g.stats["iterations"] == 30
    assert float(g.losses(x)["collision"]) < 0.1 * float(g.losses(x0)["collision"])
    sparse = guide(lib, ["crate", "block"], config=GuidanceConfig("refine", iterations=10, denoise_every=4))
    sparse.refine(x0, eps_fn)
    assert sparse.stats["network_calls"] == 3 and sparse.stats["iterations"] == 10  # iterations 0, 4, 8


def test_real_assets_resting_and_floating(tmp_path):
    """Procedural meshes (a mug on a side table's top surface): zero losses at rest; lifted, only gravity."""
    from spread.assets.build import build_library

    lib = build_library(tmp_path, categories=["mug", "side_table"], variants=1, seed=0, progress=False, caches=False)
    table, mug = lib["side_table_00"], lib["mug_00"]
    (top,) = [s for s in table.support_surfaces if s.kind == "top"][:1] or table.support_surfaces[:1]
    table_y = table.extents[1] / 2 + REST
    cx, cz = (np.add(top.xz_min, top.xz_max) / 2).tolist()
    x = state([[0.0, table_y, 0.0], [cx, table_y + top.height + REST + mug.extents[1] / 2, cz]],
              [Rotation.identity(), Rotation.from_rotvec([0, 2.0, 0])])[None]
    g = guide(lib, ["side_table_00", "mug_00"], physical=[(0, 1)])
    assert {k: float(v) for k, v in g.losses(x).items()} == {"collision": 0.0, "gravity": 0.0, "relation": 0.0}
    lifted = x.clone()
    lifted[0, 1, 1] += 2 * 0.03 / 2.5  # 3 cm up
    values = g.losses(lifted)
    assert math.isclose(float(values["gravity"]), 0.03 + TOL / 2, abs_tol=1e-5) and float(values["relation"]) == 0.0


# ---- guided sampling through the model ----------------------------------------------------------------

@pytest.fixture(scope="module")
def model_and_batch(lib):
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    cfg = model_config("tiny", depth=1, dim=32, dim_head=8, heads=2, edge_dim=16, index_dim=8, num_latents=4,
                       shape_tokens=4, shape_dim=16, tokenizer_width=16, tokenizer_points=16, num_points=16, cond_dim=32)
    model = SceneDiffusion("geometry", cfg, bounds=BOUNDS.tolist()).eval()
    ids = [["table", "cup", "crate", "block"], ["crate", "block"]]
    B, N, M = 2, 4, 16
    mask = torch.tensor([[True] * 4, [True, True, False, False]])
    pair = mask[:, :, None] & mask[:, None, :]
    physical = torch.zeros(B, N, N, dtype=torch.long)
    physical[0, 0, 1] = 1
    physical = physical.masked_fill(~pair, 3)
    g = torch.Generator().manual_seed(0)
    spatial = torch.randint(0, 6, (B, N, N), generator=g).masked_fill(~pair, 7)
    points = (torch.rand(B, N, M, 3, generator=g) - 0.5) * 0.4 * mask[..., None, None]
    normals = torch.nn.functional.normalize(torch.randn(B, N, M, 3, generator=g), dim=-1)
    batch = dict(x=torch.zeros(B, N, 9), mask=mask, spatial=spatial, physical=physical, points=points, normals=normals)
    return model, batch, ids


def make_guidance(lib, model_and_batch, config):
    model, batch, ids = model_and_batch
    return SceneGuidance(config, lib, ids, batch["physical"], batch["mask"], model.network.bounds)


def guided_states(model, batch, sampler, generator, guidance):
    """States sampled through the pipeline with ``guidance`` as its callback (None: unguided)."""
    from spread.sampling.pipeline import ScenePipeline, guidance_callback

    callback = guidance_callback(guidance) if guidance is not None else None
    x, _ = ScenePipeline(model, None, sampler).sample_states(batch, generator, [callback] if callback else [])
    return x


def test_guidance_none_is_bit_for_bit(lib, model_and_batch):
    model, batch, _ = model_and_batch
    network = model.ema.module
    cond = network.condition(batch)

    def reference(sampler):  # what sample_states did before guidance existed
        with torch.no_grad():
            return reverse_process(Sampler.from_config(sampler), lambda x, t: network(x, t, cond), cond.mask,
                                   generator=torch.Generator().manual_seed(3))

    for sampler in ("ddim-4", "dpmsolver++-3"):
        ref = reference(sampler)
        assert torch.equal(model.sample_states(batch, sampler, generator=torch.Generator().manual_seed(3)), ref)
        inactive = GuidanceConfig("paper", collision=0, gravity=0, relation=0)
        for guidance in (None, *(make_guidance(lib, model_and_batch, c) for c in ("none", inactive))):
            out = guided_states(model, batch, sampler, torch.Generator().manual_seed(3), guidance)
            assert torch.equal(out, ref)


@pytest.mark.parametrize("sampler", ["ddim-6", "dpmsolver++-6", "ddpm-6"])
def test_paper_and_refine_modes_sample(lib, model_and_batch, sampler):
    model, batch, _ = model_and_batch
    gen = lambda: torch.Generator().manual_seed(1)  # noqa: E731
    plain = model.sample_states(batch, sampler, generator=gen())
    for config in (GuidanceConfig("paper", start=0.5), GuidanceConfig("refine", iterations=4)):
        guidance = make_guidance(lib, model_and_batch, config)
        out = guided_states(model, batch, sampler, gen(), guidance)
        assert torch.isfinite(out).all() and not torch.equal(out, plain), config.mode
        assert (out[~batch["mask"]] == 0).all(), "padding stays zero"
        stats = guidance.stats
        if config.mode == "paper":
            assert stats["steps"] == 3 and stats["network_calls"] == 0  # steps 3, 4, 5 of 6
        else:
            assert stats["steps"] == 4 and stats["network_calls"] == 4 and stats["network_s"] > 0
        poses = model.decode(guided_states(model, batch, sampler, gen(), make_guidance(lib, model_and_batch, config)),
                             batch["mask"])
        assert torch.isfinite(poses.translation).all()


def test_paper_schedule_and_gravity_window(lib, model_and_batch):
    """Guidance from ceil(start·K), gravity from ceil(gravity_from·K); inner steps multiply."""
    config = GuidanceConfig("paper", start=0.25, gravity_from=0.75, inner_steps=2)
    guidance = make_guidance(lib, model_and_batch, config)
    seen = []
    original = guidance.step

    def spy(x, gravity=True, at=None):
        seen.append("gravity" in guidance.weights(at, gravity))  # the terms acting at this step
        return original(x, gravity=gravity, at=at)

    guidance.step = spy
    model, batch, _ = model_and_batch
    guided_states(model, batch, "ddim-8", torch.Generator().manual_seed(0), guidance)
    assert seen == [False] * 8 + [True] * 4  # steps 2..5 without, 6..7 with gravity, twice each


def test_the_built_in_terms_are_spelled_in_one_module():
    """Everything else asks the registry or GuidanceConfig (weights(), weight_keys()): no module lists the trio
    (``("collision", "gravity", "relation")``, ``guidance.collision, guidance.gravity, ...``) but the config's."""
    import re
    from pathlib import Path

    import spread
    from spread.guidance.terms import term_names

    trio = re.compile(r"""["'](guidance[._])?collision["']\s*,\s*["'](guidance[._])?gravity["']""")
    found = {p.relative_to(Path(spread.__file__).parent).as_posix() for p in Path(spread.__file__).parent.rglob("*.py")
             if trio.search(p.read_text())}
    assert found <= {"guidance/config.py"}, found
    assert GuidanceConfig.weight_keys() == ("collision", "gravity", "relation")
    weights = GuidanceConfig("paper", collision=0.5, terms={"box_iou": 0.2}).weights()
    assert weights["collision"] == 0.5 and weights["box_iou"] == 0.2 and weights["gravity"] == 1e-3  # by name
    assert set(weights) == set(term_names())  # every registered term: the built-ins are ordinary terms


def test_a_guidance_step_finds_the_support_pairs_once_per_sample_not_by_a_device_read_every_step(lib):
    """The graph's support pairs are the same every step: found once (``support_pairs``/``held_pairs``, the rows of
    supports.nonzero()); a step of relation or over then reads nothing back from the device, one of gravity or settle
    only the data-dependent triangles under each supported object (counted by OperatorCounter on CPU tensors)."""
    from spread.model.opcount import OperatorCounter

    ids = ["table", "cup", "crate", "phone"]
    x = state([[0, y_on("table"), 0], [0.1, 1.0, 0.05], [1.0, 0.3, 1.0], [-0.55, 0.9, 0.0]])[None].float()  # the phone half off the table
    reads = {}
    for name, weights in (("gravity", dict(gravity=4e-3)), ("settle", dict(terms={"settle": 0.3})),
                          ("relation", dict(relation=1e-3)), ("over", dict(terms={"over": 0.05}))):
        config = GuidanceConfig.from_config({"mode": "refine", "collision": 0.0, "gravity": 0.0, "relation": 0.0,
                                             **weights})
        g = guide(lib, ids, [(0, 1), (0, 3)], config=config)
        pairs = g._graph(x.device, x.dtype)["support_pairs"]
        assert pairs.tolist() == [[0, 0, 1], [0, 0, 3]]
        with OperatorCounter() as counter:
            moved = g.step(x, at=(99, 100))
        reads[name] = counter.syncs
        assert not torch.equal(moved, x)  # each term acts here
    assert reads == {"gravity": 1, "settle": 1, "relation": 0, "over": 0}
