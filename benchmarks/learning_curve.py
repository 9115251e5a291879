"""Quality against compute: GRecall, Col_mesh, ASD (and Stability) of unguided and guided samples on held-out
test graphs, for every checkpoint of a training run, against optimiser steps, scenes seen and training time.

    # 1. train, keeping a checkpoint every K steps (spread-train's Hydra overrides after --)
    python benchmarks/learning_curve.py train RUN --data DIR --steps 3000 --every 250 -- experiment=cpu_hour
    # 2. score every checkpoint on the test graphs of another dataset (another generator seed)
    python benchmarks/learning_curve.py eval RUN --test DIR --graphs 100 [--sampler ddim-50]
           [--guided 3000 last | --guided all] [--guidance guidance.gravity=4e-3 ...]
           [--stability-runs 10 --stability-at last] [--graph-scale 2]
    # 3. one table (95% bootstrap intervals over scenes) and one plot for one or more runs
    python benchmarks/learning_curve.py report LABEL=RUN ... [--png FILE] [--targets] [--wandb DIR]
           [--paired-against LABEL [--paired-mode guided]]   # each run's last checkpoint minus LABEL's, per test graph

``train`` runs ``spread-train`` in this process (one torch thread unless ``threads=`` says otherwise) with
``trainer.max_steps``, a checkpoint every ``--every`` steps (all kept) and the run's ``clock.jsonl``
(:mod:`spread.training.clock`: steps, scenes seen and training seconds — validation excluded — of each
checkpoint). ``eval`` samples one scene per test graph with the checkpoint's EMA weights (one seeded noise
generator per graph, so every checkpoint sees the same x_T), then — for the checkpoints named by ``--guided`` —
refines those same unguided states with the guidance config of ``--guidance`` (default ``guidance=refine`` with
the run's own ``sampling.guidance`` overrides when its config has them), and scores each scene with the
evaluation's per-scene functions (DESIGN §6): GRecall, Col_mesh, ASD and, with ``--stability-runs R``, Stability
over R physics runs at the checkpoints named by ``--stability-at`` (default: every evaluated one; the protocol's
10 runs is ``--stability-runs 10``). Per-scene records go to ``RUN/curve/<step>_<mode>.jsonl`` with each scene's
sampling seconds (a rerun skips what exists, unless Stability is now asked for and the file lacks it).
Every checkpoint is sampled with the same noise: its graph ``i`` draws x_T from seed ``seed · 1000003 + i``.
``--split val`` samples a dataset's val graphs instead (to choose guidance weights away from the test graphs).
Metrics pool over scenes as ``spread-evaluate`` does (ratios of sums); the intervals resample scenes with
replacement (2,000 resamples, seed 0). ``report --wandb DIR`` also logs each curve as a wandb run.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path

import numpy as np

def _metrics():
    """(key, label, display scale, digits) of the default metrics: the registry's display (ASD in mm)."""
    from spread.reporting.tables import metric_columns

    return tuple((c.key, c.label + c.arrow, c.scale, c.digits) for c in metric_columns(with_set=False))


METRICS = _metrics()


# ---- train -------------------------------------------------------------------------------------------

def cmd_train(args) -> None:
    from spread.configs import compose
    from spread.training.fit import train

    out = Path(args.run)
    overrides = [f"data.root={args.data}", f"out_dir={out}", f"trainer.max_steps={args.steps}",
                 "trainer.max_time=null", f"checkpoint.every_n_train_steps={args.every}", "checkpoint.save_top_k=-1",
                 "logger=csv", "trainer.enable_progress_bar=false", *args.overrides]
    cfg = compose("train", overrides)
    out.mkdir(parents=True, exist_ok=True)
    (out / "overrides.json").write_text(json.dumps(overrides, indent=1))
    train(cfg, run_dir=out)


# ---- eval --------------------------------------------------------------------------------------------

def checkpoints(run: Path) -> dict[int, Path]:
    """step → checkpoint file of a run: ``checkpoints/step0001000.ckpt`` → 1000, and ``last.ckpt`` under the
    newest step of the run's ``clock.jsonl`` (the clock records every save; the final save is last.ckpt) when
    no step file has that step."""
    found = {int(m.group(1)): p for p in (run / "checkpoints").glob("step*.ckpt")
             if (m := re.fullmatch(r"step(\d+)", p.stem))}
    last = run / "checkpoints" / "last.ckpt"
    times = clock(run)
    if last.exists() and times:
        found.setdefault(max(times), last)
    return dict(sorted(found.items()))


