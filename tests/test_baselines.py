"""Table 1 baselines (spread.baselines): ATISS, DiffuScene, PhyScene-style guidance, InstructScene.

* Each method's own mechanism, by a known answer: ATISS's next-object likelihood does not depend on the
  order of its context; DiffuScene's slot mask hides empty slots from the loss; InstructScene's edge
  dropout hands the network the padding graph; PhyScene's box-IoU guidance pushes two overlapping boxes
  apart. Plus the oriented IoU and InstructScene's predicates on hand-made boxes.
* The platform path for every method: fast_dev_run through ``spread-train experiment=<m>_quick``, a checkpoint
  that loads back (by its hyperparameters) and samples the same, ``spread-sample`` writing scene files and
  ``spread-evaluate`` scoring all of them with no failure.

One small generated dataset (12 rooms over 12 categories: 7 train, 2 val, 3 test); torch on one thread.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from spread.scene import list_scene_files, read_scene, write_scene

from helpers import FAST_TRAIN, QUIET, compose, make_dataset, sample_in_process, train_in_process

METHODS = ("atiss", "diffuscene", "instructscene")
CATEGORIES = ["bed", "nightstand", "sofa", "coffee_table", "armchair", "side_table", "lamp", "book", "cup", "bowl",
              "dining_table", "chair"]


# ---- fixtures ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("bldata"), categories=CATEGORIES)


@pytest.fixture(scope="module")
def facts(dataset) -> dict:
    from spread.baselines.base import dataset_facts

    return dataset_facts(dataset)


@pytest.fixture(scope="module")
def batch(dataset) -> dict:
    from spread.data import SceneDataModule

    dm = SceneDataModule(dataset, batch_size=4, num_points=1)
    dm.setup("fit")
    return next(iter(dm.train_dataloader()))


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory) -> dict[str, Path]:
    """method → a checkpoint after 3 training steps of ``experiment=<method>_quick``; physcene derived from
    DiffuScene's by :func:`spread.baselines.with_box_guidance`."""
    from spread.baselines import with_box_guidance

    root = tmp_path_factory.mktemp("blruns")
    out = {}
    for method in METHODS:
        run = root / method
        summary = train_in_process(run, f"experiment={method}_quick", f"data.root={dataset}", "trainer.max_time=null",
                                   "trainer.max_steps=3", "trainer.check_val_every_n_epoch=1", *FAST_TRAIN)
        assert summary["global_step"] == 3 and math.isfinite(summary["metrics"]["val/loss"])
        out[method] = run / "checkpoints" / "last.ckpt"
    out["physcene"] = with_box_guidance(out["diffuscene"], root / "physcene.ckpt")
    return out


def pad_batch(batch: dict, extra: int, garbage: bool = True) -> dict:
    """The batch with ``extra`` more padded objects per scene (random values there when ``garbage``)."""
    from spread.data.collate import PAD_SPEC

    B, N = batch["mask"].shape
    out = dict(batch, mask=torch.cat([batch["mask"], torch.zeros(B, extra, dtype=torch.bool)], 1))
    gen = torch.Generator().manual_seed(5)
    for key, (value, dims) in PAD_SPEC.items():
        t = batch[key]
        shape = list(t.shape)
        for d in range(1, dims + 1):
            shape[d] = N + extra
        grown = torch.full(shape, value, dtype=t.dtype)
        grown[(slice(None),) + (slice(0, N),) * dims] = t
        if garbage and t.is_floating_point() and dims == 1:
            grown[:, N:] = torch.rand(grown[:, N:].shape, generator=gen) * 3 - 1
        out[key] = grown
    return out


# ---- configs -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_model_yaml_presets_match_the_config_classes(method):
    from spread.baselines import module_class

    cls = module_class(method).config_class
    assert dict(compose("train", f"model={method}").model.config) == cls.tiny().to_dict()
    assert dict(compose("train", f"model={method}_paper").model.config) == cls.paper().to_dict()
    paper = compose("train", f"experiment={method}")
    assert paper.model.config.name == "paper" and paper.data.batch_size == 128
    assert compose("train", f"experiment={method}_quick").model.config.name == "tiny"


