"""What the geometry features show the network while it samples, against what training shows it at the same t.

The +Geometry perceiver reads, at every denoising step, each object's signed nearest-other-object distances of
the state x_t it is given (:func:`spread.model.geometry.state_distances`). It learns what to do with them from
training states x_t = √ᾱ_t x_0 + √(1 − ᾱ_t) ε of collision-free rooms. This script puts the two side by side on
the same graphs: per real object (with a neighbour) its deepest penetration max(0, −min_p d(p)) in mm,

* ``sampling``: in the states the sampler hands the network (DDIM with the checkpoint's EMA weights and the graph
  scale), at each step's t;
* ``training``: in x_t drawn as in training from the graphs' own ground-truth rooms at the same t;

and a last row ``x_0``: the sampler's output against the ground-truth rooms themselves (the proxy is not 0 on
collision-free rooms: objects tucked under or into others read as penetrating by the nearest point's normal).

One table: t, then for each, the median and 90th percentile penetration (mm) and the share of objects deeper than
1 cm (Col_mesh's threshold). Where sampling's low-t states hold penetrations training never shows at that t, the
perceiver meets them out of its training distribution and has nothing learned to do with them.

Above the table, what the proxy reads on the ground-truth rooms themselves — the share of objects "penetrating"
> 1 cm — against their meshes' exact penetration (``--exact-graphs`` rooms: ``trimesh`` containment of each object's
samples in every other object's watertight mesh), and with ``--proxy-points`` the proxy at other M (the paper's
2,000), with ``--thickness`` the proxy with its sign gated by the neighbour's local thickness, with ``--parts`` the
signed distance to the other objects' convex parts (``model.config.geometry_distance=parts``) (``--no-sampling``: only
these lines). A checkpoint trained with ``geometry_distance=parts`` is measured with its own distance throughout.
``--picture PNG`` draws the first ground-truth room instead, red where the proxy reads a sample inside
another object. benchmarks/RESULTS.md, "Equal wall time, four tries at the perceiver, and what the geometry
features read".

    python benchmarks/exposure_gap.py RUN/checkpoints/last.ckpt DATA --graphs 48 --every 7 --exact-graphs 48 \
        --proxy-points 256,1000,2000
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def penetration_mm(cloud, x: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor) -> np.ndarray:
    """Per real object with a neighbour: max(0, −min over its points of d) in mm, of states x (B, N, 9)."""
    from spread.model.geometry import state_distances

    d = state_distances(cloud, x, offset, scale, "pruned")  # (B, N, M) metres
    deepest = (-d.amin(-1)).clamp(min=0) * 1000
    keep = cloud.has_other[..., 0]
    return deepest[keep].numpy()


def exact_penetration_mm(scene, library, M: int, seed: int) -> np.ndarray:
    """Per object of a room (with another object): the deepest its M surface samples lie inside any other object's
    mesh, mm (``trimesh`` containment and closest point on the watertight meshes): what the proxy should read."""
    import trimesh

    rng = np.random.default_rng(seed)
    meshes = [library.mesh(a) for a in scene.asset_id]
    world = []
    for k, aid in enumerate(scene.asset_id):
        points = library.geometry(aid).surface_points
        pick = rng.choice(len(points), size=min(M, len(points)), replace=False)
        world.append(points[pick] @ np.asarray(scene.rotation[k]).T + np.asarray(scene.translation[k]))
    deepest = []
    for i in range(len(meshes)):
        depth = 0.0
        for j, mesh in enumerate(meshes):
            if j == i:
                continue
            local = (world[i] - np.asarray(scene.translation[j])) @ np.asarray(scene.rotation[j])
            inside = mesh.contains(local)
            if inside.any():
                _, dist, _ = trimesh.proximity.closest_point(mesh, local[inside])
                depth = max(depth, float(dist.max()))
        deepest.append(depth * 1000)
    return np.asarray(deepest if len(meshes) > 1 else [])


def draw_proxy_room(data, index: int, offset, scale, path: Path) -> str:
    """One ground-truth room's surface samples from two sides, red where the proxy reads the point inside another
    object by > 1 cm (the meshes' exact test finds none in these rooms); returns the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from spread.data import collate_scenes
    from spread.model.geometry import prepare_points, state_distances
    from spread.model.poses import poses_from_state

    batch = collate_scenes([data[index]])
    cloud = prepare_points(batch["points"], batch["normals"], batch["mask"])
    d = state_distances(cloud, batch["x"], offset, scale, "pruned")[0]  # (N, M) metres
    t, R = poses_from_state(batch["x"], offset.new_tensor([*(offset - scale).tolist(), *(offset + scale).tolist()]))
    world = torch.einsum("nij,nmj->nmi", R[0], batch["points"][0]) + t[0, :, None]
    n = int(batch["mask"][0].sum())
    world, d = world[:n].reshape(-1, 3).numpy(), d[:n].reshape(-1).numpy()
    inside = d < -0.01
    scene = data.read(index)
    per_object = (d.reshape(n, -1) < -0.01).mean(1)
    title = (f"{scene.scene_id}: {inside.mean():.0%} of the samples read > 1 cm inside another object "
             f"(red; {int((per_object > 0).sum())} of {n} objects), collision-free by the meshes")
    fig = plt.figure(figsize=(13, 5.5))
    centres = world.reshape(n, -1, 3).mean(1)
    names = [a.rsplit("_", 1)[0] for a in scene.asset_id]
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.scatter(world[~inside, 0], world[~inside, 2], world[~inside, 1], s=1.5, c="#9aa7b8", alpha=0.5)
    ax.scatter(world[inside, 0], world[inside, 2], world[inside, 1], s=4, c="#d62728")
    for c, name in zip(centres, names):
        ax.text(c[0], c[2], c[1] + 0.15, name, fontsize=7)
    ax.set_xlabel("x (m)"), ax.set_ylabel("z (m)"), ax.set_zlabel("y, up (m)")
    ax.view_init(elev=25, azim=-60)
    ax.set_box_aspect(np.ptp(world[:, [0, 2, 1]], axis=0))
    top = fig.add_subplot(1, 2, 2)  # from above
    top.scatter(world[~inside, 0], world[~inside, 2], s=1.5, c="#9aa7b8", alpha=0.5, label="read outside")
    top.scatter(world[inside, 0], world[inside, 2], s=4, c="#d62728", label="read > 1 cm inside another object")
    for c, name in zip(centres, names):
        top.annotate(name, (c[0], c[2]), fontsize=7, xytext=(4, 4), textcoords="offset points")
    top.set_aspect("equal"), top.set_xlabel("x (m)"), top.set_ylabel("z (m)"), top.set_title("from above", fontsize=9)
    top.legend(loc="upper right", fontsize=7, markerscale=3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return title


def thickness_gated_mm(batch, library, scenes, offset, scale) -> tuple[np.ndarray, np.ndarray]:
    """Per object of ground-truth rooms: the deepest penetration (mm) the proxy reads as released, and as it would
    read with its sign gated by the neighbour's local thickness — p counts as inside q's object only if it lies behind
    q's normal plane by less than the solid's thickness behind q (a ray from q along −n_q to the far surface), so a
    board's far face or a point a metre away no longer reads as inside. A measurement for a better feature, not the
    model's: the nearest other-object sample by brute force (exact, as the model's search)."""
    import trimesh

    from spread.model.poses import poses_from_state

    bounds = torch.cat([offset - scale, offset + scale])
    t, R = poses_from_state(batch["x"], bounds)
    released, gated = [], []
    for b, scene in enumerate(scenes):
        n = len(scene.asset_id)
        local, normals = batch["points"][b, :n].double().numpy(), batch["normals"][b, :n].double().numpy()
        thickness = np.zeros(local.shape[:2])
        for j, aid in enumerate(scene.asset_id):
            mesh = library.mesh(aid)
            hits, rays, _ = mesh.ray.intersects_location(local[j] - 1e-4 * normals[j], -normals[j],
                                                         multiple_hits=False)
            thickness[j, rays] = np.linalg.norm(hits - (local[j][rays] - 1e-4 * normals[j][rays]), axis=1)
        Rb, tb = R[b, :n].double().numpy(), t[b, :n].double().numpy()
        world = np.einsum("nij,nmj->nmi", Rb, local) + tb[:, None]
        wnorm = np.einsum("nij,nmj->nmi", Rb, normals)
        flat, nflat, tflat = world.reshape(-1, 3), wnorm.reshape(-1, 3), thickness.reshape(-1)
        owner = np.repeat(np.arange(n), local.shape[1])
        dist = torch.cdist(torch.from_numpy(flat), torch.from_numpy(flat)).numpy()
        dist[owner[:, None] == owner[None]] = np.inf
        q = dist.argmin(1)
        depth = -((flat - flat[q]) * nflat[q]).sum(-1)  # > 0: behind q's normal plane
        near = np.linalg.norm(flat - flat[q], axis=1)
        read = np.where(depth > 0, near, 0.0)  # the released proxy's penetration (|d| where the sign is −)
        inside = (depth > 0) & (depth < tflat[q])
        released.append(read.reshape(n, -1).max(1) * 1000)
        gated.append(np.where(inside, near, 0.0).reshape(n, -1).max(1) * 1000)
    keep = [len(s.asset_id) > 1 for s in scenes]
    return (np.concatenate([r for r, k in zip(released, keep) if k]),
            np.concatenate([g for g, k in zip(gated, keep) if k]))


def main() -> None:
    from spread.data import SceneDataset, collate_scenes
    from spread.model.diffusion import Sampler, denoise
    from spread.model.geometry import batch_cloud, prepare_points
    from spread.model.module import SceneDiffusion
    from spread.model.poses import denormalize_affine
    from spread.safe_load import load_checkpoint

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpt", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--split", default="test")
    ap.add_argument("--graphs", type=int, default=48)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--sampler", default="ddim-50")
    ap.add_argument("--graph-scale", type=float, default=2.0)
    ap.add_argument("--every", type=int, default=5, help="report every k-th sampling step (and the last)")
    ap.add_argument("--picture", type=Path, default=None,
                    help="draw the first ground-truth room with the points the proxy reads inside (PNG) and stop")
    ap.add_argument("--no-sampling", action="store_true", help="only the ground-truth rooms' lines (no sampling)")
    ap.add_argument("--thickness", action="store_true",
                    help="also the proxy with its sign gated by the neighbour's thickness on the ground-truth rooms")
    ap.add_argument("--proxy-points", default="",
                    help="also the proxy on the ground-truth rooms at these M (comma list, e.g. 256,2000: the paper's)")
    ap.add_argument("--parts", action="store_true",
                    help="also what the parts distance (geometry_distance=parts) reads on the ground-truth rooms")
    ap.add_argument("--exact-graphs", type=int, default=12,
                    help="ground-truth rooms whose exact mesh penetration is measured beside the proxy's (slow)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    model = SceneDiffusion.from_checkpoint(load_checkpoint(args.ckpt)).eval()
    offset, scale = denormalize_affine(model.bounds)
    alpha_bar = model.alphas_cumprod
    distance = getattr(model.network.config, "geometry_distance", "chamfer")  # what the model reads, measured here
    data = SceneDataset(args.dataset, args.split, num_points=model.network.config.num_points,
                        bounds=model.bounds.tolist(), geometry_distance="parts" if args.parts else distance)
    if args.picture is not None:
        print(draw_proxy_room(data, 0, offset, scale, args.picture))
        return
    sampler = Sampler.from_config(args.sampler)
    sampled: dict[int, list] = {}
    trained: dict[int, list] = {}
    for start in range(0, 0 if args.no_sampling else min(args.graphs, len(data)), args.batch):
        batch = collate_scenes([data[k] for k in range(start, min(start + args.batch, args.graphs, len(data)))])
        cloud = batch_cloud(batch, batch["mask"], parts=distance == "parts")
        problem = model.denoising(batch, graph_scale=args.graph_scale)
        eps_fn, seen = problem.eps_fn, []

        def recording(x_t, t, eps_fn=eps_fn, seen=seen):
            seen.append((int(t[0]), x_t.detach().clone()))
            return eps_fn(x_t, t)

        problem.eps_fn = recording
        generator = torch.Generator().manual_seed(start)
        with torch.no_grad():
            final = denoise(problem, sampler, generator)
            sampled.setdefault(-1, []).append(penetration_mm(cloud, final, offset, scale))
            trained.setdefault(-1, []).append(penetration_mm(cloud, batch["x"], offset, scale))
            for i, (t, x_t) in enumerate(seen):
                if i % args.every and i != len(seen) - 1:
                    continue
                sampled.setdefault(t, []).append(penetration_mm(cloud, x_t, offset, scale))
                a = alpha_bar[t]
                noise = torch.randn(batch["x"].shape, generator=generator)
                x_train = (a.sqrt() * batch["x"] + (1 - a).sqrt() * noise) * batch["mask"][..., None]
                trained.setdefault(t, []).append(penetration_mm(cloud, x_train, offset, scale))
        print(f"graphs {start + len(batch['mask'])} / {min(args.graphs, len(data))}", flush=True)

    proxy = np.concatenate(trained[-1]) if trained else None
    if args.exact_graphs and proxy is not None:
        exact = np.concatenate([exact_penetration_mm(data.read(k), data.library, model.network.config.num_points, k)
                                for k in range(min(args.exact_graphs, len(data)))])
        print(f"ground-truth rooms: the proxy reads {np.mean(proxy > 10):.3f} of the objects as penetrating > 1 cm "
              f"(median {np.median(proxy):.1f} mm); the meshes themselves, exactly ({min(args.exact_graphs, len(data))} "
              f"rooms, {len(exact)} objects): {np.mean(exact > 10):.3f} (median {np.median(exact):.1f} mm, max "
              f"{exact.max():.1f} mm)")
    if args.thickness:
        rooms = range(min(args.graphs, len(data)))
        pairs = [thickness_gated_mm(collate_scenes([data[k] for k in rooms[i:i + args.batch]]), data.library,
                                    [data.read(k) for k in rooms[i:i + args.batch]], offset, scale)
                 for i in range(0, len(rooms), args.batch)]
        released, gated = (np.concatenate([p[k] for p in pairs]) for k in (0, 1))
        print(f"ground-truth rooms, {len(released)} objects: the proxy as released reads {np.mean(released > 10):.3f} "
              f"as penetrating > 1 cm ({np.mean(released > 50):.3f} > 5 cm); with its sign gated by the neighbour's "
              f"thickness {np.mean(gated > 10):.3f} ({np.mean(gated > 50):.3f} > 5 cm)")
    if args.parts:
        rooms = range(min(args.graphs, len(data)))
        batches = (collate_scenes([data[k] for k in rooms[i:i + args.batch]]) for i in range(0, len(rooms), args.batch))
        reads = np.concatenate([penetration_mm(batch_cloud(batch, batch["mask"], parts=True), batch["x"], offset, scale)
                                for batch in batches])
        print(f"ground-truth rooms, {len(reads)} objects: the parts distance reads {np.mean(reads > 10):.3f} of them as "
              f"penetrating > 1 cm (median {np.median(reads):.1f} mm, max {reads.max():.1f} mm)")
    for m in [int(v) for v in args.proxy_points.split(",") if v]:
        dense = SceneDataset(args.dataset, args.split, num_points=m, bounds=model.bounds.tolist())
        reads = []
        for start in range(0, min(args.graphs, len(dense)), args.batch):
            batch = collate_scenes([dense[k] for k in range(start, min(start + args.batch, args.graphs, len(dense)))])
            reads.append(penetration_mm(prepare_points(batch["points"], batch["normals"], batch["mask"]), batch["x"],
                                        offset, scale))
        reads = np.concatenate(reads)
        print(f"ground-truth rooms, the proxy at M = {m}: {np.mean(reads > 10):.3f} of the objects read as penetrating "
              f"> 1 cm (median {np.median(reads):.1f} mm)")
    if sampled:
        print(f"\n{args.ckpt}: {min(args.graphs, len(data))} graphs of {args.dataset / args.split}, {args.sampler}, "
              f"graph scale {args.graph_scale}; deepest penetration per object (mm)")
        print(f"{'t':>5} | {'sampling median':>15} {'p90':>7} {'> 1 cm':>7} | {'training median':>15} {'p90':>7} "
              f"{'> 1 cm':>7}")
        for t in sorted(sampled, reverse=True):
            s, r = np.concatenate(sampled[t]), np.concatenate(trained[t])
            print(f"{t if t >= 0 else 'x_0':>5} | {np.median(s):>15.1f} {np.percentile(s, 90):>7.1f} "
                  f"{np.mean(s > 10):>7.3f} | {np.median(r):>15.1f} {np.percentile(r, 90):>7.1f} {np.mean(r > 10):>7.3f}")


if __name__ == "__main__":
    main()