def pick(spec: list[str], steps: list[int]) -> set[int]:
    """The checkpoint steps a ``--guided`` / ``--stability-at`` list names: ``all``, ``last`` (the newest) or
    step numbers (each must be a checkpoint of the run)."""
    chosen: set[int] = set()
    for item in spec:
        if item == "all":
            chosen.update(steps)
        elif item == "last":
            if steps:
                chosen.add(max(steps))
        elif not str(item).isdigit():
            raise ValueError(f"checkpoint '{item}': give a step number, 'last' or 'all'")
        elif int(item) not in steps:
            raise ValueError(f"checkpoint step {item}: the run has checkpoints at {sorted(steps)}")
        else:
            chosen.add(int(item))
    return chosen


def has_stability(path: Path) -> bool:
    """Whether a curve file exists and its records carry Stability."""
    if not path.exists():
        return False
    first = path.read_text().split("\n", 1)[0]
    return bool(first) and "stability_pairs" in json.loads(first)


def clock(run: Path) -> dict[int, dict]:
    """step → {scenes, seconds} from the run's clock.jsonl (the newest record of each step)."""
    records = {}
    path = run / "clock.jsonl"
    if path.exists():
        for line in path.read_text().splitlines():
            r = json.loads(line)
            records[int(r["step"])] = r
    return records


def run_guidance(run: Path, extra: list[str]):
    """The GuidanceConfig of ``guidance=refine`` plus the run's experiment ``sampling.guidance`` overrides
    (those that set guidance keys) and ``extra``."""
    from omegaconf import OmegaConf

    from spread.configs import compose, to_object

    overrides = []
    cfg_file = run / ".hydra" / "config.yaml"
    if cfg_file.exists():
        sampling = OmegaConf.load(cfg_file).get("sampling") or {}
        overrides = [o for o in (sampling.get("guidance") or []) if str(o).startswith("guidance.")]
    cfg = compose("sample", ["ckpt=x", "data.root=x", "out_dir=x", "guidance=refine", *overrides, *extra])
    return to_object(cfg).guidance, overrides + list(extra)


def sample_graphs(pipeline, sources: list, generators: list, guided: bool) -> tuple[dict, dict]:
    """One batch of test graphs ``sources`` (scenes) sampled by ``pipeline`` (one generator per graph) and, when
    ``guided``, the same sampler output refined by the pipeline's guidance callback (what sampling with
    ``guidance=refine`` does): ({mode: [scene with the sampled poses]}, {mode: seconds for the batch}); modes
    ``unguided`` and ``guided``."""
    import torch

    from spread.sampling.pipeline import repair_rotations

    batch = pipeline.encode(sources)
    s0 = time.perf_counter()
    x, mask = pipeline.sample_states(batch, generators)
    states, seconds = {"unguided": x}, {"unguided": time.perf_counter() - s0}
    if guided:
        s0 = time.perf_counter()
        (callback,) = pipeline.callbacks(batch, sources)
        eps_fn, _ = pipeline.model.denoiser(batch, pipeline.use_ema, pipeline.graph_scale)
        with torch.no_grad():
            states["guided"] = callback.after(x.clone(), eps_fn)
        seconds["guided"] = seconds["unguided"] + time.perf_counter() - s0
    scenes = {}
    for mode, st in states.items():
        poses = pipeline.model.decode(st, mask)
        scenes[mode] = []
        for b, src in enumerate(sources):
            k = src.num_objects
            R, _ = repair_rotations(poses.rotation[b, :k].numpy())
            scenes[mode].append(src.with_poses(poses.translation[b, :k].numpy(), R, scene_id=src.scene_id))
    return scenes, seconds


def score(scene, library, stability_runs: int) -> dict:
    from spread.metrics import scene_collisions, scene_graph_recall, scene_stability, scene_support_distance

    g = scene_graph_recall(scene, library)
    c = scene_collisions(scene, library)
    d = scene_support_distance(scene, library)
    record = {"scene_id": scene.scene_id, "objects": scene.num_objects, "grecall_matches": int(g.matches),
              "grecall_pairs": int(g.pairs), "colliding": int(np.sum(c.colliding)),
              "asd_abs": [abs(float(p.min_signed_distance)) for p in d.pairs]}
    if stability_runs > 0:
        s = scene_stability(scene, library, runs=stability_runs)
        record.update(stability_unchanged=int(sum(s.unchanged)), stability_pairs=int(s.pairs * s.runs),
                      still=int(sum(s.still)), still_of=int(s.num_objects * s.runs))
    return record