def test_physcene_experiment_is_diffuscene_with_box_guidance():
    cfg = compose("train", "experiment=physcene_quick")
    assert cfg.model._target_.endswith("diffuscene.DiffuScene") and cfg.model.method == "physcene"
    assert dict(cfg.model.box_guidance) == {"weight": 0.15, "clip": 0.1, "last_steps": 10}


# ---- ATISS -------------------------------------------------------------------------------------------

def test_atiss_likelihood_does_not_depend_on_context_order(batch, facts):
    from spread.baselines.atiss import ATISS

    torch.manual_seed(0)
    model = ATISS("tiny", **facts)
    mask = batch["mask"]
    B, N = mask.shape
    target = torch.zeros(B, dtype=torch.long)
    context = mask.clone()
    context[:, 0] = False  # every other object of the scene is the context of object 0
    ll = model.log_likelihood(batch, context, target)
    for seed in (1, 2):
        perm = torch.randperm(N, generator=torch.Generator().manual_seed(seed))
        shuffled = dict(batch, **{k: batch[k][:, perm] for k in ("x", "mask", "category_index", "extents")})
        ll_perm = model.log_likelihood(shuffled, context[:, perm], perm.argsort()[target])
        torch.testing.assert_close(ll_perm, ll, rtol=1e-5, atol=1e-4)
    fewer = context.clone()
    fewer[:, 1] = False  # a different set is a different likelihood: the check above can fail
    assert (model.log_likelihood(batch, fewer, target) - ll).abs().max() > 1e-3


def test_atiss_dmll_is_a_distribution_and_samples_follow_it():
    from spread.baselines import dmll

    params = torch.tensor([[0.3, -0.2, 0.1, -0.4, 0.5, -3.0]])  # two logistics: [π, μ, log s]
    grid = torch.linspace(-1, 1, 256)  # the bin centres
    total = dmll.log_prob(params.expand(256, -1), grid).exp().sum()
    torch.testing.assert_close(total, torch.tensor(1.0), atol=1e-4, rtol=0)
    peaked = torch.tensor([[6.0, -6.0, 0.3, -0.6, -4.0, -4.0]])  # one component, scale e^-4
    x = dmll.sample(peaked.expand(2000, -1), torch.rand(2000, 2, generator=torch.Generator().manual_seed(0)))
    assert x.min() >= -1 and x.max() <= 1 and abs(float(x.mean()) - 0.3) < 0.01 and float(x.std()) < 0.1


# ---- DiffuScene ----------------------------------------------------------------------------------------

def test_diffuscene_slot_mask_hides_empty_slots_from_the_loss(batch, facts):
    from spread.baselines.diffuscene import DiffuScene

    torch.manual_seed(0)
    model = DiffuScene("tiny", **facts)
    model.network.eval()
    loss = model.loss(batch, model.network, generator=torch.Generator().manual_seed(3))["loss"]
    garbage = pad_batch(batch, 5)  # 5 more slots per scene, random values in them
    padded = model.loss(garbage, model.network, generator=torch.Generator().manual_seed(3))["loss"]
    torch.testing.assert_close(padded, loss, rtol=1e-5, atol=1e-6)
    N = batch["mask"].shape[1]
    garbage["mask"][:, N] = True  # the same slots marked real do count: the check above can fail
    garbage["category_index"][:, N] = 0
    counted = model.loss(garbage, model.network, generator=torch.Generator().manual_seed(3))["loss"]
    assert abs(float((counted - loss).detach())) > 1e-3


def test_box_iou_guidance_moves_overlapping_boxes_apart(facts):
    from spread.baselines.box_iou import oriented_iou
    from spread.baselines.diffuscene import BoxGuidance, DiffuScene

    model = DiffuScene("tiny", **facts)
    x = torch.zeros(1, 2, 8 + model.num_classes)
    x[0, :, 0] = torch.tensor([-0.05, 0.05])  # normalised centres 0.1 apart in x
    x[0, :, 6] = torch.tensor([1.0, math.cos(0.3)])  # headings 0 and 0.3 rad
    x[0, :, 7] = torch.tensor([0.0, math.sin(0.3)])
    sizes = torch.tensor([[[1.0, 0.5, 1.0], [1.0, 0.5, 1.0]]])
    mask = torch.ones(1, 2, dtype=torch.bool)

    def iou_and_gap(state):
        boxes = model.boxes(torch.cat([state[..., :3], torch.zeros_like(state[..., :3]), state[..., 6:8]], -1))
        boxes[..., 3:6] = sizes
        return float(oriented_iou(boxes[0, 0], boxes[0, 1])), float((boxes[0, 1, :3] - boxes[0, 0, :3]).norm())

    iou0, gap0 = iou_and_gap(x)
    assert iou0 > 0.5
    y = model.guidance_step(x, sizes, mask, BoxGuidance())
    iou1, gap1 = iou_and_gap(y)
    assert iou1 < iou0 and gap1 > gap0
    assert torch.equal(y[..., [1, 3, 4, 5]], x[..., [1, 3, 4, 5]]) and torch.equal(y[..., 8:], x[..., 8:])
    for _ in range(3):
        y = model.guidance_step(y, sizes, mask, BoxGuidance())
    assert iou_and_gap(y)[0] < 0.05 * iou0


