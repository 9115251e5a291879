"""One evaluation run (``spread-evaluate``): scene files → ``per_scene.jsonl``, ``metrics.json``, renders.

1. List the scene files of ``scenes`` and the reference split ``reference/<split>``; the asset library
   is ``reference/assets``.
2. Resume: read ``out_dir/per_scene.jsonl`` (deduplicated, compacted; :mod:`~spread.evaluation.resume`)
   and schedule only the scenes without a line. ``out_dir/protocol.json`` pins what the lines were measured
   with (the protocol, FID settings, the asset library's index, the numbers' code version); a re-launch with
   another one redoes the folder from scratch and records why in ``metrics.json``
   (``redone_because: "changed: <keys>"``): mixed lines are never summed, old numbers never reported as new.
3. Fan the rest out as Ray tasks (:func:`~spread.evaluation.fanout.fan_out`); the driver appends each
   record as it arrives and advances the progress bar.
4. ``metrics.json`` (atomic) is computed from the file's deduplicated lines of this folder's scenes, so a
   resumed run reports exactly what a single run would; it keeps the sampling identity of the scenes it measured
   (``sampled_with``: :func:`sampled_with`); with each metric its 95 % bootstrap interval over
   scenes (``<metric>_lo`` / ``_hi``, ``bootstrap``: :mod:`~spread.evaluation.bootstrap`, seeded by the
   protocol's seed). FID reference statistics are computed by Ray tasks too when an extractor is available;
   otherwise FID is null with the reason.
5. A few top-down renders of evaluated scenes go to ``out_dir/renders/`` (none in the sampling run's own folder,
   whose renders show them already: :func:`sampling_folder`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from omegaconf import MISSING

from spread.evaluation.aggregate import fid_values, per_room_type_values, summary_values, usable
from spread.evaluation.bootstrap import RESAMPLES, bootstrap_intervals
from spread.evaluation.fanout import fan_out, run_tasks
from spread.evaluation.protocol import EvalProtocol, FIDConfig, versions
from spread.evaluation.resume import dedupe, load_finished
from spread.evaluation.work import (
    evaluate_chunk, failure_record, reference_fid_state, scene_key, worker_extractor, worker_library,
)
from spread.io import append_jsonl, check_folder_kind, read_json, read_jsonl, write_json_atomic
from spread.runtime.ray import RaySettings, ray_session

PER_SCENE = "per_scene.jsonl"
METRICS = "metrics.json"
PROTOCOL = "protocol.json"


@dataclass
class EvaluationConfig:
    """scenes: folder of scene files; reference: dataset folder (``assets/`` + ``reference_split/``);
    out_dir: run folder; chunk_size: scenes per Ray task; resume: keep ``per_scene.jsonl`` lines;
    retry_failed: on resume, evaluate scenes whose line has an error again; renders: top-down PNGs of
    the first evaluated scenes; progress: tqdm bar; bootstrap_resamples: resamples of the confidence intervals
    (0: none); max_objects: largest scene evaluated (None: twice the reference dataset's largest, its
    ``stats.json``'s ``max_objects``, as sampling's default; 0: no limit) — a larger one is left out by name before
    any work (``scenes_over_limit`` in ``metrics.json``); protocol / fid: what is measured and how (DESIGN §6);
    ray: where. The ``spread-evaluate``
    config (``conf/evaluate.yaml``) is this record plus the command's logger (:mod:`spread.configs`)."""

    scenes: str = MISSING
    reference: str = MISSING
    out_dir: str = MISSING
    reference_split: str = "test"
    chunk_size: int = 4
    resume: bool = True
    retry_failed: bool = False
    renders: int = 8
    progress: bool = True
    bootstrap_resamples: int = RESAMPLES
    max_objects: int | None = None
    protocol: EvalProtocol = field(default_factory=EvalProtocol)
    fid: FIDConfig = field(default_factory=FIDConfig)
    ray: RaySettings = field(default_factory=RaySettings)

    def __post_init__(self) -> None:
        from spread.checks import whole_number

        for key in ("chunk_size", "renders", "bootstrap_resamples"):
            whole_number(getattr(self, key), key, 1 if key == "chunk_size" else 0)
        self.max_objects = whole_number(self.max_objects, "max_objects", 0, null="twice the reference's largest "
                                        "scene")