def cmd_eval(args) -> None:
    import torch

    from spread.io import write_text_atomic
    from spread.sampling.run import DataSplit, SamplingConfig
    from spread.sampling.worker import load_pipeline

    torch.set_num_threads(args.threads)
    for run in map(Path, args.runs):
        steps = checkpoints(run)
        if args.steps:
            missing = set(args.steps) - set(steps)
            if missing:
                raise ValueError(f"{run}: no checkpoint at steps {sorted(missing)} (have {sorted(steps)})")
            steps = {s: p for s, p in steps.items() if s in set(args.steps)}
        guidance, guidance_overrides = run_guidance(run, args.guidance)
        guided_steps = pick(args.guided, list(steps))
        stability_steps = pick(args.stability_at or ["all"], list(steps)) if args.stability_runs > 0 else set()
        out = run / "curve"
        out.mkdir(exist_ok=True)
        tag = "" if args.graph_scale == 1.0 else f"-cfg{args.graph_scale:g}"  # a mode of its own in the report
        (out / "settings.json").write_text(json.dumps({
            "test": str(args.test), "split": args.split, "graphs": args.graphs, "sampler": args.sampler,
            "seed": args.seed, "graph_scale": args.graph_scale,
            "stability_runs": args.stability_runs, "guidance": guidance.to_dict(),
            "guidance_overrides": guidance_overrides}, indent=1))
        for step, ckpt in steps.items():
            modes = ["unguided"] + (["guided"] if step in guided_steps else [])
            stability = args.stability_runs if step in stability_steps else 0
            simulated = {m: stability if m in args.stability_modes else 0 for m in modes}
            todo = [m for m in modes if not (out / f"{step:07d}_{m}{tag}.jsonl").exists()
                    or (simulated[m] and not has_stability(out / f"{step:07d}_{m}{tag}.jsonl"))]
            if not todo:
                continue
            t0 = time.perf_counter()
            pipeline = load_pipeline(SamplingConfig(
                ckpt=str(ckpt), data=DataSplit(str(args.test), args.split), out_dir=str(out), sampler=args.sampler,
                device="cpu", guidance=guidance if "guided" in todo else None, graph_scale=args.graph_scale))
            data = pipeline.dataset
            n = min(args.graphs, len(data))
            if n < args.graphs:
                print(f"warning: {args.test} has {len(data)} {args.split} graphs, fewer than --graphs {args.graphs}")
            records = {m: [] for m in todo}
            for start in range(0, n, args.batch):
                idx = list(range(start, min(n, start + args.batch)))
                sources = [data.read(i) for i in idx]
                gens = [torch.Generator().manual_seed(args.seed * 1_000_003 + i) for i in idx]
                scenes, seconds = sample_graphs(pipeline, sources, gens, guided="guided" in todo)
                for mode in todo:
                    for scene in scenes[mode]:
                        record = score(scene, data.library, simulated[mode])
                        record["sample_seconds"] = round(seconds[mode] / len(idx), 4)
                        records[mode].append(record)
            for mode in todo:
                lines = "".join(json.dumps(r) + "\n" for r in records[mode])
                write_text_atomic(out / f"{step:07d}_{mode}{tag}.jsonl", lines)
                summary = pooled(records[mode])
                per_scene = sum(r["sample_seconds"] for r in records[mode]) / len(records[mode])
                print(f"{run.name} step {step} {mode}: " + ", ".join(f"{k} {v:.4f}" for k, v in summary.items())
                      + f" (sampling {per_scene:.2f} s/scene, total {time.perf_counter() - t0:.0f} s)", flush=True)


# ---- pooling and intervals ---------------------------------------------------------------------------

def sums(records: list[dict]) -> np.ndarray:
    """(scenes, 8) per-scene sums: matches, pairs, colliding, objects, Σ|d|, support pairs, unchanged, pairs."""
    rows = []
    for r in records:
        rows.append([r["grecall_matches"], r["grecall_pairs"], r["colliding"], r["objects"], sum(r["asd_abs"]),
                     len(r["asd_abs"]), r.get("stability_unchanged", 0), r.get("stability_pairs", 0)])
    return np.asarray(rows, np.float64)


