"""The GPU paths (issue 29), checked on CPU: the dense nearest search (torch, and its Triton kernel under Triton's
interpreter) finds what the pruned search finds, the lean network computes what the network computed before the
rewrite (recorded outputs, old checkpoints load), a step launches few kernels and reads nothing on the host, and the
sampling loop's states are diffusers' to the bit."""

import json
import os
import subprocess
import sys

import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.utils._python_dispatch import TorchDispatchMode

from model_fixture import FIXTURE, network, outputs, seeded_state
from spread.model.geometry import prepare_points, signed_chamfer_features, signed_distances
from spread.model.nearest import nearest_other_point
import spread.model.nearest_dense as nd
from spread.model.nearest_dense import nearest_dense_search

BOUNDS = [-3.0, 0.0, -3.0, 3.0, 2.5, 3.0]


def scenes(sizes=(7, 3, 1, 5), n_max=8, m=70, seed=0, spread=1.2):
    """Random boxes-ish point clouds: scenes of the given sizes (a lone object, padding), posed close together."""
    g = torch.Generator().manual_seed(seed)
    B = len(sizes)
    mask = torch.arange(n_max)[None, :] < torch.tensor(sizes)[:, None]
    points = (torch.rand(B, n_max, m, 3, generator=g) - 0.5) * 0.6
    normals = torch.nn.functional.normalize(torch.randn(B, n_max, m, 3, generator=g), dim=-1)
    t = (torch.rand(B, n_max, 3, generator=g) - 0.5) * 2 * spread
    R = torch.from_numpy(Rotation.random(B * n_max, random_state=seed).as_matrix()).float().view(B, n_max, 3, 3)
    return points, normals, t, R, mask