@dataclass
class EvaluationResult:
    """metrics: the ``metrics.json`` content; records: the deduplicated per-scene lines of this run's
    scenes; renders: PNG paths written; out_dir."""

    metrics: dict
    records: list[dict]
    renders: list[Path]
    out_dir: Path


def sampling_folder(out: Path, scenes) -> bool:
    """Whether ``out`` is the sampling run folder whose ``scenes/`` are evaluated (``spread-sample evaluate=true``,
    ``spread-evaluate scenes=<run>/scenes out_dir=<run>``): its ``renders/`` then are the sampling run's (ground
    truth | generated, 3D figures), which the evaluation neither writes over nor deletes."""
    return Path(str(scenes)).name == "scenes" and Path(out).resolve() == Path(str(scenes)).resolve().parent


def check_protocol(out: Path, protocol: EvalProtocol, fid: FIDConfig, resume: bool, assets: str,
                   own_renders: bool = True) -> str | None:
    """Pin ``protocol.json`` (:func:`spread.runtime.fingerprint.evaluation_identity`: what a per-scene line depends
    on besides its scene file); returns why the folder is redone from scratch by the platform's done-check (None:
    a resume or a new folder): lines measured with anything else (or any, with ``resume=false``) are deleted with
    the old ``metrics.json`` and renders (``own_renders``: the folder's renders are the evaluation's, not a sampling
    run's: :func:`sampling_folder`) before the new record is pinned, so a run stopped then leaves no result beside
    settings that did not make it."""
    from spread.runtime.fingerprint import done_check, evaluation_identity, normalised

    path = out / PROTOCOL
    fingerprint = normalised(evaluation_identity(protocol, fid, assets))
    try:
        before = read_json(path)
    except (OSError, ValueError):
        before = None
    decision = done_check(before, fingerprint, present=(out / PER_SCENE).exists() or (out / METRICS).exists(),
                          resume=resume, unknown=f"its {PER_SCENE} has no readable {PROTOCOL}")
    if decision.fresh:
        for old in [*(evaluation_renders(out) if own_renders else ()), out / PER_SCENE, out / METRICS]:
            old.unlink(missing_ok=True)
    write_json_atomic(path, fingerprint)
    return decision.reason


def reference_fid(cfg: EvaluationConfig, reference_files: list[Path], assets: str):
    """(SceneFID with the reference states merged in, or None; status; failed reference scenes)."""
    from spread.metrics import SceneFID

    if not cfg.fid.enabled:
        return None, "disabled: fid.enabled is false", []
    loaded = worker_extractor(cfg.fid)  # loaded once per process (the next run of a sweep trial re-uses it)
    if loaded.extractor is None:
        return None, loaded.status, []
    if len(reference_files) < 2:
        return None, f"unavailable: the reference split has {len(reference_files)} scene files (FID needs ≥ 2)", []
    fid = SceneFID(cfg.fid.feature_model, extractor=loaded.extractor, feature_dim=loaded.feature_dim or None,
                   kid_seed=cfg.protocol.seed)
    fid.fid_status = loaded.status
    failed = []
    for part in run_tasks([str(p) for p in reference_files], 16, cfg.ray, reference_fid_state,
                          (assets, cfg.fid, cfg.protocol.seed)):
        fid.merge_state(part["state"])
        failed += part["failed"]
    return fid, loaded.status, failed


def same_scenes(inputs: dict[str, str], reference_files: list[Path]) -> bool:
    """Whether the evaluated scene files (``inputs``: key → SHA-256, :func:`input_hashes`) are the reference split's
    files, by content (the same folder, or a copy of it)."""
    from spread import readonce

    if len(inputs) != len(reference_files) or not inputs:
        return False
    try:
        return sorted(inputs.values()) == sorted(readonce.file_sha256(p) for p in reference_files)
    except (OSError, ValueError):
        return False


def evaluation_renders(out: Path) -> list[Path]:
    """The pictures an earlier evaluation wrote in ``out/renders`` (:func:`write_renders`: ``<scene_id>.png`` of a scene
    its ``per_scene.jsonl`` measured) — never another file of the folder (a user's picture there stays)."""
    try:
        records = read_jsonl(out / PER_SCENE)
    except (OSError, ValueError):
        records = []
    names = {f"{r['scene_id']}.png" for r in records if isinstance(r, dict) and isinstance(r.get("scene_id"), str)}
    return [out / "renders" / n for n in sorted(names)
            if "/" not in n and (out / "renders" / n).is_file() and not (out / "renders" / n).is_symlink()]