def ratios(total: np.ndarray) -> dict:
    def ratio(a, b):
        return float(a / b) if b > 0 else float("nan")

    return {"grecall": ratio(total[..., 0], total[..., 1]), "col_mesh": ratio(total[..., 2], total[..., 3]),
            "asd": ratio(total[..., 4], total[..., 5]), "stability": ratio(total[..., 6], total[..., 7])}


def pooled(records: list[dict]) -> dict:
    return {k: v for k, v in ratios(sums(records).sum(0)).items() if not math.isnan(v)}


def bootstrap(records: list[dict], resamples: int = 2000, seed: int = 0) -> dict:
    """metric → (value, low, high): the pooled value and the 2.5 / 97.5 % percentiles over scene resamples."""
    table = sums(records)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(table), (resamples, len(table)))
    totals = table[picks].sum(1)  # (resamples, 8)
    out = {}
    point = ratios(table.sum(0))
    for i, key in enumerate(("grecall", "col_mesh", "asd", "stability")):
        num, den = totals[:, 2 * i], totals[:, 2 * i + 1]
        if table[:, 2 * i + 1].sum() == 0:
            continue
        values = num / np.where(den > 0, den, np.nan)
        out[key] = (point[key], float(np.nanpercentile(values, 2.5)), float(np.nanpercentile(values, 97.5)))
    return out


def paired_difference(records: list[dict], reference: list[dict], resamples: int = 2000, seed: int = 0) -> dict:
    """metric → (Δ, low, high) of ``records`` minus ``reference`` on the same test graphs (matched by scene id):
    both pooled over one resample of the graphs at a time, so the interval holds the per-graph noise that both
    runs share (same graph, same x_T) out of the difference. Only graphs scored in both count."""
    ref = {r["scene_id"]: r for r in reference}
    ids = [r["scene_id"] for r in records if r["scene_id"] in ref]
    if not ids:
        return {}
    mine = {r["scene_id"]: r for r in records}
    a, b = sums([mine[i] for i in ids]), sums([ref[i] for i in ids])
    picks = np.random.default_rng(seed).integers(0, len(ids), (resamples, len(ids)))
    ta, tb = a[picks].sum(1), b[picks].sum(1)  # (resamples, 8)
    pa, pb = ratios(a.sum(0)), ratios(b.sum(0))
    out = {}
    for i, key in enumerate(("grecall", "col_mesh", "asd", "stability")):
        if math.isnan(pa[key]) or math.isnan(pb[key]):
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            delta = ta[:, 2 * i] / ta[:, 2 * i + 1] - tb[:, 2 * i] / tb[:, 2 * i + 1]
        out[key] = (pa[key] - pb[key], float(np.nanpercentile(delta, 2.5)), float(np.nanpercentile(delta, 97.5)))
    return out


def curve_records(run: Path, step: int, mode: str = "unguided") -> list[dict]:
    path = run / "curve" / f"{step:07d}_{mode}.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line]


# ---- report ------------------------------------------------------------------------------------------

def load_run(run: Path) -> list[dict]:
    """One row per (checkpoint, mode): step, scenes, seconds, scenes scored, metrics with intervals."""
    times = clock(run)
    rows = []
    for path in sorted((run / "curve").glob("*_*.jsonl")):
        step_text, mode = path.stem.split("_", 1)
        records = [json.loads(line) for line in path.read_text().splitlines() if line]
        step = int(step_text)
        t = times.get(step, {})
        rows.append({"step": step, "mode": mode, "scenes_seen": t.get("scenes"), "seconds": t.get("seconds"),
                     "graphs": len(records), "metrics": bootstrap(records)})
    return rows


def cell(metric: tuple, scale: float, digits: int) -> str:
    value, low, high = (scale * v for v in metric)
    return f"{value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def cmd_report(args) -> None:
    runs = {}
    for item in args.runs:
        label, _, path = item.rpartition("=")
        runs[label or Path(path).name] = load_run(Path(path))
    have = [key for key, *_ in METRICS if any(key in r["metrics"] for rows in runs.values() for r in rows)]
    print("| run | mode | step | scenes seen | train min | graphs | " + " | ".join(
        label for key, label, *_ in METRICS if key in have) + " |")
    print("|---|---|---:|---:|---:|---:|" + "---|" * len(have))
    for label, rows in runs.items():
        for r in sorted(rows, key=lambda r: (r["mode"] != "unguided", r["step"])):
            minutes = "" if r["seconds"] is None else f"{r['seconds'] / 60:.1f}"
            cells = [cell(r["metrics"][k], s, d) if k in r["metrics"] else "" for k, _, s, d in METRICS if k in have]
            print(f"| {label} | {r['mode']} | {r['step']} | {r['scenes_seen'] or ''} | {minutes} | {r['graphs']} | "
                  + " | ".join(cells) + " |")
    if args.paired_against:
        paired_table(args, runs)
    if args.png:
        plot(runs, have, Path(args.png), args.targets)
    if args.wandb:
        log_wandb(runs, Path(args.wandb))