def distances_of(world, index):
    flat = world.reshape(world.shape[0], -1, 3)
    return (flat - flat.gather(1, index[..., None].expand(-1, -1, 3))).norm(dim=-1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_search_finds_the_pruned_searchs_and_brute_forces_nearest_points_but_exact_ties(seed):
    """On the CPU ``dense`` searches with the k-d trees; brute force (CUDA's search without Triton, up to its limit)
    is checked here beside it."""
    points, normals, t, R, mask = scenes(seed=seed)
    world = torch.einsum("bnij,bnmj->bnmi", R, points) + t[:, :, None]
    dense = nearest_dense_search(world, mask)
    pruned = nearest_other_point(world, points, t, R, mask)
    full = nearest_other_point(world, points, t, R, mask, prune=False)
    M = points.shape[2]
    brute = nd._brute_force(world.reshape(world.shape[0], -1, 3), mask.repeat_interleave(M, dim=1), M)
    real = mask[:, :, None].expand(-1, -1, points.shape[2]).reshape(mask.shape[0], -1)
    lone = (mask.sum(1) == 1)[:, None].expand_as(real)
    keep = real & ~lone
    d_dense, d_pruned = distances_of(world, dense), distances_of(world, pruned)
    differ = (dense != pruned) & keep
    assert torch.allclose(d_dense[keep], d_pruned[keep], atol=1e-6), "same nearest distance everywhere"
    assert (differ.sum() <= 0.001 * keep.sum()), "indices differ only at (near-)ties"
    assert ((dense != full) & keep).sum() <= 0.001 * keep.sum()
    assert torch.allclose(distances_of(world, brute)[keep], d_dense[keep], atol=1e-6)
    assert ((dense != brute) & keep).sum() <= 0.001 * keep.sum()
    owner = dense.div(points.shape[2], rounding_mode="floor")
    own = torch.arange(real.shape[1])[None].div(points.shape[2], rounding_mode="floor")
    assert (owner != own)[keep].all(), "never a point of the query's own object"
    assert mask.gather(1, owner.clamp(max=mask.shape[1] - 1))[keep].all(), "never a padding object"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_tree_search_finds_the_exact_nearest_distance_and_refuses_nothing_the_others_find(seed):
    """``nearest=tree`` (a k-d tree per object, the CPU's default): every query's distance is brute force's, taken in
    float64 over every other real object (so at least as near as the float32 searches'), indices equal but at ties,
    never the query's own object or a padding one; index 0 for padding and a lone object's points; diverged (NaN)
    points answered as the pruned search answers them; and ``auto`` chooses it on the CPU, ``dense`` on CUDA and
    inside a compiled step."""
    from spread.model.geometry import resolve_search
    from spread.model.nearest import nearest_other_point_tree

    points, normals, t, R, mask = scenes(seed=seed)
    world = torch.einsum("bnij,bnmj->bnmi", R, points) + t[:, :, None]
    B, N, M, _ = world.shape
    tree = nearest_other_point_tree(world, mask)
    flat = world.reshape(B, N * M, 3).double()
    d2 = torch.cdist(flat, flat).square()
    owner = torch.arange(N * M) // M
    blocked = (owner[:, None] == owner[None, :])[None] | ~mask.repeat_interleave(M, 1)[:, None, :]
    d2 = d2.masked_fill(blocked, float("inf"))
    exact = d2.argmin(-1)
    real = mask.repeat_interleave(M, 1) & (mask.sum(1, keepdim=True) > 1)
    d_tree, d_exact = distances_of(world.double(), tree), distances_of(world.double(), exact)
    assert torch.allclose(d_tree[real], d_exact[real], atol=1e-12, rtol=0)
    assert ((tree != exact) & real).sum() <= 0.001 * real.sum()
    assert (owner[tree][real] != owner[None].expand(B, -1)[real]).all()
    assert mask.gather(1, (tree // M).clamp(max=N - 1))[real].all()
    assert (tree[~real] == 0).all()
    pruned = nearest_other_point(world, points, t, R, mask)
    assert (distances_of(world.double(), pruned)[real] >= d_tree[real] - 1e-12).all()
    diverged = world.clone()
    diverged[0, 1, 2, 0] = float("nan")  # no tree takes it: the pruned search's answer, as before
    eye, zero = torch.eye(3).expand(B, N, 3, 3), torch.zeros(B, N, 3)
    assert torch.equal(nearest_other_point_tree(diverged, mask),
                       nearest_other_point(diverged, diverged, zero, eye, mask))  # written out: the test's own answer
    assert resolve_search("auto", torch.device("cpu")) == "tree"
    assert resolve_search("auto", torch.device("cuda")) == "dense"
    assert torch.compile(lambda: resolve_search("auto", torch.device("cpu")), backend="eager", fullgraph=True)() \
        == "dense"


def test_dense_and_tree_features_equal_the_pruned_features_within_1e_5():
    points, normals, t, R, mask = scenes(sizes=(6, 4, 2), n_max=7, m=90, seed=4, spread=0.6)
    a = signed_chamfer_features(points, normals, t, R, mask, search="pruned")
    b = signed_chamfer_features(points, normals, t, R, mask, search="dense")
    c = signed_chamfer_features(points, normals, t, R, mask, search="tree")
    assert (a - b).abs().max() < 1e-5 and (a - c).abs().max() < 1e-5
    assert (a[..., 3] < 0).any(), "penetrating points occur (both signs checked)"
    # the network's path: a per-sample cloud in Morton order gives the same set of features, reordered
    cloud = prepare_points(points, normals, mask, morton=True)
    d = signed_distances(cloud, t, R, "dense")
    ref = signed_distances(prepare_points(points, normals, mask), t, R, "pruned")
    assert torch.allclose(d.sort(-1).values, ref.sort(-1).values, atol=1e-5)


KERNEL_CHECK = """
import itertools, torch, warnings
import spread.model.nearest_dense as nd
from spread.model.nearest import morton_order
assert nd.triton_available(torch.device('cpu'))
g = torch.Generator().manual_seed(0)
B, N, M = 3, 5, 45  # 45 points: a ragged last tile of every object
mask = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 0, 0, 0], [1, 0, 0, 0, 0]], dtype=torch.bool)  # padding, a lone object
x = torch.randn(B, N, 9, generator=g) * 0.4
pts = (torch.rand(B, N, M, 3, generator=g) - 0.5) * 0.6
nrm = torch.nn.functional.normalize(torch.randn(B, N, M, 3, generator=g), dim=-1)
off, scale = torch.tensor([0.0, 1.2, 0.0]), torch.tensor([3.0, 1.2, 3.0])
vp = mask[:, :, None].expand(B, N, M).reshape(B, N * M)
real = vp & (mask.sum(1, keepdim=True) > 1)
# the default, and smaller tiles with the index kept apart from d² (benchmarks/search_blocks.py times both)
blocks = [(nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS), (16, 32, 4, not nd.PACKED_KEYS)]
orders = (None, morton_order(pts)[..., None].expand(-1, -1, -1, 3))
for (bq, bk, warps, packed), order in itertools.product(blocks, orders):
    nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS = bq, bk, warps, packed
    p = pts if order is None else pts.gather(2, order)
    n = nrm if order is None else nrm.gather(2, order)
    world, normals, boxes = torch.ops.spread.pose_states(x, off, scale, p, n, nd.BLOCK_K)
    ref = nd.pose_torch(x, off, scale, p, n, nd.BLOCK_K)
    assert all((a - b).abs().max() < 1e-6 for a, b in zip((world, normals, boxes), ref))
    index, d = torch.ops.spread.signed_nearest(world, normals, boxes, mask, 10.0)
    ref_index = nd._brute_force(world.reshape(B, -1, 3), vp, M)
    ref_d = nd.sign_distances(world.reshape(B, -1, 3), normals.reshape(B, -1, 3), ref_index, mask, M, 10.0)
    assert (d - ref_d).abs().max() < 1e-6, (d - ref_d).abs().max()
    assert torch.equal(index[real], ref_index[real]) and (index[~real] == 0).all()
    assert (d.view(B, N, M)[2, 0] == 10.0).all() and (d.view(B, N, M)[1, 2:] == 0).all()
    other = nd.tile_boxes(world, bk // 2)  # boxes made for another tile size: refused by name, not searched wrongly
    try:
        torch.ops.spread.signed_nearest(world, normals, other, mask, 10.0)
        raise AssertionError("boxes of another block were searched")
    except ValueError as error:
        assert "BLOCK_K" in str(error)
# exact ties: points repeated within a tile, and objects 1 and 2 of scene 0 the same points at the same pose in
# reverse order (other tiles: a search may meet object 2's copy first) — the smallest index wins (torch's argmin
# rule), either way of keeping the nearest
tx, tp = x.clone(), pts.clone()
tp[:, :, 1::2] = tp[:, :, 0:-1:2]
tx[0, 2], tp[0, 2] = tx[0, 1], tp[0, 1].flip(0)
for bq, bk, warps, packed in blocks:
    nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS = bq, bk, warps, packed
    world, normals, boxes = torch.ops.spread.pose_states(tx, off, scale, tp, nrm, nd.BLOCK_K)
    index, _ = torch.ops.spread.signed_nearest(world, normals, boxes, mask, 10.0)
    assert torch.equal(index[real], nd._brute_force(world.reshape(B, -1, 3), vp, M)[real]), (bq, packed)
    hit = index[0].view(N, M)  # scene 0: objects 0, 3, 4 never find object 2 (object 1 is it, smaller); nor a point
    assert not ((hit[[0, 3, 4]] // M) == 2).any() and ((hit % M) % 2 == 0)[hit // M != 2].all(), (bq, packed)  # copy
nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS = blocks[0]
assert not nd._BROKEN
# a kernel Triton cannot build: said once, and the torch path gives the same answer
class Broken:
    def __getitem__(self, grid):
        def launch(*a, **k):
            raise RuntimeError("no such instruction")
        return launch
triton_, pose_k, search_k = nd._triton_kernels()
nd._KERNELS = (triton_, Broken(), Broken())
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    world2, normals2, boxes2 = torch.ops.spread.pose_states(x, off, scale, pts, nrm, nd.BLOCK_K)
    index2, d2 = torch.ops.spread.signed_nearest(world2, normals2, boxes2, mask, 10.0)
assert nd._BROKEN == {"pose", "search"} and len([w for w in caught if "torch implementation" in str(w.message)]) == 2
ref = nd.pose_torch(x, off, scale, pts, nrm, nd.BLOCK_K)
assert torch.equal(world2, ref[0])
print("kernels ok")
"""


def test_the_triton_kernels_match_torch_under_the_interpreter_and_fall_back_when_they_fail(tmp_path):
    """The CUDA kernels' code (pose; signed search), run by Triton's interpreter on CPU tensors (TRITON_INTERPRET=1
    must be set before the kernels are defined: a process of its own), against the torch implementations and exact
    brute force — with and without Morton order, padding, a lone object, a ragged last tile, at the default tile sizes
    and smaller ones, the nearest kept as one packed key or d² and index apart (``benchmarks/search_blocks.py``), exact
    ties going to the smallest index; boxes made for another tile size are refused; and a kernel
    that fails to build leaves the torch path running, with one warning each."""
    pytest.importorskip("triton")
    script = tmp_path / "kernels.py"
    script.write_text(KERNEL_CHECK)
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0 and "kernels ok" in done.stdout, done.stderr[-3000:]


def _recorded_network(variant):
    recorded = json.loads(FIXTURE.read_text())[variant]
    net = network(variant)
    net.load_state_dict({**seeded_state(recorded["parameters"]), "bounds": net.bounds})  # the old layout's names
    return net, recorded


@pytest.mark.parametrize("variant", ["base", "geometry"])
def test_the_network_computes_what_it_computed_before_the_rewrite(variant):
    """tests/data/model_outputs.json was written by the code before the GPU rewrite (commit 35871fd): weights in
    its parameter layout load into today's (fused projections, stacked geometry weights) and give the same ε̂ and
    the same DDIM-10 samples (float rounding: the folded LayerNorm and the fused AdaLN round differently)."""
    net, recorded = _recorded_network(variant)
    now = outputs(net)
    for key in ("eps_10", "eps_500", "eps_990", "ddim10"):
        assert torch.allclose(torch.tensor(now[key]), torch.tensor(recorded[key]), atol=1e-5, rtol=0), key


def test_old_checkpoints_convert_and_new_ones_round_trip():
    from spread.model.network import upgrade_state_dict

    net, recorded = _recorded_network("geometry")
    old_names = {name for name, _ in recorded["parameters"]}
    new_state = net.state_dict()
    assert "perceiver.context_kv" in new_state and "denoiser.geometry_kv.weight" in new_state
    assert not any(k.endswith("to_q.weight") and ".perceiver." in k and ".4." in k for k in new_state)
    upgraded = upgrade_state_dict(net, seeded_state(recorded["parameters"]))
    assert set(upgraded) == set(new_state) - {"bounds"} and not (old_names - set(new_state)) <= set()
    for key, value in upgraded.items():
        assert torch.equal(value, new_state[key]), key
    again = network("geometry")
    again.load_state_dict(new_state)  # today's layout loads as it is
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), new_state.values()))


