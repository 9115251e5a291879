"""Cost of the inside/outside test and distances for open meshes (spread.metrics.solid) against trimesh.

    python benchmarks/bench_solid.py [--queries 3000] [--repeats 3]

Meshes: icospheres of 1,280 / 20,480 / 81,920 faces with a cap cut off (open), queries uniform in the
bounding box. Columns: libigl's fast winding number (hierarchy built per call, as the metrics use it),
libigl's exact winding number, preparing a :class:`~spread.metrics.solid.SolidMesh` (face probes and
AABB tree, once per asset), its signed distance (distance + winding number), trimesh's closest point
(what the watertight path's signed distance spends its time in), all in milliseconds (best of repeats).
Also the largest |fast − exact| winding number.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def best(fn, repeats: int) -> tuple[float, object]:
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return 1000 * min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--queries", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    import igl
    import trimesh

    from spread.metrics.solid import solid_mesh

    print(f"\n| faces | fast winding ms | exact winding ms | max abs diff | SolidMesh build ms | "
          f"signed distance ms | trimesh closest point ms |  ({args.queries} queries)")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for sub in (3, 5, 6):
        sphere = trimesh.creation.icosphere(subdivisions=sub)
        keep = sphere.triangles_center[:, 1] < 0.8  # cut a cap off: an open bowl
        mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False)
        V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        Q = np.random.default_rng(0).uniform(-1.1, 1.1, (args.queries, 3))
        t_fast, w_fast = best(lambda: igl.fast_winding_number(V, F, Q), args.repeats)
        t_exact, w_exact = best(lambda: igl.winding_number(V, F, Q), args.repeats)
        t_build, solid = best(lambda: solid_mesh(mesh), args.repeats)
        t_sd, _ = best(lambda: solid.signed_distance(Q), args.repeats)
        t_tm, _ = best(lambda: trimesh.proximity.closest_point(mesh, Q), 1)
        print(f"| {len(F)} | {t_fast:.1f} | {t_exact:.1f} | {np.abs(w_fast - w_exact).max():.1e} | {t_build:.1f} | "
              f"{t_sd:.1f} | {t_tm:.0f} |")


if __name__ == "__main__":
    main()