def test_oriented_iou_known_answers_and_gradients():
    from spread.baselines.box_iou import axis_aligned_iou, oriented_iou

    def box(x=0.0, y=0.0, z=0.0, theta=0.0, s=(1.0, 1.0, 1.0)):
        return torch.tensor([x, y, z, *s, theta], dtype=torch.float64)

    unit = box()
    assert float(oriented_iou(unit, unit)) == pytest.approx(1.0)
    assert float(oriented_iou(unit, box(x=0.5))) == pytest.approx(1 / 3)
    assert float(axis_aligned_iou(unit, box(x=0.5))) == pytest.approx(1 / 3)
    assert float(oriented_iou(unit, box(x=1.0))) == pytest.approx(0.0, abs=1e-12)  # touching
    inter = 2 * (math.sqrt(2) - 1)  # a unit square and the same square turned 45°: a regular octagon
    assert float(oriented_iou(unit, box(theta=math.pi / 4))) == pytest.approx(inter / (2 - inter))
    assert float(oriented_iou(unit, box(theta=math.pi / 2))) == pytest.approx(1.0)
    assert float(oriented_iou(unit, box(y=0.5))) == pytest.approx(1 / 3)
    moving = box(x=0.3, y=0.1, z=0.2, theta=0.4, s=(1.2, 1.0, 0.8)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda b: oriented_iou(unit, b), (moving,))


# ---- InstructScene -------------------------------------------------------------------------------------

def test_instructscene_predicates_follow_its_rules():
    from spread.baselines import predicates as P

    def codes(centres, sizes, lamps=(False, False)):
        c = torch.tensor([centres], dtype=torch.float64)
        s = torch.tensor([sizes], dtype=torch.float64)
        return P.instruct_predicates(c, s, torch.zeros(1, len(centres)), torch.tensor([lamps]),
                                     torch.ones(1, len(centres), dtype=torch.bool))[0]

    cube = [0.5, 0.5, 0.5]
    far = codes([[0, 0.25, 0], [2, 0.25, 0]], [cube, cube])
    assert far[0, 1] == P.LEFT and far[1, 0] == P.RIGHT and far[0, 0] == P.NONE
    near = codes([[0, 0.25, 0], [0, 0.25, 0.8]], [cube, cube])  # +z is "in front of"
    assert near[1, 0] == P.CLOSE_FRONT and near[0, 1] == P.CLOSE_BEHIND
    assert codes([[0, 0.25, 0], [3.5, 0.25, 0]], [cube, cube])[0, 1] == P.NONE
    stacked = codes([[0, 0.25, 0], [0.1, 0.6, 0]], [cube, [0.2, 0.2, 0.2]])
    assert stacked[1, 0] == P.ABOVE and stacked[0, 1] == P.BELOW
    overlapping = codes([[0, 0.25, 0], [0.1, 0.4, 0]], [cube, cube])  # vertical overlap: horizontal relation
    assert overlapping[1, 0] == P.CLOSE_RIGHT
    assert codes([[0, 0.25, 0], [0.1, 0.4, 0]], [cube, cube], lamps=(False, True))[1, 0] == P.ABOVE
    padded = P.instruct_predicates(torch.zeros(1, 3, 3), torch.ones(1, 3, 3), torch.zeros(1, 3),
                                   torch.zeros(1, 3, dtype=torch.bool), torch.tensor([[True, True, False]]))
    assert (padded[0, 2] == P.PAD).all() and (padded[0, :, 2] == P.PAD).all()