def test_a_step_reads_nothing_on_the_host_and_geometry_launches_at_most_half_again_base(monkeypatch):
    """The paper config's widths at a small batch (the count does not depend on the sizes: 10 and 40 objects give
    the same): +Geometry dispatches at most 1.5× base's kernel operators per denoising step and per training step
    (issue 29; RESULTS.md has the paper-size counts), no Python loop over objects, blocks or points makes it grow,
    and no operator of a denoising step reads a tensor value on the host. Counted on CPU tensors taking CUDA's
    paths (padded point tokens, formed keys/values: what a GPU launches), as the benchmark counts them."""
    import spread.model.perceiver as perceiver
    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    from spread.model.opcount import OperatorCounter
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_model import synthetic_batch

    monkeypatch.setattr(perceiver, "token_multiple", lambda device: perceiver.CHANNEL_MULTIPLE)
    monkeypatch.setattr(perceiver, "cross_mode", lambda device: "formed")

    def count(variant, n, train=False):
        torch.manual_seed(0)
        model = SceneDiffusion(variant, ModelConfig(num_points=24, nearest="dense"), bounds=BOUNDS)
        batch = synthetic_batch(2, n, 24)
        if train:
            model.train()
            with OperatorCounter() as c:
                model.training_loss(batch, timesteps=torch.tensor([100, 700])).backward()
            return c.total, c.syncs
        net = model.ema.module.eval()
        with torch.no_grad():
            cond = net.condition(batch)
            with OperatorCounter() as c:
                net(batch["x"], torch.full((2,), 500), cond)
        return c.total, c.syncs

    base, base_syncs = count("base", 10)
    geo10, syncs = count("geometry", 10)
    geo40, _ = count("geometry", 40)
    assert syncs == 0 and base_syncs == 0
    assert geo40 == geo10
    assert geo10 <= 1.5 * base
    train_base, _ = count("base", 10, train=True)
    train_geo, _ = count("geometry", 10, train=True)
    assert train_geo <= 1.5 * train_base


def test_the_sampling_loop_gives_diffusers_states_to_the_bit():
    """The loop keeps its schedule on the host and draws ancestral noise up front (per scene, in the order diffusers
    would); its states equal a loop that calls diffusers' ``scheduler.step`` with the generators each step."""
    from spread.model import Sampler
    from spread.model.diffusion import NOISE_ROWS, reverse_process

    B, N = 3, 5
    mask = torch.ones(B, N, dtype=torch.bool)
    mask[2, 3:] = False
    W = torch.randn(9, 9, generator=torch.Generator().manual_seed(0)) * 0.3

    def eps_fn(x, t):
        return torch.tanh(x @ W) * (1 + t[:, None, None] / 1000)

    def reference(sampler):  # the loop before the rewrite, as it was
        keep = mask[..., None].float()
        scheduler = sampler.scheduler()
        scheduler.set_timesteps(sampler.num_steps)
        gens = [torch.Generator().manual_seed(i) for i in range(B)]
        x = torch.stack([torch.randn((max(N, NOISE_ROWS), 9), generator=g)[:N] for g in gens]) * keep
        extra = {"eta": sampler.eta} if sampler.kind == "ddim" else {}
        for t in scheduler.timesteps:
            eps = eps_fn(x, torch.full((B,), int(t))) * keep
            a = float(scheduler.alphas_cumprod[int(t)])
            x0 = ((x - (1 - a) ** 0.5 * eps) / a ** 0.5).clamp(-1, 1)
            eps = (x - a ** 0.5 * x0) / (1 - a) ** 0.5 * keep
            x = scheduler.step(eps, t, x, generator=gens, **extra).prev_sample * keep
        return x

    for sampler in (Sampler("ddpm", 1000), Sampler("ddpm", 30), Sampler("ddim", 20, eta=0.6), Sampler("ddim", 20),
                    Sampler("dpmsolver++", 12)):
        got = reverse_process(sampler, eps_fn, mask, generator=[torch.Generator().manual_seed(i) for i in range(B)])
        assert torch.equal(got, reference(sampler)), sampler


def test_ema_counts_its_updates_on_the_host_and_rereads_a_loaded_count():
    from torch import nn

    from spread.model.ema import EMA

    m = nn.Linear(2, 2)
    ema = EMA(m, 0.999)
    for _ in range(3):
        ema.update(m)
    assert int(ema.num_updates) == 3 and ema.current_decay() == pytest.approx(4 / 13)
    other = EMA(m, 0.999)
    other.load_state_dict(ema.state_dict())
    assert other.current_decay() == pytest.approx(4 / 13)
    other.update(m)
    assert int(other.num_updates) == 4 and other.current_decay() == pytest.approx(5 / 14)


def test_bf16_and_cuda_graph_settings_sample_on_cpu_and_bf16_stays_close(tmp_path):
    """``cuda_graph`` is ignored off CUDA; ``precision=bf16`` autocasts the network (float32 geometry features):
    close to float32, not equal."""
    from spread.model.diffusion import denoise
    from spread.model.module import SceneDiffusion
    from spread.sampling.pipeline import ScenePipeline
    from model_fixture import CONFIG, batch
    from spread.model import ModelConfig

    model = SceneDiffusion("geometry", ModelConfig(**CONFIG), bounds=BOUNDS).eval()
    recorded = json.loads(FIXTURE.read_text())["geometry"]  # weights that make samples move (a fresh head is zero)
    model.ema.module.load_state_dict({**seeded_state(recorded["parameters"]), "bounds": model.ema.module.bounds})
    b = batch()
    states = {}
    for precision in ("32", "bf16"):
        pipe = ScenePipeline(model, None, "ddim-5", cuda_graph=True, precision=precision)
        problem = pipe.on_device(model.denoising(b))
        states[precision] = denoise(problem, pipe.sampler, [torch.Generator().manual_seed(i) for i in range(3)])
    assert torch.isfinite(states["bf16"]).all()
    assert 0 < (states["bf16"] - states["32"]).abs().max() < 0.1
    with pytest.raises(ValueError, match="precision"):
        ScenePipeline(model, None, "ddim-5", precision="fp8")