def write_renders(out: Path, records: list[dict], assets: str, count: int, files: dict[str, Path]) -> list[Path]:
    """Top-down PNGs of the first ``count`` evaluated scenes, ``out/renders/<scene_id>.png``, each drawn from its file
    in ``scenes=`` (``files``: scene id → file), never from the path a record names (a hand-edited ``file`` drew a
    training room under a sample's name, or opened a file outside the run)."""
    from spread.render import render_topdown, save_png
    from spread.scene import read_scene

    library = worker_library(assets)
    paths = []
    for r in [r for r in records if not r.get("error")][:max(0, count)]:
        paths.append(save_png(render_topdown(read_scene(files[r["scene_id"]], assets=library), library),
                              out / "renders" / f"{r['scene_id']}.png"))
    return paths


def input_hashes(files: list[Path], keys: list[str], folder: Path) -> tuple[dict[str, str], dict[str, dict]]:
    """(scene key → SHA-256 of its file, scene key → failure record of each file refused before reading: a
    device, a FIFO, a link out of ``folder``, over the size limit; :func:`spread.io.check_input_file`). A
    refused file's hash is the marker ``"refused"``, which its failure record carries too: a resume keeps the
    record while the file stays refused and evaluates the scene once the file is a readable one."""
    from spread import readonce
    from spread.io import InputFileError, check_input_file

    inputs, refused = {}, {}
    for f, k in zip(files, keys):
        try:  # hashed once per process (a relaunch's tracker record hashed the scenes before)
            inputs[k] = readonce.file_sha256(check_input_file(f, root=folder))
        except (InputFileError, OSError) as exc:
            inputs[k] = "refused"
            refused[k] = {"scene_id": k, "file": str(f), "node_id": None, "pid": None, "input_sha256": "refused",
                          "error": f"InputFileError: {exc}", "error_type": "InputFileError"}
    return inputs, refused


def sampled_with(scenes) -> dict | None:
    """The sampling identity of the scenes evaluated (``<scenes>/../sampling.json``'s fingerprint, when the folder
    is a sampling run's ``scenes/``; None for scenes of no sampling run: ground truth, imports), read when their
    numbers are summed, so ``metrics.json`` keeps what its numbers measured after that folder is sampled again with
    other settings (``spread-report`` asks it, not the sampling folder as it is then)."""
    from spread.io import read_json_object

    path = Path(str(scenes)).parent / "sampling.json"
    if Path(str(scenes)).name != "scenes" or not path.is_file():
        return None
    try:
        manifest = read_json_object(path)
    except (OSError, ValueError):
        return None
    fingerprint = manifest.get("fingerprint")
    if not isinstance(fingerprint, dict) or "sampling" not in fingerprint:
        return None
    count = manifest.get("samples_per_graph")  # not part of the sampling identity (a run grows), but of what was scored
    return {**fingerprint, **({"samples_per_graph": count} if isinstance(count, int) else {})}


def check_fid(fid: FIDConfig) -> None:
    """``ValueError`` naming the FID setting whose backbone cannot be loaded (``fid.extractor`` that does not import,
    an unknown ``fid.feature_model``), asked of this process's extractor (:func:`worker_extractor`, loaded once: the
    reference's features need it here anyway) before an evaluation touches its folder."""
    if not fid.enabled:
        return
    try:
        worker_extractor(fid)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - an import or factory error of a user's backbone: named in one line
        what = f"fid.extractor={fid.extractor}" if fid.extractor else f"fid.feature_model={fid.feature_model}"
        raise ValueError(f"{what}: cannot be loaded ({type(exc).__name__}: {exc})") from None


def scenes_over_limit(cfg: EvaluationConfig) -> dict[str, int]:
    """Scene key → object count of each scene file of ``cfg.scenes`` over the run's object limit
    (:func:`spread.data.limit.object_limit` of ``cfg.max_objects`` against the reference dataset); a file that does
    not read as a scene is not counted here (its evaluation names why)."""
    from spread.data.limit import object_limit, scenes_over
    from spread.scene import list_scene_files

    files = list_scene_files(cfg.scenes) if Path(str(cfg.scenes)).is_dir() else []
    over = scenes_over(files, object_limit(cfg.reference, cfg.max_objects))
    return {scene_key(f): n for f, n in sorted(over.items())}


