"""Table 1 baselines (spread.methods): ATISS, DiffuScene, PhyScene-style guidance, InstructScene.

* Each method's own mechanism, by a known answer: ATISS's next-object likelihood does not depend on the
  order of its context; DiffuScene's slot mask hides empty slots from the loss; InstructScene's edge
  dropout hands the network the padding graph; PhyScene's box-IoU guidance term pushes overlapping boxes
  apart. Plus the oriented IoU and InstructScene's predicates on hand-made boxes.
* One sampling loop: DiffuScene, InstructScene and PhyScene's guidance sample through
  :func:`spread.model.diffusion.denoise` (PhyScene's guidance a registered term) exactly as their own loops did
  (``tests/data/one_loop.json``, recorded from those loops before they were removed).
* The platform path for every method: fast_dev_run through ``spread-train experiment=<m>_quick``, a checkpoint
  that loads back (by its hyperparameters) and samples the same, ``spread-sample`` writing scene files and
  ``spread-evaluate`` scoring all of them with no failure.

One small generated dataset (12 rooms over 12 categories: 7 train, 2 val, 3 test); torch on one thread.
"""

from __future__ import annotations

import json
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
    from spread.methods.base import dataset_facts

    return dataset_facts(dataset)


@pytest.fixture(scope="module")
def batch(dataset) -> dict:
    from spread.data import SceneDataModule

    dm = SceneDataModule(dataset, batch_size=4, num_points=1)
    dm.setup("fit")
    return next(iter(dm.train_dataloader()))


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory) -> dict[str, Path]:
    """method → a checkpoint after 3 training steps of ``experiment=<method>_quick``."""
    root = tmp_path_factory.mktemp("blruns")
    out = {}
    for method in METHODS:
        run = root / method
        summary = train_in_process(run, f"experiment={method}_quick", f"data.root={dataset}", "trainer.max_time=null",
                                   "trainer.max_steps=3", "trainer.check_val_every_n_epoch=1", *FAST_TRAIN)
        assert summary["global_step"] == 3 and math.isfinite(summary["metrics"]["val/loss"])
        out[method] = run / "checkpoints" / "last.ckpt"
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
    from spread.methods import module_class

    cls = module_class(method).config_class
    assert dict(compose("train", f"model={method}").model.config) == cls.tiny().to_dict()
    assert dict(compose("train", f"model={method}_paper").model.config) == cls.paper().to_dict()
    paper = compose("train", f"experiment={method}")
    assert paper.model.config.name == "paper" and paper.data.batch_size == 128
    assert compose("train", f"experiment={method}_quick").model.config.name == "tiny"


def test_physcene_is_diffuscene_sampled_with_the_box_iou_guidance_term():
    from spread.methods import method_spec
    from spread.guidance import GuidanceConfig

    spec = method_spec("physcene")
    assert spec.trained_from == "diffuscene" and spec.sampling == "pipeline" and spec.sample == ("guidance=physcene",)
    cfg = GuidanceConfig.from_config(compose("sample", "ckpt=x", "guidance=physcene").guidance)
    assert (cfg.mode, cfg.last_steps, cfg.grad_clip, cfg.terms) == ("sample", 10, 0.1, {"box_iou": 0.15})
    assert (cfg.collision, cfg.gravity, cfg.relation) == (0.0, 0.0, 0.0) and cfg.active
    assert cfg.first_step(50) == 40 and cfg.first_step(4) == 0


def test_an_old_physcene_checkpoint_is_refused_with_the_way_to_sample_it(facts):
    from spread.methods.diffuscene import DiffuScene

    with pytest.raises(ValueError, match="guidance=physcene"):
        DiffuScene("tiny", **facts, method="physcene", box_guidance={"weight": 0.15, "clip": 0.1, "last_steps": 10})