def test_cuda_graphs_record_by_default_only_the_models_whose_step_reads_nothing_on_the_host(monkeypatch):
    """``sampling.cuda_graph=null`` (the default) records a step where the model says it reads nothing on the host
    (``cuda_graph_capturable``) — and each such SPREAD configuration's step does read nothing (counted, with CUDA's
    search: ``dense``); ``true`` records or refuses by name, ``false`` never; the tree and pruned searches, the parts
    distance and the release's network are left eager by default (the pruned search's reads counted)."""
    import dataclasses

    from spread.methods.release import ReleaseDiffusion
    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    from spread.model.opcount import OperatorCounter
    from spread.sampling.pipeline import ScenePipeline, resolve_cuda_graph
    from model_fixture import CONFIG, batch

    assert resolve_cuda_graph(None, True) is True and resolve_cuda_graph(None, True, calls=9) is False
    assert resolve_cuda_graph(None, None) is False and resolve_cuda_graph(None, False) is False
    assert resolve_cuda_graph(True, None) is True and resolve_cuda_graph(False, True) is False
    with pytest.raises(ValueError, match="cuda_graph must be true, false or null.*'yes'"):
        resolve_cuda_graph("yes", True)
    assert ReleaseDiffusion.cuda_graph_capturable is False
    b = batch()
    x, t = torch.randn(*b["x"].shape), torch.full((b["x"].shape[0],), 400)

    def host_reads(model, graph_scale=1.0, geometry_scale=1.0):
        extra = {"geometry_scale": geometry_scale} if geometry_scale != 1.0 else {}
        with torch.no_grad():
            problem = model.denoising(b, True, graph_scale, **extra)
            problem.eps_fn(x, t)
            with OperatorCounter() as counter:
                problem.eps_fn(x, t)
        return counter.syncs

    config = ModelConfig(**CONFIG)
    for variant, fields, graph_scale, geometry_scale in [
            ("base", {}, 1.0, 1.0), ("base", {}, 2.0, 1.0), ("geometry", {"nearest": "auto"}, 1.0, 1.0),
            ("geometry", {"nearest": "dense"}, 2.0, 2.0),
            ("geometry", {"nearest": "dense", "geometry_at": "x0_hat", "geometry_summary": True}, 2.0, 2.0)]:
        model = SceneDiffusion(variant, dataclasses.replace(config, **fields), bounds=BOUNDS).eval()
        assert model.cuda_graph_capturable, (variant, fields)
        assert ScenePipeline(model, None, "ddim-50").cuda_graph is True
        assert ScenePipeline(model, None, "ddim-50", cuda_graph=False).cuda_graph is False
        # a loop too short to earn its recording back (three calls) stays eager by default, unless asked
        assert ScenePipeline(model, None, "ddim-5").cuda_graph is False
        assert ScenePipeline(model, None, "ddim-5", {"mode": "refine", "iterations": 10}).network_calls() == 15
        assert ScenePipeline(model, None, "ddim-5", cuda_graph=True).cuda_graph is True
        cuda_search = dataclasses.replace(config, **{**fields, "nearest": "dense"})  # auto's search on CUDA
        counted = SceneDiffusion(variant, cuda_search, bounds=BOUNDS).eval()
        assert host_reads(counted, graph_scale, geometry_scale) == 0, (variant, fields, graph_scale)
    for fields in ({"nearest": "tree"}, {"nearest": "pruned"}, {"geometry_distance": "parts"}):
        model = SceneDiffusion("geometry", dataclasses.replace(config, **fields), bounds=BOUNDS).eval()
        assert not model.cuda_graph_capturable, fields
        assert ScenePipeline(model, None, "ddim-50").cuda_graph is False
        with pytest.raises(ValueError, match="cuda_graph=true: a .* step cannot be captured.*cuda_graph=false"):
            ScenePipeline(model, None, "ddim-5", cuda_graph=True)
        if fields["nearest" if "nearest" in fields else "geometry_distance"] == "pruned":
            assert host_reads(model) > 0  # its blocks' sizes are read every step
    # on a CUDA device where the search kernel failed, dense falls back to torch (the pruned search beyond its limit)
    import spread.model.nearest_dense as dense

    monkeypatch.setattr(dense, "_BROKEN", {"search"})
    assert not dense.graph_safe("cuda") and dense.graph_safe("cpu")
    monkeypatch.setattr(dense, "graph_safe", lambda device: False)
    model = SceneDiffusion("geometry", config, bounds=BOUNDS).eval()
    assert not model.cuda_graph_capturable and ScenePipeline(model, None, "ddim-50").cuda_graph is False
    assert SceneDiffusion("base", config, bounds=BOUNDS).cuda_graph_capturable


def test_the_training_loss_compiles_as_one_graph_and_equals_eager():
    """``model.compile=true`` compiles the loss whole (no data-dependent shapes or branches: the shape tokens of a
    compiled step encode every slot and zero the padding; the bounds check is eager-only) and changes nothing:
    the same loss and gradients, padding objects and shared shapes included (aot_eager: torch.compile's tracing
    without a C++ compiler)."""
    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_model import synthetic_batch

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", ModelConfig(num_points=32, nearest="dense", dim=32, depth=1, num_latents=8,
                                                   heads=2), bounds=BOUNDS)
    model.train()
    batch = synthetic_batch(3, 5, 32)
    batch["mask"][2, 3:] = False
    batch["shape_index"] = keys = torch.tensor([[0, 1, 0, 2, 1], [3, 3, 4, 5, 6], [7, 8, 7, 0, 0]])
    for b, n, first in ((0, 2, (0, 0)), (0, 4, (0, 1)), (1, 1, (1, 0)), (2, 2, (2, 0))):  # one shape, one cloud
        assert keys[b, n] == keys[first]
        for key in ("points", "normals"):
            batch[key][b, n] = batch[key][first]

    def loss_and_grads(fn):
        torch.manual_seed(1)  # the loss draws its noise
        model.zero_grad(set_to_none=True)
        loss = fn(batch, timesteps=torch.tensor([100, 700, 400]))
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.network.parameters() if p.grad is not None]

    eager, eager_grads = loss_and_grads(model.training_loss)
    compiled, compiled_grads = loss_and_grads(torch.compile(model.training_loss, backend="aot_eager", fullgraph=True))
    assert torch.allclose(compiled, eager, atol=1e-6), (compiled, eager)
    assert len(compiled_grads) == len(eager_grads) > 0
    worst = max(float((a - b).abs().max() / b.abs().max().clamp(min=1e-12)) for a, b in zip(compiled_grads, eager_grads))
    assert worst < 1e-5, worst  # shared shapes: one encoding and a gathered gradient against one per slot


