"""Convex decomposition of real-style meshes: V-HACD (vhacdx) against CoACD, fidelity and time per asset.

    python benchmarks/bench_decomposition.py [--categories mug bowl chair ...] [--timeout 300] [--seed 0]

Meshes: variant 0 of each category of the procedural catalog (closed, concave: the boolean union of its
parts) and an *open* copy of it (its upward faces at the top removed: an open-topped shell, as public
asset sets ship cups and bins), plus the tests' hard meshes (tests/realdata.py): a table whose legs are
open shells pushed into its board (multi-body) and a single-layer open cup. Both methods run with the
platform's settings (:mod:`spread.assets.decompose`). Each (mesh, method) runs in its own process, killed
after ``--timeout`` seconds. Prints one table: faces, closed?, per method the number of parts, seconds and the Hausdorff
distance between the mesh and the parts' union (mm, and relative to the bbox diagonal).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np

DEFAULT_CATEGORIES = ["mug", "bowl", "chair", "bookcase", "basket", "desk"]


def meshes(categories, seed: int):
    import trimesh

    from spread.assets.assemble import union_mesh
    from spread.assets.catalog import make_spec

    out = []
    for cat in categories:
        mesh = union_mesh(make_spec(cat, 0, seed).parts)
        out.append((f"{cat}", mesh))
        top = mesh.bounds[1][1]
        drop = (mesh.face_normals[:, 1] > 0.9) & (mesh.triangles_center[:, 1] > top - 0.002)
        opened = trimesh.Trimesh(mesh.vertices, mesh.faces[~drop], process=False)
        opened.remove_unreferenced_vertices()
        out.append((f"{cat} (open)", opened))
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import realdata

    from spread.assets.mesh_files import clean_mesh

    bodies = [b for _, b in realdata.table_bodies()]
    table = clean_mesh(np.concatenate([b.vertices for b in bodies]),
                       np.concatenate([b.faces + sum(len(c.vertices) for c in bodies[:k]) for k, b in enumerate(bodies)]))
    out.append(("table, open legs (tests)", table.mesh))
    mug = realdata.open_mug()
    out.append(("cup, single layer (tests)", clean_mesh(mug.vertices, mug.faces).mesh))
    return out


def _run(args, queue) -> None:
    import trimesh

    from spread.assets.decompose import convex_decomposition, decomposition_fidelity

    vertices, faces, method = args
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    t0 = time.perf_counter()
    dec = convex_decomposition(mesh, method=method)
    seconds = time.perf_counter() - t0
    queue.put({"parts": len(dec.parts), "seconds": seconds, "fallback": dec.settings.get("fallback"),
               **decomposition_fidelity(mesh, dec.parts)})


def measure(mesh, method: str, timeout: float) -> dict | None:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_run, args=((np.asarray(mesh.vertices), np.asarray(mesh.faces), method), queue))
    proc.start()
    proc.join(timeout)
    if proc.is_alive():
        proc.kill()
        proc.join()
        return None
    return queue.get() if not queue.empty() else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--categories", nargs="+", default=DEFAULT_CATEGORIES)
    parser.add_argument("--timeout", type=float, default=300.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = []
    for name, mesh in meshes(args.categories, args.seed):
        row = {"mesh": name, "faces": len(mesh.faces), "closed": bool(mesh.is_watertight)}
        for method in ("vhacd", "coacd"):
            row[method] = measure(mesh, method, args.timeout)
        rows.append(row)
        print(f"done {name}", flush=True)

    def cell(r):
        if r is None:
            return f"> {args.timeout:.0f} s (killed) | – | –"
        note = " (failed: V-HACD fallback)" if r.get("fallback") else ""
        return f"{r['parts']}{note} | {r['seconds']:.1f} | {1000 * r['hausdorff']:.1f} ({r['relative']:.3f})"

    print("\n| mesh | faces | closed | V-HACD parts | s | Hausdorff mm (rel.) | CoACD parts | s | Hausdorff mm (rel.) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['mesh']} | {r['faces']} | {'yes' if r['closed'] else 'no'} | {cell(r['vhacd'])} | {cell(r['coacd'])} |")
    for method in ("vhacd", "coacd"):
        done = [r[method] for r in rows if r[method] is not None and not r[method].get("fallback")]
        if done:
            print(f"{method}: {len(done)}/{len(rows)} finished, median {np.median([d['seconds'] for d in done]):.1f} s, "
                  f"median Hausdorff {1000 * np.median([d['hausdorff'] for d in done]):.1f} mm, "
                  f"median relative {np.median([d['relative'] for d in done]):.3f}")


if __name__ == "__main__":
    main()