def paired_table(args, runs: dict) -> None:
    """Each run's last ``--paired-mode`` samples (unguided or guided) against the reference run's: paired
    differences."""
    paths = {(label or Path(path).name): Path(path) for label, _, path in (i.rpartition("=") for i in args.runs)}
    ref_label = args.paired_against
    if ref_label not in runs:
        raise SystemExit(f"--paired-against {ref_label!r} is not one of the runs ({', '.join(runs)})")

    kind = args.paired_mode

    def last(label):
        steps = [r["step"] for r in runs[label] if r["mode"].startswith(kind)]
        if not steps:
            raise SystemExit(f"--paired-mode {kind}: run {label!r} has no {kind} samples")
        return max(steps)

    # the reference's plain samples of that kind, or, when it was only sampled with CFG, its one <kind>-cfgS mode
    ref_modes = sorted(r["mode"] for r in runs[ref_label] if r["step"] == last(ref_label)
                       and r["mode"].startswith(kind))
    ref_mode = kind if kind in ref_modes else ref_modes[0]
    reference = curve_records(paths[ref_label], last(ref_label), ref_mode)
    print(f"\nPaired differences against {ref_label} (step {last(ref_label)}, {ref_mode}), same test graphs and x_T: "
          f"Δ [95 % paired bootstrap interval]")
    print("| run | step | scenes seen | train min | ΔGRecall ↑ | ΔCol_mesh ↓ | ΔASD mm ↓ |")
    print("|---|---:|---:|---:|---|---|---|")
    for label in runs:
        step = last(label)
        # the plain samples of that kind and those with classifier-free guidance on the graphs (<kind>-cfgS)
        for row in sorted((r for r in runs[label] if r["step"] == step and r["mode"].startswith(kind)),
                          key=lambda r: r["mode"]):
            if label == ref_label and row["mode"] == ref_mode:
                continue
            d = paired_difference(curve_records(paths[label], step, row["mode"]), reference)
            minutes = "" if row["seconds"] is None else f"{row['seconds'] / 60:.1f}"
            cells = [cell(d[k], s, dg) if k in d else "" for k, _, s, dg in METRICS if k != "stability"]
            name = label if row["mode"] == kind else f"{label} ({row['mode'].split('-', 1)[1]})"
            print(f"| {name} | {step} | {row['scenes_seen'] or ''} | {minutes} | " + " | ".join(cells) + " |")


def log_wandb(runs: dict, out_dir: Path) -> list[str]:
    """One wandb run per curve (``job_type=learning_curve``, group = its label; offline unless ``WANDB_MODE``
    says otherwise): per checkpoint ``<mode>/<metric>`` with ``_low`` / ``_high`` bounds, on the step axis
    ``curve/step``, with ``curve/scenes`` and ``curve/minutes``. Returns the runs' folders."""
    from spread.tracking.loggers import LoggerConfig, init_run, run_folder

    folders = []
    out_dir.mkdir(parents=True, exist_ok=True)
    for label, rows in runs.items():
        run = init_run(LoggerConfig(), "learning_curve", out_dir, {"label": label}, group=label, name=label)
        run.define_metric("curve/step")
        run.define_metric("*", step_metric="curve/step")
        for step in sorted({r["step"] for r in rows}):
            data = {"curve/step": step}
            for r in (r for r in rows if r["step"] == step):
                if r["scenes_seen"] is not None:
                    data["curve/scenes"] = r["scenes_seen"]
                if r["seconds"] is not None:
                    data["curve/minutes"] = r["seconds"] / 60
                for key, (value, low, high) in r["metrics"].items():
                    data.update({f"{r['mode']}/{key}": value, f"{r['mode']}/{key}_low": low,
                                 f"{r['mode']}/{key}_high": high})
            run.log(data)
        folders.append(run_folder(run))
        run.finish()
    return folders