def test_a_batch_padded_to_more_objects_has_the_same_training_loss_and_gradients():
    """The compiled step pads each batch to a bucket of object counts (``model.compile_bucket``): padding objects
    are masked everywhere — graph attention, the perceiver, the nearest-other-object search, every loss term — so the
    loss and its gradients are those of the unpadded batch (the same noise and timesteps for the real objects; no
    dropout, whose masks are drawn per slot; the zero-initialised layers made live, or ε̂ ≡ 0 would hide any leak)."""
    from spread.data.collate import pad_objects
    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_model import synthetic_batch

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", ModelConfig(num_points=32, nearest="dense", dim=32, depth=1, num_latents=8,
                                                   heads=2, dropout=0.0), bounds=BOUNDS, penetration_weight=0.5).train()
    with torch.no_grad():
        for p in model.network.parameters():
            if not p.any():
                p.normal_(0.0, 0.02)
    batch = synthetic_batch(3, 5, 32)
    batch["mask"][2, 3:] = False
    batch["extents"] = batch["points"].amax(2) - batch["points"].amin(2)  # the penetration term's boxes, metres
    noise, timesteps = torch.randn(3, 5, 9), torch.tensor([100, 700, 400])

    def loss_and_grads(b, eps):
        model.zero_grad(set_to_none=True)
        loss = model.training_loss(b, noise=eps, timesteps=timesteps)
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.network.parameters() if p.grad is not None]

    loss, grads = loss_and_grads(batch, noise)
    padded = pad_objects(batch, 8)
    assert padded["mask"].shape == (3, 8) and padded["mask"].sum() == batch["mask"].sum()
    loss8, grads8 = loss_and_grads(padded, torch.cat([noise, torch.randn(3, 3, 9)], 1))  # any noise on the padding
    assert torch.allclose(loss8, loss, rtol=1e-6, atol=1e-7), (loss8, loss)
    assert len(grads8) == len(grads) > 0
    scale = max(float(b.abs().max()) for b in grads)  # against the largest gradient: some are ~0 (softmax shifts)
    worst = max(float((a - b).abs().max()) for a, b in zip(grads8, grads))
    assert worst < 1e-6 * scale, (worst, scale)


def test_the_compile_setting_compiles_the_step_once_per_bucket_in_its_mode_and_marks_every_cuda_graph_step(monkeypatch):
    """``model.compile=true model.compile_mode=reduce-overhead`` (CUDA graphs on a GPU): the step's loss is compiled
    in that mode as one static graph (``dynamic=False``) per bucket of object counts — batches of 4 and 7 objects pad
    to ``compile_bucket=8`` and share one graph, one of 9 pads to 16 and makes a second — each step is marked as a new
    CUDA-graph step, and the loss handed on is not the graph's own buffer; an unknown mode or a bucket below 1 is
    refused by name, and so is compiling the pruned search (``auto`` compiles the dense one). Dynamo's ``eager``
    backend: ``fullgraph=True`` still fails on any graph break, and the test above compiles the training loss through
    aot_eager (its backward traced too)."""
    import dataclasses

    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_model import synthetic_batch

    real_compile, modes, marks, graphs = torch.compile, [], [], []

    def counting_backend(gm, example_inputs):  # called once per graph Dynamo compiles
        graphs.append(sorted({tuple(t.shape)[1] for t in example_inputs if isinstance(t, torch.Tensor) and t.dim() == 3
                              and t.shape[0] == 2}))
        return gm.forward

    monkeypatch.setattr(torch, "compile", lambda fn, mode=None, **kw: modes.append((mode, kw))
                        or real_compile(fn, backend=counting_backend, **kw))
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: marks.append(1))
    # auto: the pruned search on CPU eagerly, the dense one while compiling (fullgraph fails on the pruned blocks)
    config = ModelConfig(num_points=16, nearest="auto", dim=32, depth=1, num_latents=8, heads=2)
    torch.manual_seed(0)
    model = SceneDiffusion("geometry", config, bounds=BOUNDS, compile=True, compile_mode="reduce-overhead").train()
    batch = synthetic_batch(2, 4, 16)
    for _ in range(2):
        loss = model.training_step(batch, 0)
        loss.backward()
        assert torch.isfinite(loss) and loss.grad_fn is not None
    # one graph (a graph break would split the step into several CUDA graphs with host code between)
    assert modes == [("reduce-overhead", {"fullgraph": True, "dynamic": False})] and len(marks) == 2
    assert len(graphs) == 1 and 8 in graphs[0], graphs  # 4 objects padded to the bucket, 8
    model.training_step(synthetic_batch(2, 7, 16), 0).backward()  # the same bucket: no new graph
    assert len(graphs) == 1 and len(marks) == 3
    model.training_step(synthetic_batch(2, 9, 16), 0).backward()  # the next: a second, static graph
    assert len(graphs) == 2 and 16 in graphs[1] and 9 not in graphs[1], graphs
    assert model.hparams["compile_mode"] == "reduce-overhead"
    # the optimiser's step drops the graph-owned gradients once used (a teardown moving the model must not read them)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in model.network.parameters()]

    def closure():
        loss = model.training_step(batch, 0)
        loss.backward()
        return loss

    model.optimizer_step(0, 0, optimizer, closure)
    assert all(p.grad is None for p in model.parameters())
    assert any(not torch.equal(a, p) for a, p in zip(before, model.network.parameters()))  # it did step
    eager = SceneDiffusion("geometry", config, bounds=BOUNDS).train()
    eager.optimizer_step(0, 0, torch.optim.AdamW(eager.parameters(), lr=1e-3),
                         lambda: eager.training_step(batch, 0).backward())
    assert any(p.grad is not None for p in eager.parameters())  # other modes leave them to Lightning
    with pytest.raises(ValueError, match="compile_mode.*'fast'"):
        SceneDiffusion("geometry", config, bounds=BOUNDS, compile=True, compile_mode="fast")
    for search in ("pruned", "tree"):
        with pytest.raises(ValueError, match=f"model.compile=true cannot compile model.config.nearest={search}"):
            SceneDiffusion("geometry", dataclasses.replace(config, nearest=search), bounds=BOUNDS, compile=True)
    with pytest.raises(ValueError, match="model.compile=true cannot compile model.config.geometry_distance=parts"):
        SceneDiffusion("geometry", dataclasses.replace(config, geometry_distance="parts"), bounds=BOUNDS, compile=True)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match=f"compile_bucket must be an integer >= 1.*{bad!r}"):
            SceneDiffusion("geometry", config, bounds=BOUNDS, compile=True, compile_bucket=bad)
    for variant in ("geometry", "base"):  # refused when the model is made, not at its first training step
        with pytest.raises(ValueError, match="model.config.nearest: unknown search 'kd'"):
            SceneDiffusion(variant, dataclasses.replace(config, nearest="kd"), bounds=BOUNDS)