def test_instructscene_edge_dropout_replaces_the_graph_by_the_padding_code(batch, facts):
    from spread.baselines.instructscene import InstructScene
    from spread.baselines.predicates import PAD, drop_edges

    edges = torch.randint(0, 11, (3, 4, 4))
    dropped = drop_edges(edges, torch.tensor([True, False, True]))
    assert (dropped[0] == PAD).all() and (dropped[2] == PAD).all() and torch.equal(dropped[1], edges[1])

    seen = []
    for rate in (1.0, 0.0):
        model = InstructScene("tiny", graph_dropout=rate, **facts)
        network = model.network.train()
        original = network.edge_features
        network.edge_features = lambda e, original=original: seen.append(e.clone()) or original(e)
        model.loss(batch, network, generator=torch.Generator().manual_seed(0))
    _, graph, obj = model.boxes_and_graph(batch)
    assert (seen[0] == PAD).all()  # rate 1: every training scene gets the null graph
    assert torch.equal(seen[1], graph) and (graph[obj.mask[:, :, None] & obj.mask[:, None, :]] != PAD).all()


# ---- the platform path ---------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_fast_dev_run(dataset, tmp_path, method):
    summary = train_in_process(tmp_path / "fdr", f"experiment={method}_quick", f"data.root={dataset}",
                               "trainer.fast_dev_run=true", *QUIET, "logger=csv")
    assert summary["global_step"] == 1 and math.isfinite(summary["metrics"]["train/loss"])


@pytest.mark.parametrize("method", ["atiss", "diffuscene", "instructscene", "physcene"])
def test_checkpoint_round_trip_loads_the_method_and_samples_the_same(trained, batch, method):
    from spread.baselines import load_module

    model = load_module(trained[method])
    assert model.hparams.method == method and model.hparams.categories and model.hparams.bounds
    again = load_module(trained[method])
    state, state_again = model.state_dict(), again.state_dict()
    assert state.keys() == state_again.keys() and all(torch.equal(state[k], state_again[k]) for k in state)
    gens = lambda: [torch.Generator().manual_seed(i) for i in range(batch["x"].shape[0])]  # noqa: E731
    a = model.sample(batch, "ddim-3", generator=gens())
    b = again.sample(batch, "ddim-3", generator=gens())
    torch.testing.assert_close(a.translation, b.translation)
    torch.testing.assert_close(a.rotation, b.rotation)
    R = a.rotation[batch["mask"]]
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3).expand_as(R), atol=1e-5, rtol=0)


def test_spread_sample_refuses_spread_guidance_on_a_baseline(dataset, trained, tmp_path):
    with pytest.raises(ValueError, match="SceneDiffusion checkpoint"):
        sample_in_process(f"ckpt={trained['atiss']}", f"data.root={dataset}", f"out_dir={tmp_path / 's'}",
                          "guidance=refine", "logger=none")


def test_samples_of_every_method_pass_spread_evaluate(dataset, trained, tmp_path):
    from spread.experiments.commands import InProcessCommands

    merged = tmp_path / "all"
    merged.mkdir()
    test_graphs = {read_scene(f).scene_id: read_scene(f) for f in list_scene_files(dataset / "test")}
    for method, ckpt in trained.items():
        out = tmp_path / method
        result = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "logger=none")
        assert len(result.files) == len(test_graphs) == 3
        for f in result.files:
            scene = read_scene(f)
            source = test_graphs[str(scene.extras["conditioned_on"])]
            assert list(scene.asset_id) == list(source.asset_id)  # the object set is the graph's
            assert np.array_equal(scene.spatial, source.spatial) and not np.allclose(scene.translation,
                                                                                     source.translation)
            scene.scene_id = f"{method}__{scene.scene_id}"
            write_scene(scene, merged / f"{scene.scene_id}.npz")
    metrics = InProcessCommands().evaluate([
        f"scenes={merged}", f"reference={dataset}", f"out_dir={tmp_path / 'eval'}", "protocol.stability_runs=1",
        "ray.num_cpus=2", "progress=false", "renders=0", "logger=none", "fid.enabled=false"])
    assert metrics["n_scenes"] == 12 and metrics["n_failed"] == 0 and metrics["n_evaluated"] == 12
    assert 0.0 <= metrics["col_mesh"] <= 1.0 and 0.0 <= metrics["grecall"] <= 1.0