def evaluated_with(cfg: EvaluationConfig, assets: str, over: dict[str, int] | None = None) -> dict:
    """What ``metrics.json``'s numbers were measured with (``spread-report`` asks it, not ``protocol.json`` as it
    is when the report runs): the evaluation identity (:func:`spread.runtime.fingerprint.evaluation_identity`), the
    reference split and its content (FID/KID's real set), in the shape a sweep point records them; and the scenes
    the object limit left out (``over``: :func:`scenes_over_limit`, asked when None), where it left out any — they
    change what the numbers average over, as sampling's ``graphs_over_limit`` does."""
    from spread.runtime.fingerprint import evaluation_identity, left_out, normalised, tree_digest

    over = scenes_over_limit(cfg) if over is None else over
    return normalised({**evaluation_identity(cfg.protocol, cfg.fid, assets),
                       "reference_split": str(cfg.reference_split),
                       "reference": tree_digest(Path(cfg.reference) / cfg.reference_split),
                       **({"scenes_over_limit": left_out(over)} if over else {})})  # bounded: a tracker's tag


def run_evaluation(cfg: EvaluationConfig, before_work: Callable[[], None] | None = None) -> EvaluationResult:
    """Evaluate every scene file of ``cfg.scenes`` (module docstring); ``before_work()`` runs once the checks
    passed (the command records its config there). The run holds ``out_dir``'s lock
    (:func:`spread.io.run_lock`): a second evaluation of the same folder is refused while this one runs."""
    from spread.io import run_lock

    with run_lock(cfg.out_dir, "spread-evaluate"):
        return _run_evaluation(cfg, before_work)