def test_the_training_noise_is_diffusers_add_noise_to_the_bit_from_a_buffer_that_moves_with_the_module():
    """x_t of the training step (the module's ᾱ buffer, no attribute assigned inside a CUDA-graph'd step) equals
    diffusers' ``DDPMScheduler.add_noise`` bit for bit, at every timestep and in float64 too; the buffer is the
    scheduler's ᾱ and stays out of the state dict (old checkpoints load)."""
    from spread.model import ModelConfig
    from spread.model.diffusion import training_scheduler
    from spread.model.module import SceneDiffusion

    model = SceneDiffusion("base", ModelConfig(num_points=16, dim=32, depth=1, heads=2), bounds=BOUNDS)
    reference = training_scheduler()
    assert torch.equal(model.alphas_cumprod, reference.alphas_cumprod)
    assert "alphas_cumprod" not in model.state_dict()
    g = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        x0 = torch.randn(1000, 3, 9, generator=g, dtype=dtype)
        noise = torch.randn(1000, 3, 9, generator=g, dtype=dtype)
        t = torch.arange(1000)
        assert torch.equal(model.add_noise(x0, noise, t), reference.add_noise(x0, noise, t))
    assert model.double().alphas_cumprod.dtype == torch.float64  # a buffer: moved and cast with the module


def test_the_search_simulation_is_exact_and_the_nearest_tile_first_pass_evaluates_fewer_tiles():
    """benchmarks/search_tiles.py replays the kernel's culling (it asserts the replayed search finds the exact
    nearest distances): the nearest-tile first pass is one tile against the stride pass's P/(16·64), its second pass
    never below the fewest any order could visit, and in all fewer tiles than the stride pass."""
    from helpers import load_script

    from spread.model.nearest_dense import pose_torch
    from spread.model.poses import denormalize_affine

    tiles = load_script("search_tiles")
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_gpu import synthetic_batch

    batch = synthetic_batch(2, 6, 256)
    world = pose_torch(batch["x"], *denormalize_affine(torch.tensor(BOUNDS)), batch["points"], batch["normals"])[0]
    stride, near = tiles.simulate(world, "stride"), tiles.simulate(world, "neartile")
    assert stride["first pass"] == 2 and near["first pass"] == 1  # 6 × 256 keys / (16 × 64) → 2 tiles
    for r in (stride, near):
        assert r["pass 2"] >= r["fewest pass 2"] - 1e-9
    assert near["total"] < stride["total"]


def test_point_tokens_are_padded_to_a_multiple_of_8_on_cuda_and_the_keys_values_are_each_layers_layernorm_and_projection():
    """On CUDA the point tokens carry zero channels up to a multiple of 8 (a bf16 product with an inner dimension of
    107 runs in a slow kernel, and so does the LayerNorm of 107-channel rows); on the CPU they are not padded (its
    fused LayerNorm is faster). Either way the perceiver's keys and values of every cross-attention are each layer's
    ``to_kv(LayerNorm(token))`` over the 107 real channels, with that layer's LayerNorm scale and shift (the padding
    meets zero weights). The padded path runs here on CPU tensors, asked for by its multiple."""
    import torch.nn.functional as F

    from spread.model.perceiver import GeometryPerceiver, point_token_dim, point_tokens, static_tokens, token_multiple

    assert token_multiple(torch.device("cuda")) == 8 and token_multiple(torch.device("cpu")) == 1
    torch.manual_seed(0)
    perceiver = GeometryPerceiver(dim=32, num_latents=8, depth=3, num_bands=6, index_dim=64)
    with torch.no_grad():  # layers that differ: a wrong fold or a shifted channel shows
        perceiver.context_scale.normal_(1.0, 0.3)
        perceiver.context_shift.normal_(0.0, 0.3)
    B, N, M = 2, 3, 50
    mask = torch.tensor([[True, True, True], [True, True, False]])
    points = (torch.rand(B, N, M, 3) - 0.5) * mask[..., None, None]
    distance = torch.randn(B, N, M) * 2.0  # metres, both signs
    C = point_token_dim(6, 64)
    plain = point_tokens(distance, perceiver.static(points, mask))  # the CPU's
    padded = point_tokens(distance, static_tokens(points, mask, 6, perceiver.max_frequency, 64, multiple=8))
    assert C == 107 and plain.shape == (B, N * M, 107) and padded.shape == (B, N * M, 112)
    assert torch.equal(padded[..., :C], plain) and torch.equal(padded[..., C:], torch.zeros(B, N * M, 112 - C))
    assert torch.equal(plain[..., 39], distance.reshape(B, -1))  # d after the 39 Fourier channels of xyz
    with torch.no_grad():
        for tokens in (plain, padded):
            for layer, kv in enumerate(perceiver.context(tokens).chunk(3, dim=-1)):
                normed = F.layer_norm(plain, (C,), perceiver.context_scale[layer], perceiver.context_shift[layer])
                expected = F.linear(normed, perceiver.context_kv[layer])
                assert torch.allclose(kv, expected, atol=1e-5, rtol=1e-5), float((kv - expected).abs().max())


class ShapesMade(TorchDispatchMode):
    """Records the shape of every tensor an operator returns inside it (``seen``)."""

    def __init__(self):
        super().__init__()
        self.seen = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        result = func(*args, **(kwargs or {}))
        if isinstance(result, torch.Tensor):
            self.seen.add(tuple(result.shape))
        return result


