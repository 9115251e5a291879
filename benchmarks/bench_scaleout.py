"""Scale-out of spread-sample and spread-evaluate: throughput with 1 and 2 Ray workers here, the parts of the
cost (Ray start, actor start, model load, per-batch and per-scene work, Ray call overhead), and a model of the
time on W workers fitted from those parts. Prints one table.

    python benchmarks/bench_scaleout.py [--data DATASET] [--ckpt CKPT] [--graphs 12] [--samples-per-graph 2]
        [--batch 4] [--steps 50] [--eval-scenes 12] [--stability-runs 10] [--out /tmp/bench_scaleout]

Without ``--data`` a 24-room dataset is generated (12 test graphs); without ``--ckpt`` the tiny geometry model
(``experiment=quick``) is trained for 20 steps (the cost per step does not depend on the weights much).
Every end-to-end run is a complete :func:`run_sampling` / :func:`run_evaluation` (``resume=false``, no
renders, no FID, no logger) on a private local Ray started for it with ``num_cpus`` = workers, timed from the
call to its return: Ray start-up, worker imports and model loads included. The parts are timed apart:

* Ray start / stop: ``ray.init(num_cpus=2)`` and ``ray.shutdown()`` with nothing running;
* actor start: one ``SampleWorker`` actor from ``.remote()`` to ready (process, imports, model load), then two
  at once; model load: a second ``SampleWorker`` built in this (warm) process;
* per batch: ``SampleWorker.sample`` in this process (no Ray), per scene = per batch / batch size;
* Ray call overhead: round trip of an actor method / a task that does nothing.

The model: ``T(W) = T_start(W) + ceil(B / W) * t_batch + B / W * t_call + T_driver`` for sampling (B batches),
``T(W) = T_start(W) + N * t_scene / W + tasks / W * t_call + T_driver`` for evaluation (N scenes), where
T_start is Ray start plus the slowest worker start and T_driver the rest (reading graphs, hashing the
checkpoint, writing manifests), taken from the 1-worker run and then used to predict the 2-worker run.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path


def dataset(out: Path, rooms: int) -> Path:
    """A generated dataset folder with half of ``rooms`` in its test split."""
    from spread.procgen.dataset import DatasetConfig, generate_dataset

    data = out / "data"
    if not (data / "manifest.json").exists():
        generate_dataset(data, DatasetConfig(rooms=rooms, seed=3, processes=2, renders=0, val_fraction=0.1,
                                             test_fraction=0.5), progress=False)
    return data


def checkpoint(out: Path, data: Path) -> Path:
    """The tiny geometry model trained for 20 steps (``experiment=quick``)."""
    from hydra import compose, initialize_config_dir

    from spread.configs import conf_dir
    from spread.training.fit import train

    run = out / "train"
    ckpt = run / "checkpoints" / "last.ckpt"
    if not ckpt.exists():
        with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
            cfg = compose("train", [f"out_dir={run}", "experiment=quick", f"data.root={data}", "logger=none",
                                    "trainer.max_time=null", "trainer.max_steps=20",
                                    "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
                                    "trainer.check_val_every_n_epoch=1000"])
        train(cfg, run)
    return ckpt


def sampling_config(args, data: Path, ckpt: Path, out: Path, workers: int):
    from spread.runtime.ray import RaySettings
    from spread.sampling import DataSplit, SamplingConfig

    return SamplingConfig(ckpt=str(ckpt), data=DataSplit(str(data)), out_dir=str(out), sampler=f"ddim-{args.steps}",
                          samples_per_graph=args.samples_per_graph, seed=0, batch_size=args.batch, workers=workers,
                          device="cpu", threads=1, resume=False, renders=0, progress=False,
                          ray=RaySettings(num_cpus=max(1, workers)))


def timed(fn, *a, **kw):
    t0 = time.perf_counter()
    value = fn(*a, **kw)
    return time.perf_counter() - t0, value


def sampling_parts(args, data: Path, ckpt: Path, scenes_dir: Path) -> dict:
    """Model load, per-batch cost (this process), Ray start/stop, actor start, call overhead."""
    import ray

    from spread.sampling import list_graphs, plan_batches
    from spread import readonce
    from spread.sampling.worker import SampleWorker

    cfg = sampling_config(args, data, ckpt, scenes_dir.parent, 1)
    graphs = list_graphs(data, "test")[:args.graphs]
    batches = plan_batches(graphs, args.samples_per_graph, args.batch, 0)
    SampleWorker(cfg, scenes_dir)  # imports, caches
    readonce.clear()  # the model load below reads the checkpoint again (a cold process would)
    load, worker = timed(SampleWorker, cfg, scenes_dir)
    worker.sample(batches[0])  # warm
    per_batch = [timed(worker.sample, b)[0] for b in batches[:3]]
    sizes = [len(b.items) for b in batches[:3]]
    parts = {"model_load": load, "batch": statistics.mean(per_batch), "scene": sum(per_batch) / sum(sizes),
             "batches": len(batches), "scenes": sum(len(b.items) for b in batches)}

    parts["ray_start"], _ = timed(ray.init, num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        actor = ray.remote(SampleWorker).options(num_cpus=1)
        t0 = time.perf_counter()
        a = actor.remote(cfg, scenes_dir)
        ray.get(a.__ray_ready__.remote())
        parts["actor_start_1"] = time.perf_counter() - t0
        calls = [timed(ray.get, a.__ray_ready__.remote())[0] for _ in range(30)]
        parts["call_actor"] = statistics.median(calls)

        @ray.remote(num_cpus=1)
        def noop():
            return None

        ray.get(noop.remote())
        parts["call_task"] = statistics.median(timed(ray.get, noop.remote())[0] for _ in range(30))
        ray.kill(a)
        t0 = time.perf_counter()
        two = [actor.remote(cfg, scenes_dir) for _ in range(2)]
        ray.get([x.__ray_ready__.remote() for x in two])
        parts["actor_start_2"] = time.perf_counter() - t0
        for x in two:
            ray.kill(x)
    finally:
        parts["ray_stop"], _ = timed(ray.shutdown)
    return parts


def evaluation_config(scenes: Path, data: Path, out: Path, workers: int, stability_runs: int):
    from spread.evaluation import EvalProtocol, EvaluationConfig, FIDConfig
    from spread.runtime import RaySettings

    return EvaluationConfig(scenes=str(scenes), reference=str(data), out_dir=str(out), resume=False, renders=0,
                            progress=False, chunk_size=2, protocol=EvalProtocol(stability_runs=stability_runs),
                            fid=FIDConfig(enabled=False), ray=RaySettings(num_cpus=workers))


def fmt(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=None, help="dataset folder (default: generate 24 rooms)")
    ap.add_argument("--ckpt", type=Path, default=None, help="checkpoint (default: train the tiny model 20 steps)")
    ap.add_argument("--graphs", type=int, default=12, help="test graphs sampled")
    ap.add_argument("--samples-per-graph", type=int, default=2)
    ap.add_argument("--batch", type=int, default=4, help="samples per batch (= per Ray call)")
    ap.add_argument("--steps", type=int, default=50, help="DDIM steps")
    ap.add_argument("--eval-scenes", type=int, default=12, help="generated scenes evaluated")
    ap.add_argument("--stability-runs", type=int, default=10)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_scaleout")
    args = ap.parse_args()
    os.environ.setdefault("WANDB_MODE", "disabled")

    import torch

    from spread.evaluation import run_evaluation
    from spread.io import read_jsonl
    from spread.sampling import run_sampling
    from spread.scene import list_scene_files

    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    data = args.data or dataset(args.out, 24)
    ckpt = args.ckpt or checkpoint(args.out, data)
    # a split of exactly --graphs test graphs, so that every run samples the same graphs
    sub = args.out / "graphs"
    shutil.rmtree(sub, ignore_errors=True)
    (sub / "test").mkdir(parents=True)
    for f in list_scene_files(data / "test")[:args.graphs]:
        shutil.copy(f, sub / "test" / f.name)
    for name in ("assets", "stats.json"):
        (sub / name).symlink_to((data / name).resolve())

    from spread.sampling import list_graphs

    graphs = len(list_graphs(sub, "test"))
    load_before = os.getloadavg()[0]
    parts = sampling_parts(args, sub, ckpt, args.out / "parts" / "scenes")
    sample_wall, sample_manifest = {}, {}
    for w in (1, 2):
        out = args.out / f"sample_w{w}"
        sample_wall[w], result = timed(run_sampling, sampling_config(args, sub, ckpt, out, w))
        sample_manifest[w] = result.manifest
    scenes = args.out / "eval_scenes"
    shutil.rmtree(scenes, ignore_errors=True)
    scenes.mkdir()
    for f in list_scene_files(args.out / "sample_w2" / "scenes")[:args.eval_scenes]:
        shutil.copy(f, scenes / f.name)
    eval_wall, eval_records = {}, {}
    for w in (1, 2):
        out = args.out / f"eval_w{w}"
        eval_wall[w], result = timed(run_evaluation, evaluation_config(scenes, data, out, w, args.stability_runs))
        eval_records[w] = [r for r in read_jsonl(out / "per_scene.jsonl") if not r.get("error")]
    load_after = os.getloadavg()[0]

    # ---- the model ------------------------------------------------------------------------------------
    B, S = parts["batches"], parts["scenes"]
    N = len(eval_records[1])
    t_scene_eval = statistics.mean(sum(r["seconds"].values()) for r in eval_records[1])
    eval_tasks = math.ceil(N / 2)  # chunk_size=2

    def sample_start(w: int) -> float:
        return parts["ray_start"] + (parts["actor_start_1"] if w == 1 else parts["actor_start_2"])

    def sample_model(w: int, driver: float) -> float:
        return sample_start(w) + math.ceil(B / w) * parts["batch"] + B / w * parts["call_actor"] + driver

    def eval_model(w: int, driver: float) -> float:
        return parts["ray_start"] + N * t_scene_eval / w + eval_tasks / w * parts["call_task"] + driver

    sample_driver = sample_wall[1] - sample_model(1, 0.0)
    eval_driver = eval_wall[1] - eval_model(1, 0.0)

    print(f"# bench_scaleout  {time.strftime('%Y-%m-%d')}  {platform.machine()}  {os.cpu_count()} cores, torch "
          f"{torch.__version__}, 1 thread per worker; load avg {load_before:.1f} before, {load_after:.1f} after; "
          f"{graphs} graphs x {args.samples_per_graph} = {S} samples in {B} batches of <= {args.batch}, "
          f"ddim-{args.steps}, tiny geometry model; {N} generated scenes evaluated, "
          f"{args.stability_runs} Stability runs, chunks of 2, no FID")
    print("| quantity | 1 worker | 2 workers | 2 vs 1 |")
    print("|---|---|---|---|")
    s1, s2 = S / sample_wall[1], S / sample_wall[2]
    print(f"| sampling: wall s (scenes/min) | {fmt(sample_wall[1], 1)} ({fmt(60 * s1, 1)}) | "
          f"{fmt(sample_wall[2], 1)} ({fmt(60 * s2, 1)}) | {fmt(sample_wall[1] / sample_wall[2])}x |")
    print(f"| sampling: model, s (predicted for 2 from the 1-worker fit) | {fmt(sample_model(1, sample_driver), 1)} | "
          f"{fmt(sample_model(2, sample_driver), 1)} | |")
    print(f"| sampling: s per batch inside the workers (manifest) | {fmt(sample_manifest[1]['seconds_per_batch'])} | "
          f"{fmt(sample_manifest[2]['seconds_per_batch'])} | |")
    e1, e2 = N / eval_wall[1], N / eval_wall[2]
    print(f"| evaluation: wall s (scenes/min) | {fmt(eval_wall[1], 1)} ({fmt(60 * e1, 1)}) | "
          f"{fmt(eval_wall[2], 1)} ({fmt(60 * e2, 1)}) | {fmt(eval_wall[1] / eval_wall[2])}x |")
    print(f"| evaluation: model, s (predicted for 2 from the 1-worker fit) | {fmt(eval_model(1, eval_driver), 1)} | "
          f"{fmt(eval_model(2, eval_driver), 1)} | |")
    e2_scene = statistics.mean(sum(r["seconds"].values()) for r in eval_records[2])
    print(f"| evaluation: s per scene inside the workers | {fmt(t_scene_eval)} | {fmt(e2_scene)} | |")
    # busy worker-seconds / (wall - start-up): how many cores the workers really had (~W on an idle machine)
    busy_s = {w: sample_manifest[w]["seconds_per_batch"] * sample_manifest[w]["batches_run"] for w in (1, 2)}
    busy_e = {w: sum(sum(r["seconds"].values()) for r in eval_records[w]) for w in (1, 2)}
    par_s = {w: busy_s[w] / max(1e-9, sample_wall[w] - sample_start(w)) for w in (1, 2)}
    par_e = {w: busy_e[w] / max(1e-9, eval_wall[w] - parts["ray_start"]) for w in (1, 2)}
    print(f"| cores busy after start-up: sampling / evaluation (worker-s / wall-s) | {fmt(par_s[1])} / "
          f"{fmt(par_e[1])} | {fmt(par_s[2])} / {fmt(par_e[2])} | |")
    print(f"| slow-down of the work itself, 2 workers vs 1 (contention for cores) | | "
          f"{fmt(sample_manifest[2]['seconds_per_batch'] / sample_manifest[1]['seconds_per_batch'])}x / "
          f"{fmt(e2_scene / t_scene_eval)}x | |")
    print("| **parts** | | | |")
    print(f"| Ray start (ray.init, 2 CPUs) / stop, s | {fmt(parts['ray_start'])} / {fmt(parts['ray_stop'])} | | |")
    print(f"| sampling actor start: process + imports + model load, s | {fmt(parts['actor_start_1'])} | "
          f"{fmt(parts['actor_start_2'])} (both) | |")
    print(f"| model load in a warm process, s | {fmt(parts['model_load'], 3)} | | |")
    print(f"| sampling: s per batch of {args.batch} / per scene (this process, no Ray) | "
          f"{fmt(parts['batch'], 3)} / {fmt(parts['scene'], 3)} | | |")
    print(f"| evaluation: s per scene (worker timings, all metrics but FID) | {fmt(t_scene_eval, 3)} | | |")
    print(f"| Ray call round trip: actor method / task, ms | {fmt(1000 * parts['call_actor'], 1)} / "
          f"{fmt(1000 * parts['call_task'], 1)} | | |")
    print(f"| driver rest (fit residual): sampling / evaluation, s | {fmt(sample_driver, 1)} / {fmt(eval_driver, 1)} "
          f"| | |")


if __name__ == "__main__":
    main()