def _run_evaluation(cfg: EvaluationConfig, before_work: Callable[[], None] | None = None) -> EvaluationResult:
    from spread.scene import list_scene_files
    from tqdm.auto import tqdm

    started = time.perf_counter()
    out = Path(cfg.out_dir)
    # its own, or the sampling run whose scenes it measures (spread-evaluate scenes=<run>/scenes out_dir=<run>)
    check_folder_kind(out, "spread-evaluate", {"evaluation", "sampling run"} if sampling_folder(out, cfg.scenes)
                      else {"evaluation"})
    out.mkdir(parents=True, exist_ok=True)
    files = list_scene_files(cfg.scenes) if Path(cfg.scenes).is_dir() else []
    if not files:
        raise FileNotFoundError(f"scenes={cfg.scenes}: no scene files (<scene_id>.npz) to evaluate")
    keys = [scene_key(f) for f in files]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{cfg.scenes}: two scene files share a name")
    assets = str(Path(cfg.reference) / "assets")
    if not (Path(assets) / "index.json").exists():
        raise FileNotFoundError(f"reference={cfg.reference}: no asset library at {assets} (missing index.json)")
    over = scenes_over_limit(cfg)  # left out by name before any work, the run goes on with the others
    if over:
        from spread.data.limit import object_limit

        limit = object_limit(cfg.reference, cfg.max_objects)
        if len(over) == len(files):
            raise ValueError(f"scenes={cfg.scenes}: every scene is over the object limit {limit} (the largest holds "
                             f"{max(over.values())} objects; set max_objects=<n> to raise it, 0: no limit)")
        import logging

        logging.getLogger("spread.evaluate").warning(
            "left out %d of %d scenes over the object limit %d (max_objects): %s", len(over), len(files), limit,
            ", ".join(f"{k} ({n} objects)" for k, n in list(over.items())[:3]))
        files, keys = [f for f, k in zip(files, keys) if k not in over], [k for k in keys if k not in over]
    from spread import readonce

    readonce.asset_library(assets)  # its index read here: a bad record is refused before any worker starts
    ref_dir = Path(cfg.reference) / cfg.reference_split
    reference_files = list_scene_files(ref_dir) if ref_dir.is_dir() else []
    per_scene = out / PER_SCENE
    check_fid(cfg.fid)  # a backbone that cannot be loaded is refused before the folder is touched
    in_sampling_run = sampling_folder(out, cfg.scenes)
    redone_because = check_protocol(out, cfg.protocol, cfg.fid, cfg.resume, assets, own_renders=not in_sampling_run)
    if before_work is not None:
        before_work()
    inputs, refused = input_hashes(files, keys, Path(cfg.scenes))
    finished, changed = load_finished(per_scene, retry_failed=cfg.retry_failed, inputs=inputs)
    for key, record in refused.items():  # never sent to a worker: recorded here, the run goes on
        if key not in finished:
            finished[key] = record
            append_jsonl(per_scene, record)
    todo = [str(f) for f, k in zip(files, keys) if k not in finished]
    bar = tqdm(total=len(files), initial=len(files) - len(todo), desc="scenes", unit="scene",
               disable=not cfg.progress)

    def on_record(record: dict) -> None:
        if record["scene_id"] in finished:  # never twice, whatever happens upstream
            return
        finished[record["scene_id"]] = record
        append_jsonl(per_scene, record)
        bar.update(1)

    with ray_session(cfg.ray, owner=out) as cluster:
        fan = fan_out(todo, cfg.chunk_size, cfg.ray, evaluate_chunk, (assets, cfg.protocol, cfg.fid), on_record,
                      failure_record) if todo else None
        fid, fid_status, ref_failed = reference_fid(cfg, reference_files, assets)
    bar.close()
    if fid is not None and same_scenes(inputs, reference_files):  # the status fid_values records is the metric's
        fid.fid_status = (f"{fid.fid_status}; warning: scenes= holds the reference split's own files ({ref_dir}), so "
                          f"FID and KID compare a set with itself (~0 by construction); give another reference_split")

    wanted = set(keys)
    records = [r for k, r in dedupe(read_jsonl(per_scene)).items() if k in wanted]
    records.sort(key=lambda r: r["scene_id"])
    metrics = summary_values(records, cfg.protocol)
    by_type = per_room_type_values(records, cfg.protocol)
    if by_type is not None:
        metrics["per_room_type"] = by_type
    if cfg.bootstrap_resamples > 0:
        metrics.update(bootstrap_intervals(records, cfg.bootstrap_resamples, seed=cfg.protocol.seed,
                                           metrics=cfg.protocol.build_metrics()))
    metrics.update(fid_values(fid, records, fid_status, len(reference_files) - len(ref_failed),
                              cfg.fid.feature_model))
    kept = cfg.protocol.build_metrics()  # what each record's states must be to enter the sums
    metrics.update({
        "failed": [{"scene_id": r["scene_id"], "error": r.get("error") or "unusable record (a non-finite, missing "
                    "or malformed metric state)"} for r in records if not usable(r, kept)],
        "failed_metrics": [{"scene_id": r["scene_id"], "metric": name, "error": error} for r in records
                           if usable(r, kept) for name, error in (r.get("metric_errors") or {}).items()],
        "fid_reference_failed": ref_failed,
        "scenes": str(Path(str(cfg.scenes)).absolute()), "sampled_with": sampled_with(cfg.scenes),  # read from anywhere
        "evaluated_with": evaluated_with(cfg, assets, over), "evaluated_scenes": [r["scene_id"] for r in records],
        "scenes_over_limit": [{"scene_id": k, "objects": n} for k, n in over.items()],
        "bootstrap_resamples": int(cfg.bootstrap_resamples),
        "reference": str(cfg.reference), "reference_split": cfg.reference_split,
        "protocol": cfg.protocol.to_dict(cfg.fid), "versions": versions(), "redone_because": redone_because,
        "run": {"evaluated_this_run": len(todo), "resumed": len(files) - len(todo),
                "skipped_as_done": len(files) - len(todo), "redone_input_changed": len(changed),
                "tasks": fan.tasks if fan else 0, "split_chunks": fan.split_chunks if fan else 0,
                "chunk_size": cfg.chunk_size, "seconds": round(time.perf_counter() - started, 3),
                "ray": {**cluster, "max_retries": cfg.ray.max_retries,
                        "scheduling_strategy": cfg.ray.scheduling_strategy}},
    })
    write_json_atomic(out / METRICS, metrics)
    # in the sampling run's folder its renders show these scenes already (reports find them there)
    renders = [] if in_sampling_run else write_renders(out, records, assets, cfg.renders, dict(zip(keys, files)))
    if not in_sampling_run:  # an earlier run's picture of a scene this run does not render (removed since) goes
        for stale in set(evaluation_renders(out)) - set(renders):
            stale.unlink(missing_ok=True)
    return EvaluationResult(metrics, records, renders, out)