def plot(runs: dict, have: list[str], png: Path, targets: bool) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes_x = (("step", "optimiser steps"), ("scenes_seen", "training scenes seen"), ("seconds", "training minutes"))
    target = {"grecall": (0.93, "unguided target"), "col_mesh": (0.12, "guided target"),
              "asd": (20.0, "guided target"), "stability": (0.95, "guided target")}
    fig, grid = plt.subplots(len(have), 3, figsize=(13, 2.8 * len(have)), squeeze=False, sharex="col")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row, key in enumerate(have):
        _, label, scale, _ = next(m for m in METRICS if m[0] == key)
        for col, (xkey, xlabel) in enumerate(axes_x):
            ax = grid[row][col]
            for c, (name, rows) in enumerate(runs.items()):
                modes = sorted({r["mode"] for r in rows}, key=lambda m: (m.startswith("guided"), m))
                for mode, style in ((m, "--s" if m.startswith("guided") else "-o") for m in modes):
                    pts = sorted((r[xkey] / (60 if xkey == "seconds" else 1), *(scale * v for v in r["metrics"][key]))
                                 for r in rows if r["mode"] == mode and key in r["metrics"] and r[xkey] is not None)
                    if not pts:
                        continue
                    x, y, lo, hi = map(np.asarray, zip(*pts))
                    colour = colours[c % len(colours)]
                    ax.plot(x, y, style, color=colour, ms=3, label=f"{name} {mode}")
                    ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="none", ecolor=colour, elinewidth=0.8, capsize=2)
                    ax.fill_between(x, lo, hi, color=colour, alpha=0.12)
            if targets and key in target:
                ax.axhline(target[key][0], color="k", lw=0.8, ls=":", label=target[key][1])
            if key == "asd":
                ax.set_yscale("log")
                ax.yaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
                ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            if row == len(have) - 1:
                ax.set_xlabel(xlabel)
            if xkey == "scenes_seen":
                ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v / 1000:g}k"))
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            if row == 0 and col == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)
    print(f"plot: {png}")


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("run")
    t.add_argument("--data", required=True)
    t.add_argument("--steps", type=int, required=True)
    t.add_argument("--every", type=int, default=250)
    e = sub.add_parser("eval")
    e.add_argument("runs", nargs="+")
    e.add_argument("--test", required=True, help="dataset whose test split holds the graphs")
    e.add_argument("--split", default="test", help="the split of --test whose graphs are sampled (val to tune)")
    e.add_argument("--graphs", type=int, default=100)
    e.add_argument("--sampler", default="ddim-50")
    e.add_argument("--batch", type=int, default=16)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--steps", type=int, nargs="*", help="only these checkpoints")
    e.add_argument("--guided", nargs="*", default=[], help="checkpoint steps to refine, 'last' or 'all'")
    e.add_argument("--guidance", nargs="*", default=[], help="guidance overrides (guidance.gravity=4e-3)")
    e.add_argument("--stability-runs", type=int, default=0, help="physics runs per scene (0: no Stability)")
    e.add_argument("--stability-at", nargs="*", default=[], help="checkpoint steps, 'last' or 'all' (default)")
    e.add_argument("--stability-modes", nargs="+", default=["unguided", "guided"], choices=["unguided", "guided"],
                   help="which samples Stability simulates (default both)")
    e.add_argument("--threads", type=int, default=1)
    e.add_argument("--graph-scale", type=float, default=1.0,
                   help="classifier-free guidance on the graphs (models trained with model.graph_dropout > 0); "
                        "curve files get the mode suffix -cfgS")
    r = sub.add_parser("report")
    r.add_argument("runs", nargs="+", help="LABEL=RUN folders")
    r.add_argument("--png")
    r.add_argument("--targets", action="store_true", help="draw the cpu_hour targets")
    r.add_argument("--wandb", help="also log each curve to wandb, files under this folder")
    r.add_argument("--paired-against", metavar="LABEL",
                   help="also tabulate every run's last checkpoint minus this run's, paired per test graph")
    r.add_argument("--paired-mode", choices=("unguided", "guided"), default="unguided",
                   help="which samples --paired-against compares (default unguided)")
    args = ap.parse_args(argv)
    args.overrides = extra
    {"train": cmd_train, "eval": cmd_eval, "report": cmd_report}[args.command](args)


if __name__ == "__main__":
    main()