def test_diffusion_baselines_sample_through_the_one_loop_as_their_own_loops_did(dataset, batch, facts):
    """DiffuScene and InstructScene (graph scale 1 and 2) through ``denoise``, and DiffuScene with
    ``guidance=physcene`` through the guidance term, equal the samples their separate loops and PhyScene's
    ``BoxGuidance`` made (recorded at commit 1c238c2, same random weights, same batch, DDIM-12)."""
    import json

    from spread.assets import AssetLibrary
    from spread.methods.diffuscene import DiffuScene
    from spread.methods.instructscene import InstructScene
    from spread.guidance import GuidanceConfig, SceneGuidance
    from spread.sampling.pipeline import guidance_callback

    recorded = json.loads((Path(__file__).parent / "data" / "one_loop.json").read_text())["samples"]
    gens = lambda: [torch.Generator().manual_seed(i) for i in range(batch["x"].shape[0])]  # noqa: E731
    torch.manual_seed(0)
    ds = DiffuScene("tiny", **facts).eval()
    torch.manual_seed(1)
    ins = InstructScene("tiny", **facts).eval()
    with torch.no_grad():
        for p in list(ds.parameters()) + list(ins.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    ds.ema.module.load_state_dict(ds.network.state_dict())
    ins.ema.module.load_state_dict(ins.network.state_dict())
    library = AssetLibrary.load(dataset / "assets")
    names = sorted(library.records)
    ids = [[names[int(i)] for i in batch["asset_index"][b][batch["mask"][b]]] for b in range(batch["x"].shape[0])]
    problem = ds.denoising(batch)
    guidance = SceneGuidance(GuidanceConfig.from_config(compose("sample", "ckpt=x", "guidance=physcene").guidance),
                             library, ids, batch["physical"], batch["mask"], ds.bounds,
                             decode=lambda x: tuple(problem.decode(x)), state_dim=problem.state_dim)
    samples = {"ds": ds.sample(batch, "ddim-12", generator=gens()),
               "ds_guided": ds.sample(batch, "ddim-12", generator=gens(), callbacks=[guidance_callback(guidance)]),
               "ins": ins.sample(batch, "ddim-12", generator=gens()),
               "ins2": ins.sample(batch, "ddim-12", generator=gens(), graph_scale=2.0)}
    assert guidance.stats["steps"] == 10  # the last 10 of 12 steps
    # float32 round-off: recorded under an earlier torch; torch 2.14 moves one rotation entry of every sample set by
    # 1.6e-5 (the same entry in all four: the rot6d decode's arithmetic, not the loops) and ins2's translation by
    # 1.3e-5. A step of a loop done differently moves them by orders of magnitude more (the guided samples, below).
    for name, poses in samples.items():
        for part in ("translation", "rotation"):
            expected = torch.tensor(recorded[f"{name}_{part}"], dtype=torch.float32)
            torch.testing.assert_close(getattr(poses, part), expected, atol=5e-5, rtol=0, msg=f"{name} {part}")
    moved = (samples["ds_guided"].translation - samples["ds"].translation).abs().max()
    assert moved > 5e-4  # the guidance did act (10× the tolerance)


# ---- ATISS -------------------------------------------------------------------------------------------

def test_diffusion_baselines_steps_read_nothing_on_the_host_so_cuda_graphs_record_them_by_default(batch, facts):
    """DiffuScene's and InstructScene's network calls in the one loop (with and without classifier-free guidance on
    the graph, and the imputation hook) read no tensor on the host: ``sampling.cuda_graph=null`` records them on CUDA,
    as SPREAD's (issue 29: the same for the baselines that share the loop)."""
    from spread.methods.diffuscene import DiffuScene
    from spread.methods.instructscene import InstructScene
    from spread.model.opcount import OperatorCounter
    from spread.sampling.pipeline import ScenePipeline

    for cls in (DiffuScene, InstructScene):
        model = cls("tiny", **facts).eval()
        assert ScenePipeline(model, None, "ddim-50").cuda_graph is True
        for graph_scale in (1.0, 2.0):
            with torch.no_grad():
                problem = model.denoising(batch, True, graph_scale)
                x = torch.randn(*problem.mask.shape, problem.state_dim)
                t = torch.full((problem.mask.shape[0],), 300)
                problem.eps_fn(x, t)
                with OperatorCounter() as counter:
                    problem.x0_hook(problem.eps_fn(x, t), None)
            assert counter.total > 100 and counter.syncs == 0, (cls.__name__, graph_scale)


def test_atiss_likelihood_does_not_depend_on_context_order(batch, facts):
    from spread.methods.atiss import ATISS

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
    from spread.methods import dmll

    params = torch.tensor([[0.3, -0.2, 0.1, -0.4, 0.5, -3.0]])  # two logistics: [π, μ, log s]
    grid = torch.linspace(-1, 1, 256)  # the bin centres
    total = dmll.log_prob(params.expand(256, -1), grid).exp().sum()
    torch.testing.assert_close(total, torch.tensor(1.0), atol=1e-4, rtol=0)
    peaked = torch.tensor([[6.0, -6.0, 0.3, -0.6, -4.0, -4.0]])  # one component, scale e^-4
    x = dmll.sample(peaked.expand(2000, -1), torch.rand(2000, 2, generator=torch.Generator().manual_seed(0)))
    assert x.min() >= -1 and x.max() <= 1 and abs(float(x.mean()) - 0.3) < 0.01 and float(x.std()) < 0.1


# ---- DiffuScene ----------------------------------------------------------------------------------------

def test_diffuscene_slot_mask_hides_empty_slots_from_the_loss(batch, facts):
    from spread.methods.diffuscene import DiffuScene

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


def test_box_iou_guidance_term_moves_overlapping_boxes_apart_in_x_z_and_heading_only(dataset, batch, facts):
    """Every object of the batch's scenes stacked near the room's centre: a guidance step of the registered term
    box_iou on DiffuScene's states lowers the summed box IoU, moves only centre x, z and (cos θ, sin θ), each value
    by at most the clip, and repeated steps separate the boxes."""
    from spread.assets import AssetLibrary
    from spread.methods.diffuscene import DiffuScene
    from spread.guidance import GuidanceConfig, SceneGuidance

    model = DiffuScene("tiny", **facts).eval()
    problem = model.denoising(batch)
    known, mask, _ = model.state(batch)
    x = known.clone()
    x[..., 0] = 0.02 * torch.arange(x.shape[1])  # centres 2 % of the room apart in x, z = 0: heavy overlap
    x[..., 2] = 0.0
    x = x * mask[..., None]
    library = AssetLibrary.load(dataset / "assets")
    names = sorted(library.records)
    ids = [[names[int(i)] for i in batch["asset_index"][b][mask[b]]] for b in range(mask.shape[0])]
    config = GuidanceConfig("sample", collision=0.0, gravity=0.0, relation=0.0, terms={"box_iou": 0.15},
                            grad_clip=0.1)
    guide = SceneGuidance(config, library, ids, batch["physical"], mask, model.bounds,
                          decode=lambda s: tuple(problem.decode(s)), state_dim=problem.state_dim)
    loss0 = float(guide.losses(x, which=["box_iou"])["box_iou"])
    y = guide.step(x)
    assert float(guide.losses(y, which=["box_iou"])["box_iou"]) < loss0
    moved = (y - x).abs()
    assert moved[..., [0, 2, 6, 7]].max() > 0 and moved[..., [0, 2, 6, 7]].max() <= 0.1 + 1e-7
    assert torch.equal(y[..., [1, 3, 4, 5]], x[..., [1, 3, 4, 5]]) and torch.equal(y[..., 8:], x[..., 8:])
    for _ in range(20):
        y = guide.step(y)
    assert float(guide.losses(y, which=["box_iou"])["box_iou"]) < 0.5 * loss0


def test_oriented_iou_known_answers_and_gradients():
    from spread.box_geometry import axis_aligned_iou, oriented_iou

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
    from spread.methods import predicates as P

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
    from spread.methods.instructscene import InstructScene
    from spread.methods.predicates import PAD, drop_edges

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


@pytest.mark.parametrize("method", ["atiss", "diffuscene", "instructscene"])
def test_checkpoint_round_trip_loads_the_method_and_samples_the_same(trained, batch, method):
    from spread.methods import load_module

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


def test_spread_sample_refuses_guidance_for_a_method_that_samples_its_own_way(dataset, trained, tmp_path):
    with pytest.raises(ValueError, match="samples its own way"):
        sample_in_process(f"ckpt={trained['atiss']}", f"data.root={dataset}", f"out_dir={tmp_path / 's'}",
                          "guidance=refine", "logger=none")


def test_a_setting_a_method_does_not_read_makes_no_second_identity_and_its_label_says_what_ran(dataset, trained,
                                                                                                 tmp_path):
    """ATISS reads no sampler, graph scale or precision, DiffuScene no graph scale: sampled again with other values
    of these, the same folder is re-used as it is (same identity, same bytes), and ATISS's label is its own loop,
    not a DDIM it never ran. InstructScene reads the graph scale: there it is another identity."""
    from spread.methods.registry import method_spec
    from spread.runtime.fingerprint import settings

    base = [f"data.root={dataset}", "logger=none", "progress=false", "renders=0", "figures=0", "workers=0"]
    for method, ignored, read in (("atiss", ["sampler=ddpm", "graph_scale=3.0", "precision=bf16"], None),
                                  ("diffuscene", ["graph_scale=3.0"], None),
                                  ("instructscene", [], "graph_scale=3.0")):
        out = tmp_path / method
        first = sample_in_process(f"ckpt={trained[method]}", f"out_dir={out}", *base, "sampler.steps=4")
        made = {p.name: p.read_bytes() for p in first.files}
        if ignored:
            again = sample_in_process(f"ckpt={trained[method]}", f"out_dir={out}", *base, "sampler.steps=4", *ignored)
            assert again.written == [] and again.manifest["fingerprint"] == first.manifest["fingerprint"], method
            assert {p.name: p.read_bytes() for p in again.files} == made
        if read:
            again = sample_in_process(f"ckpt={trained[method]}", f"out_dir={out}", *base, "sampler.steps=4", read)
            assert again.manifest["redone_because"] and "graph_scale" in again.manifest["redone_because"]
    atiss = json.loads((tmp_path / "atiss" / "sampling.json").read_text())
    assert atiss["sampler"] == method_spec("atiss").ignores["sampler"] == "one pass per object"
    assert atiss["fingerprint"]["sampling"]["sampler"] == "one pass per object"
    assert settings(atiss["fingerprint"])["sampler"] == "one pass per object"
    assert "sampler=one pass per object " in str(read_scene(next((tmp_path / "atiss" / "scenes").glob("*.npz")))
                                                  .extras["source"])  # the scenes' provenance says the same
    diffuscene = json.loads((tmp_path / "diffuscene" / "sampling.json").read_text())
    assert diffuscene["sampler"] == "ddim-4" and diffuscene["fingerprint"]["sampling"]["graph_scale"] == 1.0
    # declared, never inferred: a plug-in's own loop may read the sampler it is handed
    from spread.methods.registry import MethodSpec

    assert MethodSpec("mine", object, sampling="own").ignores == {}
    from spread.registry import RegistryError

    with pytest.raises(RegistryError, match=r"ignores=\['seed'\].*'sampler', 'graph_scale', 'precision'"):
        MethodSpec("mine", object, ignores={"seed": 0})


def test_a_guidance_mode_a_method_runs_as_another_is_declared_once_and_asked_by_its_sampling_and_identity():
    from spread.guidance import GuidanceConfig
    from spread.methods import MethodSpec, method_spec
    from spread.methods.release import ReleaseDiffusion

    paper, refine = GuidanceConfig(mode="paper"), GuidanceConfig(mode="refine")
    release = method_spec("release")
    assert release.guidance_run(paper) == GuidanceConfig(mode="release")
    assert ReleaseDiffusion.resolve_guidance(paper) == release.guidance_run(paper)  # what the pipeline runs
    assert release.guidance_run(refine) is refine and method_spec("spread").guidance_run(paper) is paper
    off = GuidanceConfig(mode="none")
    assert release.guidance_run(off) is off
    with pytest.raises(ValueError, match="key 'mode' is 'papr', choose from"):  # a declared mode that is none
        MethodSpec("mine", object, guidance_modes={"paper": "papr"}).guidance_run(paper)


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_samples_of_every_method_pass_spread_evaluate(dataset, trained, tmp_path):
    from spread.commands.in_process import InProcessCommands

    merged = tmp_path / "all"
    merged.mkdir()
    test_graphs = {read_scene(f).scene_id: read_scene(f) for f in list_scene_files(dataset / "test")}
    rows = [(m, ckpt, []) for m, ckpt in trained.items()]
    rows += [("physcene", trained["diffuscene"], ["guidance=physcene"]),  # PhyScene's row: DiffuScene + its term
             ("instructscene_refined", trained["instructscene"], ["guidance=refine", "guidance.iterations=2"])]
    for method, ckpt, extra in rows:
        out = tmp_path / method
        result = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "logger=none", *extra)
        assert len(result.files) == len(test_graphs) == 3
        if extra:  # guided through the pipeline's callbacks: the guidance took its steps
            assert result.manifest["guidance"]["mode"] == {"guidance=physcene": "sample"}.get(extra[0], "refine")
            assert result.manifest["guidance_totals"]["steps"] > 0
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
    assert metrics["n_scenes"] == 15 and metrics["n_failed"] == 0 and metrics["n_evaluated"] == 15
    assert 0.0 <= metrics["col_mesh"] <= 1.0 and 0.0 <= metrics["grecall"] <= 1.0