@pytest.mark.parametrize("multiple", [1, 8])
def test_the_perceivers_absorbed_cross_attention_is_the_formed_one_and_never_makes_the_keys_and_values(multiple):
    """The perceiver's two ways to its cross-attentions (``cross_mode``: absorbed on the CPU, formed on CUDA) are one
    function: in float64 the latents and every parameter's gradient agree, unpadded tokens (the CPU's) and padded
    (CUDA's), two heads, padding objects masked out; the absorbed way never makes the (B, N·M, depth·2·heads·dim_head)
    keys/values the formed one makes; an unknown way is refused by name."""
    from spread.model.perceiver import GeometryPerceiver, cross_mode, static_tokens

    assert cross_mode(torch.device("cpu")) == "absorbed" and cross_mode(torch.device("cuda")) == "formed"
    torch.manual_seed(0)
    perceiver = GeometryPerceiver(dim=32, num_latents=8, depth=3, cross_heads=2, cross_dim_head=8, heads=2,
                                  dim_head=8, num_bands=6, index_dim=64).double()
    with torch.no_grad():  # layers that differ: a wrong fold shows
        perceiver.context_scale.normal_(1.0, 0.3)
        perceiver.context_shift.normal_(0.0, 0.3)
    B, N, M = 2, 3, 40
    mask = torch.tensor([[True, True, True], [True, True, False]])
    points = ((torch.rand(B, N, M, 3) - 0.5) * mask[..., None, None]).double()
    distance = torch.randn(B, N, M, dtype=torch.float64)
    static = static_tokens(points, mask, 6, perceiver.max_frequency, 64, multiple=multiple)
    out, grads = {}, {}
    for mode in ("formed", "absorbed"):
        out[mode] = perceiver(distance, static, mode)
        grads[mode] = torch.autograd.grad(out[mode].square().sum(), list(perceiver.parameters()))
    assert torch.allclose(out["formed"], out["absorbed"], atol=1e-10, rtol=0)
    for name, a, b in zip([n for n, _ in perceiver.named_parameters()], grads["formed"], grads["absorbed"]):
        assert torch.allclose(a, b, atol=1e-9, rtol=0), name
    assert grads["absorbed"][[n for n, _ in perceiver.named_parameters()].index("context_shift")].abs().sum() > 0

    kv_shape = (N * M, 3 * 2 * 2 * 8)

    for mode, makes in (("formed", True), ("absorbed", False)):
        with torch.no_grad(), ShapesMade() as shapes:
            perceiver(distance, static, mode)
        assert (kv_shape in {shape[-2:] for shape in shapes.seen}) == makes, mode
    with pytest.raises(ValueError, match="mode must be one of .*'fused'"):
        perceiver(distance, static, "fused")


