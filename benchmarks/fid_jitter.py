"""FID and KID against the jitter of ground-truth rooms: the metric must rank ground truth < 5 cm < 15 cm.

    python benchmarks/fid_jitter.py --out /tmp/fidjitter            # generates both datasets (~10 min)
    python benchmarks/fid_jitter.py --reference DIR --generated DIR  # two dataset folders you have

The reference set is the test split of one dataset (generator seed 0); the "generated" sets are the test
split of a second dataset (another generator seed: other rooms from the same distribution) as they are,
and with every object's translation jittered by N(0, σ²) per axis, σ = 5 cm and 15 cm
(``benchmarks/jitter_scenes.py``). FID and KID use the protocol's renders and the default Inception
features (:class:`spread.metrics.SceneFID`), overall and per room type (the ``room_type`` each generated
room carries). Features are computed once per scene and reused for every row. Prints one table.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from jitter_scenes import jitter_scene  # noqa: E402

SIGMAS = (0.0, 0.05, 0.15)


def generate(out: Path, seed: int, rooms: int) -> Path:
    """A dataset whose test split holds rooms // 2 rooms (nothing if it is there already)."""
    if not (out / "manifest.json").exists():
        script = Path(sys.executable).parent / "spread-generate"
        subprocess.run([str(script), f"out_dir={out}", f"rooms={rooms}", f"seed={seed}", "val_fraction=0.0",
                        "test_fraction=0.5", "renders=0", "progress=false"], check=True)
    return out


def features_of(scenes, library, extractor, batch: int = 16) -> np.ndarray:
    from spread.metrics import fid_render

    out = []
    for start in range(0, len(scenes), batch):
        out.append(extractor(np.stack([fid_render(s, library) for s in scenes[start:start + batch]])))
    return np.concatenate(out)


def distances(generated: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    from spread.metrics.feature_distances import frechet_distance, kernel_distance

    return frechet_distance(generated, reference), kernel_distance(generated, reference)


def main() -> None:
    import torch

    from spread.assets.library import AssetLibrary
    from spread.metrics.extractors import load_extractor
    from spread.scene import list_scene_files, read_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/fid_jitter"))
    ap.add_argument("--reference", type=Path, help="dataset folder (its test split is the reference)")
    ap.add_argument("--generated", type=Path, help="dataset folder (its test split is jittered)")
    ap.add_argument("--rooms", type=int, default=200, help="rooms per generated dataset (half go to test)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    reference_dir = args.reference or generate(args.out / "reference", 0, args.rooms)
    generated_dir = args.generated or generate(args.out / "generated", 1, args.rooms)
    loaded = load_extractor("inception_v3")
    if not loaded.available:
        raise SystemExit(loaded.status)
    library = AssetLibrary.load(reference_dir / "assets")
    started = time.perf_counter()
    reference = [read_scene(p) for p in list_scene_files(reference_dir / "test")]
    truth = [read_scene(p) for p in list_scene_files(generated_dir / "test")]
    ref_features = features_of(reference, library, loaded.extractor)
    ref_types = np.array([str(s.extras.get("room_type", "all")) for s in reference])
    rows = []
    for sigma in SIGMAS:
        scenes = [jitter_scene(s, sigma, np.random.default_rng([args.seed, k])) if sigma else s
                  for k, s in enumerate(truth)]
        feats = features_of(scenes, library, loaded.extractor)
        types = np.array([str(s.extras.get("room_type", "all")) for s in scenes])
        per_type = defaultdict(dict)
        for t in sorted(set(types) & set(ref_types)):
            if (types == t).sum() >= 2 and (ref_types == t).sum() >= 2:
                per_type[t] = distances(feats[types == t], ref_features[ref_types == t])
        rows.append((sigma, len(scenes), *distances(feats, ref_features), dict(per_type)))
    seconds = time.perf_counter() - started
    room_types = sorted({t for row in rows for t in row[4]})
    print(f"reference: {len(reference)} rooms of {reference_dir}/test; generated: {len(truth)} rooms of "
          f"{generated_dir}/test; Inception features ({loaded.status}); {seconds:.0f} s")
    header = "| jitter σ | rooms | FID ↓ | KID ↓ | " + " | ".join(f"{t} FID / KID" for t in room_types) + " |"
    print(header)
    print("|" + "---:|" * (4 + len(room_types)))
    for sigma, n, fid, kid, per_type in rows:
        cells = [f"{per_type[t][0]:.1f} / {per_type[t][1]:.4f}" if t in per_type else "–" for t in room_types]
        label = "ground truth" if sigma == 0 else f"{100 * sigma:.0f} cm"
        print(f"| {label} | {n} | {fid:.2f} | {kid:.4f} | " + " | ".join(cells) + " |")
    fids = [r[2] for r in rows]
    kids = [r[3] for r in rows]
    print(f"monotonic: FID {fids[0] < fids[1] < fids[2]}, KID {kids[0] < kids[1] < kids[2]}")
    for t in room_types:
        if all(t in r[4] for r in rows):
            f, k = [r[4][t][0] for r in rows], [r[4][t][1] for r in rows]
            print(f"  {t} ({(ref_types == t).sum()} reference rooms): FID monotonic {f[0] < f[1] < f[2]}, "
                  f"KID monotonic {k[0] < k[1] < k[2]}")


if __name__ == "__main__":
    main()