def test_the_benchmarks_oracle_samples_the_rooms_own_poses_and_its_jitter_moves_only_translations_by_centimetres():
    """bench_gpu.Oracle stands in for a trained network in the guided pipeline's trained-like rows: DDIM-2 and
    DDPM-20 through the one sampling loop end at the batch's own states (0 cm), and with 3 cm of jitter each real
    object's translation is off by that draw (per-axis spread ≈ 3 cm) while its rotation is unchanged; the network
    itself is never called."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_gpu import Oracle, model, synthetic_batch

    from spread.model import Sampler
    from spread.model.diffusion import denoise

    m = model("base", 64).eval()
    batch = synthetic_batch(4, 8, 64)
    batch["mask"][1, 5:] = False
    batch["x"] = batch["x"].clamp(-0.9, 0.9) * batch["mask"][..., None]
    calls = []
    m.network.register_forward_hook(lambda *a: calls.append(1))
    m.ema.module.register_forward_hook(lambda *a: calls.append(1))
    truth = m.decode(batch["x"], batch["mask"])
    for sampler in ("ddim-2", "ddpm-20"):
        x = denoise(Oracle(m, 0.0).denoising(batch), Sampler.from_config(sampler),
                    [torch.Generator().manual_seed(i) for i in range(4)])
        assert torch.allclose(x, batch["x"], atol=1e-4), sampler
    x = denoise(Oracle(m, 0.03).denoising(batch), Sampler.from_config("ddim-2"),
                [torch.Generator().manual_seed(i) for i in range(4)])
    jittered = m.decode(x, batch["mask"])
    real = batch["mask"].bool()
    shift = (jittered.translation - truth.translation)[real]
    assert 0.015 < shift.std().item() < 0.045 and shift.abs().max().item() < 0.2
    assert torch.allclose(jittered.rotation, truth.rotation, atol=1e-4)
    assert not calls


def test_the_shape_tokenizers_absorbed_cross_attention_is_the_formed_one_and_chosen_only_where_it_is_no_more_work():
    """The point-cloud tokenizer's cross-attention two ways (``shape_tokens.cross_mode``): in float64 the tokens and
    every parameter's gradient agree; the absorbed way never makes the (objects, points, 2·width) keys/values; it is
    chosen on the CPU for the tiny config's sizes (16 queries, width 64) and not for the paper's (256 queries, width
    128: 2.7× the arithmetic) nor on CUDA; an unknown way is refused by name."""
    from spread.configs import model_config
    from spread.model.shape_tokens import PointCloudTokenizer, cross_mode

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    tiny, paper = model_config("tiny"), model_config("paper")
    assert cross_mode(cpu, tiny.shape_tokens, tiny.tokenizer_width, tiny.tokenizer_heads) == "absorbed"
    assert cross_mode(cpu, paper.shape_tokens, paper.tokenizer_width, paper.tokenizer_heads) == "formed"
    assert cross_mode(cuda, tiny.shape_tokens, tiny.tokenizer_width, tiny.tokenizer_heads) == "formed"
    torch.manual_seed(0)
    tokenizer = PointCloudTokenizer(num_tokens=4, token_dim=8, width=16, heads=2, num_points=24).double()
    V, P = 5, 24
    points = torch.rand(V, P, 3, dtype=torch.float64) - 0.5
    normals = torch.nn.functional.normalize(torch.randn(V, P, 3, dtype=torch.float64), dim=-1)
    out, grads = {}, {}
    for mode in ("formed", "absorbed"):
        out[mode] = tokenizer.encode(points, normals, mode)
        grads[mode] = torch.autograd.grad(out[mode].square().sum(), list(tokenizer.parameters()))
    assert torch.allclose(out["formed"], out["absorbed"], atol=1e-12, rtol=0)
    for name, a, b in zip([n for n, _ in tokenizer.named_parameters()], grads["formed"], grads["absorbed"]):
        assert torch.allclose(a, b, atol=1e-11, rtol=0), name
    assert grads["absorbed"][[n for n, _ in tokenizer.named_parameters()].index("cross.to_kv.weight")].abs().sum() > 0

    for mode, makes in (("formed", True), ("absorbed", False)):
        with torch.no_grad(), ShapesMade() as shapes:
            tokenizer.encode(points, normals, mode)
        assert ((V, P, 2 * 16) in shapes.seen) == makes, mode
    with pytest.raises(ValueError, match="mode must be one of .*'fused'"):
        tokenizer.encode(points, normals, "fused")


def test_queries_only_attention_equals_sdpa_and_is_chosen_only_for_grad_free_contexts_on_the_cpu_within_its_budget(
        monkeypatch):
    """``layers.attend_queries_only`` (two products and a softmax) is ``F.scaled_dot_product_attention`` with the
    context as keys and values: in float64 the output and the queries' gradient agree, with a bool and an additive
    mask; ``queries_only`` picks it only on the CPU, in float32/64, with gradients on, for queries that need them over a
    context that does not, within ``QUERIES_ONLY_SCORES``."""
    import torch.nn.functional as F

    from spread.model import layers
    from spread.model.layers import attend_queries_only, key_bias, queries_only

    torch.manual_seed(0)
    B, Nq, Nk, C = 3, 5, 17, 6
    q = torch.randn(B, 1, Nq, C, dtype=torch.float64, requires_grad=True)
    c = torch.randn(B, 1, Nk, C, dtype=torch.float64)
    real = torch.rand(B, Nk) > 0.3
    real[:, 0] = True
    for mask in (real[:, None, None, :], key_bias(real).double(), None):
        expected = F.scaled_dot_product_attention(q, c, c, attn_mask=mask, scale=0.3)
        got = attend_queries_only(q, c, mask, 0.3)
        assert torch.allclose(got, expected, atol=1e-12, rtol=0)
        g_expected, = torch.autograd.grad(expected.square().sum(), q)
        g_got, = torch.autograd.grad(got.square().sum(), q)
        assert torch.allclose(g_got, g_expected, atol=1e-11, rtol=0)
    assert queries_only(q, c, None)
    assert not queries_only(q, c.clone().requires_grad_(), None)  # the context's gradient is wanted: flash
    assert not queries_only(q.detach(), c, None)
    assert not queries_only(q.detach().bfloat16().requires_grad_(), c.bfloat16(), None)  # bf16: flash's float32 sums
    with torch.no_grad():
        assert not queries_only(q, c, None)  # without gradients the flash kernel is faster
    monkeypatch.setattr(layers, "QUERIES_ONLY_SCORES", B * Nq * Nk - 1)
    assert not queries_only(q, c, None)


def test_graph_guidance_makes_each_steps_posed_geometry_once_and_samples_exactly_as_when_each_branch_makes_it(
        monkeypatch):
    """Classifier-free guidance on the graphs calls the network twice a step on the same states (the graph and the
    null graph); the geometry features read no graph, so within a step they are made once (``sharing_geometry``):
    DDIM-4 at graph_scale 2 makes the posed features 4 times, not 8, and its samples equal, bit for bit, those made
    when each branch makes its own. Nothing is kept between calls: the same states a second time are posed again;
    with geometry_scale 2 the blind features are made once for the whole run."""
    import spread.model.network as network_module
    from spread.configs import model_config
    from spread.model.module import SceneDiffusion
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_model import synthetic_batch

    torch.manual_seed(0)
    model = SceneDiffusion("geometry", model_config("tiny"), bounds=BOUNDS).eval()
    batch = synthetic_batch(2, 5, 64)
    calls = []
    original = network_module.SceneDenoiser._geometry_features

    def counted(self, x_t, cond, blind):
        calls.append(blind)
        return original(self, x_t, cond, blind)

    monkeypatch.setattr(network_module.SceneDenoiser, "_geometry_features", counted)
    shared = model.sample(batch, "ddim-4", generator=torch.Generator().manual_seed(0), graph_scale=2.0)
    assert calls.count(False) == 4
    eps_fn, _ = model.denoiser(batch, graph_scale=2.0, geometry_scale=2.0)
    calls.clear()
    with torch.no_grad():
        x, t = torch.randn(2, 5, 9), torch.full((2,), 500)
        eps_fn(x, t)
        eps_fn(x, t)
    assert calls == [False, True, False]  # posed once a call, blind once for the run
    calls.clear()
    monkeypatch.setattr(network_module, "reusable", lambda: False)  # nothing reused: each branch makes its own
    separate = model.sample(batch, "ddim-4", generator=torch.Generator().manual_seed(0), graph_scale=2.0)
    assert calls.count(False) == 8
    assert torch.equal(shared.translation, separate.translation) and torch.equal(shared.rotation, separate.rotation)


def test_the_tile_size_benchmark_runs_every_choice_end_to_end(tmp_path):
    """``python benchmarks/search_blocks.py --json OUT`` as a GPU slot runs it, here on the CPU's torch path at its
    toy size: a row for every (BLOCK_Q, BLOCK_K, warps, keys) choice and both poses, each choice's boxes accepted for
    its tile size, the answers compared and saved. (The torch path ignores the tile sizes, so equal answers here say
    the script compares them; that the kernel's choices agree is the interpreter test's, and the script's own run
    under ``TRITON_INTERPRET=1``.)"""
    from helpers import load_script

    out = tmp_path / "blocks.json"
    script = os.path.join(os.path.dirname(__file__), "..", "benchmarks", "search_blocks.py")
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    done = subprocess.run([sys.executable, script, "--json", str(out)], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = {k: v for k, v in json.loads(out.read_text()).items() if k.startswith("search/")}
    assert len(rows) == 2 * len(load_script("search_blocks").CHOICES)
    assert all(v["indices_differ"] == 0 and v["max_distance_diff"] == 0 for v in rows.values())
    assert "q16_k32_w4_apart" in " ".join(rows) and "| 16 | 32 | 4 | apart |" in done.stdout


@pytest.mark.parametrize("arch", [80, 90])
def test_the_kernels_compile_for_an_a100_and_an_h100_here_without_a_gpu(arch, tmp_path, monkeypatch):
    """Triton compiles the pose and search kernels for compute capability 8.0 (A100) and 9.0 (H100/H200) on this CPU
    machine, with the ptxas its wheel carries — what the interpreter cannot check (types of the machine code, the
    constexpr branches); the default search needs no spilled registers; the kept-apart variant at 16 × 32 compiles
    too."""
    triton = pytest.importorskip("triton")
    from pathlib import Path

    monkeypatch.setenv("TRITON_CACHE_DIR", str(tmp_path))  # compiled here, from scratch, and left in the test's folder
    if not (Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "ptxas").exists():
        pytest.skip("this Triton has no NVIDIA backend")
    from helpers import load_script
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    import spread.model.nearest_dense as nd

    blocks = load_script("search_blocks")
    default = blocks.compiled(blocks.CHOICES[0], arch)
    assert blocks.CHOICES[0] == (nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS)
    assert 0 < default["registers"] <= 255 and default["local"] == 0
    assert blocks.compiled((16, 32, 4, False), arch)["registers"] > 0
    pose = nd._triton_kernels()[1]
    signature = {**{name: "*fp32" for name in ("x_ptr", "off_ptr", "scale_ptr", "pts_ptr", "nrm_ptr", "world_ptr",
                                               "wnrm_ptr", "box_ptr")}, "M": "i32", "KT": "i32",
                 "BK": "constexpr", "EPS": "constexpr"}
    kernel = triton.compile(ASTSource(fn=pose, signature=signature, constexprs={"BK": nd.BLOCK_K, "EPS": nd.ROT_EPS}),
                            target=GPUTarget("cuda", arch, 32))
    assert len(kernel.asm["cubin"]) > 0
