"""Runs on disk → flat records: run folders (``metrics.json`` + config) and wandb offline runs (no network).

A **run folder** (DESIGN §4) is a folder with an evaluation ``metrics.json`` (one that has ``col_mesh``):
``spread-evaluate``'s out_dir, or a ``spread-sample evaluate=true`` out_dir. Its **identity** is what its numbers
were made with, as recorded beside them (:mod:`spread.runtime.fingerprint`): ``point.json``'s fingerprint, else the
sampling fingerprint of the scenes its ``metrics.json`` recorded when it summed them (``sampled_with``; for an
evaluation written before that record: the ``sampling.json`` of its own folder, or of the sampling run whose scenes
it evaluated, as it is now) with the evaluation's ``protocol.json``, else what ``.hydra/config.yaml`` (the composed config) gives. A record carries its
flat :func:`~spread.runtime.fingerprint.settings` (``settings``: every guidance term's weight by name,
``guidance.iterations``, the sampler, the protocol, ...), ``identity`` (their short digest: runs alike in
everything share it) and each metric's value and confidence interval (:mod:`spread.reporting.intervals`: from
``metrics.json``, or bootstrapped from ``per_scene.jsonl``).

A **wandb offline run** is a ``wandb/offline-run-<time>-<id>`` folder. wandb ≥ 0.2x keeps an offline run
only in ``run-<id>.wandb``: a LevelDB-style log (7-byte file header, 32 KiB blocks, records of
``crc32 · length · type`` + a protobuf ``Record``). :func:`read_wandb_run` decodes it with wandb's own
protobuf classes and folds the run's config and summary updates (``files/config.yaml`` and
``files/wandb-summary.json`` are read instead where an older wandb wrote them).

:func:`find_runs` expands the ``runs`` argument of ``spread-report``: run folders, wandb run folders,
globs, and sweep folders (searched recursively). Errors name the path that is wrong.
"""

from __future__ import annotations

import glob
import json
import struct
from pathlib import Path
from typing import Iterable

from spread.reporting.intervals import ci_columns, row_intervals
from spread.reporting.tables import CI_SETTINGS
from spread.io import read_bytes_checked, read_json_object, read_text_checked

#: ``metrics.json`` keys copied into a record besides every registered value's (:func:`record_metrics`).
RECORD_EXTRAS = ("n_scenes", "n_objects", "n_failed", "fid_status")


def record_metrics() -> list[str]:
    """The ``metrics.json`` keys a run record copies: every registered value (plugins' too; Stability's
    ``still_fraction``), FID, KID, then the extras."""
    from spread.metrics.registry import display_values, METRICS

    return [*[v.name for v in display_values(METRICS.names())], *RECORD_EXTRAS]


def metric_names() -> list[str]:
    from spread.metrics.registry import METRICS

    return METRICS.names()


#: Markers of a run folder that has not finished (no ``metrics.json`` yet).
UNFINISHED_MARKERS = ("sampling.json", "scenes", "per_scene.jsonl", "protocol.json")
WANDB_BLOCK = 32768
WANDB_HEADER = 7


class RunError(ValueError):
    """A run path that cannot be read; the message names the path."""


def select(tree, dotted: str):
    """``tree["a"]["b"]`` for ``"a.b"``, or ``tree["a.b"]`` (wandb sweeps use flat dotted keys); None if absent."""
    if isinstance(tree, dict) and dotted in tree:
        return tree[dotted]
    node = tree
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def is_evaluation(metrics: dict) -> bool:
    """An evaluation's ``metrics.json`` (it counts evaluated scenes and records its protocol), whichever metrics
    it selected."""
    if not isinstance(metrics, dict):
        return False
    return "n_evaluated" in metrics or any(k in metrics for k in metric_names())


def is_eval_metrics(path: Path) -> bool:
    try:
        return is_evaluation(read_json_object(path))
    except (OSError, ValueError):
        return False


def is_finished_run(path: str | Path) -> bool:
    """True when ``path/metrics.json`` is an evaluation's (written atomically at its end): a sweep point whose
    run folder holds one is finished and can be skipped."""
    return is_eval_metrics(Path(path) / "metrics.json")


def is_wandb_run(path: Path) -> bool:
    return path.is_dir() and path.name.startswith(("offline-run-", "run-")) and (
        any(path.glob("*.wandb")) or (path / "files" / "wandb-summary.json").exists())


def is_eval_wandb_run(path: Path) -> bool:
    """A wandb run folder whose summary holds evaluation metrics (not a training or ablation run)."""
    try:
        read_wandb_run(path)
        return True
    except (RunError, OSError, ValueError):
        return False


def is_unfinished_run(path: Path) -> bool:
    return not (path / "metrics.json").exists() and any((path / m).exists() for m in UNFINISHED_MARKERS)


def why_unfinished(path: Path) -> str:
    """Why the run folder ``path`` (:func:`is_unfinished_run`) has no results yet, and what gives it some: a sampling
    run that finished without an evaluation is not a run that has not finished."""
    sampling = path / "sampling.json"
    if sampling.exists() and not any((path / m).exists() for m in ("per_scene.jsonl", "protocol.json")):
        try:
            record = read_json_object(sampling, RunError)
        except (RunError, OSError) as exc:
            return f"no metrics.json, and its sampling.json is unreadable: {exc}"
        if record.get("status") == "running":
            return f"no metrics.json: it is still sampling, or was stopped ({sampling}: status running)"
        import shlex

        fingerprint = record.get("fingerprint")
        root = fingerprint.get("data_root") if isinstance(fingerprint, dict) else None
        line = " ".join(shlex.quote(a) for a in (f"scenes={path / 'scenes'}", f"out_dir={path}"))
        reference = shlex.quote(f"reference={root}") if isinstance(root, str) and root else "reference=<the dataset>"
        return (f"no metrics.json: its scenes are sampled but not evaluated (yet, or sampled without evaluate=true); "
                f"give its evaluation's folder, or evaluate it in place: spread-evaluate {line} {reference}")
    return "no metrics.json (the run has not finished)"


# ---- run folders ---------------------------------------------------------------------------------

def read_run_folder(path: str | Path) -> dict:
    """One record of a run folder: name, source, its settings and identity (module docstring) and the metrics."""
    path = Path(path)
    metrics_path = path / "metrics.json"
    if not metrics_path.exists():
        raise RunError(f"{path}: {why_unfinished(path)}" if is_unfinished_run(path) else
                       f"{path}: no metrics.json (the run has not finished, or this is not a run folder)")
    metrics = read_json_object(metrics_path, RunError)
    if not is_evaluation(metrics):
        raise RunError(f"{metrics_path}: not an evaluation metrics.json (no registered metric and no 'n_evaluated')")
    check_shape(metrics_path, metrics)
    record = {"run": path.name, "source": str(path), "kind": "folder",
              **identity_fields(folder_identity(path, metrics))}
    record.update({k: metrics.get(k) for k in record_metrics()})
    record.update(ci_columns(row_intervals(metrics, path)))
    return record


def check_shape(path: Path, metrics: dict) -> None:
    """``RunError`` naming the file and key when a ``metrics.json`` holds a part the report reads in another shape
    than the evaluation writes it (a hand edit): ``bootstrap`` an object, ``per_room_type`` an object of objects
    and the counts ``n_scenes``, ``n_objects``, ``n_failed`` whole numbers ≥ 0; no value, interval bound or room
    type's value a ``NaN`` (the evaluation writes null where a metric has no value: a table would show a NaN as that
    missing value, –, hiding the edit). A metric's own value that is not a number, or ±inf, is shown
    ``invalid (...)`` instead, :class:`~spread.reporting.tables.Column`)."""
    if metrics.get("bootstrap") is not None and not isinstance(metrics["bootstrap"], dict):
        raise RunError(f"{path}: key 'bootstrap' is {type(metrics['bootstrap']).__name__}, expected an object")
    check_bootstrap(path, metrics.get("bootstrap") or {})
    sampled = metrics.get("sampled_with")
    if sampled is not None and not (isinstance(sampled, dict) and all(
            sampled.get(part) is None or isinstance(sampled[part], dict) for part in ("guidance", "sampling"))):
        raise RunError(f"{path}: key 'sampled_with' is not a sampling identity (an object whose 'sampling' and "
                       f"'guidance' are objects), as spread-evaluate writes it")
    rooms = metrics.get("per_room_type")
    if rooms is not None and not (isinstance(rooms, dict) and all(isinstance(v, dict) for v in rooms.values())):
        raise RunError(f"{path}: key 'per_room_type' is not an object of room types to objects of metrics")
    from spread.checks import is_whole

    for key in ("n_scenes", "n_objects", "n_failed"):  # counts: a table prints them as they are
        value = metrics.get(key)
        if value is not None and not (is_whole(value) and 0 <= value < 2 ** 53):
            raise RunError(f"{path}: key '{key}' is {value!r:.40}, expected a whole number in [0, 2^53)")
    names = [n for key in record_metrics() for n in (key, f"{key}_lo", f"{key}_hi")]
    for where, block in [("", metrics), *[(f"per_room_type.{t}.", v) for t, v in (rooms or {}).items()]]:
        for name in names:
            value = block.get(name)
            if isinstance(value, float) and value != value:
                raise RunError(f"{path}: key '{where}{name}' is NaN, a value spread-evaluate never writes (null "
                               f"where a metric has no value); restore the file or evaluate the run again")


def check_bootstrap(path: Path, block: dict) -> None:
    """``RunError`` naming the file and key for a ``bootstrap`` block whose fields the report's interval note reads
    in another shape than the evaluation writes them (:func:`spread.evaluation.bootstrap`): ``level`` a number in
    (0, 1), ``resamples`` and ``seed`` whole numbers, ``measured`` an object of whole counts ≥ 0."""
    import math

    from spread.checks import is_whole

    level = block.get("level")
    if "level" in block and not (isinstance(level, (int, float)) and not isinstance(level, bool)
                                 and math.isfinite(level) and 0 < level < 1):
        raise RunError(f"{path}: key 'bootstrap.level' is {level!r}, expected a number in (0, 1)")
    for key in ("resamples", "seed"):
        if key in block and not (is_whole(block[key]) and block[key] >= 0):
            raise RunError(f"{path}: key 'bootstrap.{key}' is {block[key]!r}, expected a whole number ≥ 0")
    measured = block.get("measured")
    if "measured" in block and not (isinstance(measured, dict) and all(
            is_whole(v) and v >= 0 for v in measured.values())):
        raise RunError(f"{path}: key 'bootstrap.measured' is not an object of whole counts ≥ 0 per metric")
    if block and "level" not in block:
        raise RunError(f"{path}: key 'bootstrap.level' is missing (the intervals' confidence level)")


def identity_fields(identity: dict) -> dict:
    """A record's ``settings`` (flat, :func:`spread.runtime.fingerprint.settings`) and ``identity`` (their digest)."""
    from spread.runtime.fingerprint import settings, short

    flat = settings(identity)
    return {"settings": flat, "identity": short(flat)}


def folder_identity(path: Path, metrics: dict) -> dict:
    """What a run folder's numbers were made with, as recorded beside them (module docstring), in today's spelling
    (:func:`spread.runtime.fingerprint.upgraded`: a record of an earlier version names the same settings the same
    way; a recorded ``device: auto`` is kept as written)."""
    from spread.runtime.fingerprint import upgraded

    return upgraded(recorded_identity(path, metrics))


def recorded_identity(path: Path, metrics: dict) -> dict:
    """:func:`folder_identity` as the folder's records spell it."""
    from spread.runtime.fingerprint import config_identity, measured_identity

    point = optional_json(path / "point.json")
    if isinstance(point.get("fingerprint"), dict):  # a sweep point: its record, but what metrics.json measured with
        return {**point["fingerprint"], **(measured_identity(metrics) or {})}  # wins where they differ (another
        # command wrote into the folder)
    identity: dict = {}
    hydra = path / ".hydra" / "config.yaml"
    if hydra.exists():
        from omegaconf import OmegaConf

        text = read_text_checked(hydra)
        try:
            tree = OmegaConf.to_container(OmegaConf.create(text), resolve=False)
        except Exception as exc:  # noqa: BLE001 - YAML's and OmegaConf's parse errors: the file named in one line
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise RunError(f"{hydra}: not a readable config ({first})") from None
        try:
            identity |= config_identity(tree if isinstance(tree, dict) else {})
        except (ValueError, TypeError) as exc:
            raise RunError(f"{hydra}: {exc}") from None
    if isinstance(metrics.get("sampled_with"), dict):  # what the evaluation measured, as it recorded it
        identity |= metrics["sampled_with"]
    else:  # none recorded (written before that record, or scenes of no fingerprinted run): the folders as they are
        identity = recorded_sampling(path, metrics, identity)
    recorded = metrics.get("evaluated_with")
    if isinstance(recorded, dict) and isinstance(recorded.get("protocol"), dict):  # what its numbers measured with
        identity["evaluation"] = recorded
    else:  # written before that record: the folder's protocol.json as it is
        protocol = optional_json(path / "protocol.json")
        if isinstance(protocol.get("protocol"), dict):
            identity["evaluation"] = protocol
    return identity


def recorded_sampling(path: Path, metrics: dict, identity: dict) -> dict:
    """``identity`` with the sampling identity an evaluation without a ``sampled_with`` record is given: its
    scenes' sampling folder's ``sampling.json`` fingerprint as it is when the report reads it (or, for older
    manifests, its guidance where ``identity`` has none)."""
    from spread.runtime.fingerprint import config_identity

    identity = dict(identity)
    for sampling in sampling_manifests(path, metrics):
        manifest = read_json_object(sampling, RunError)
        if isinstance(manifest.get("fingerprint"), dict) and "sampling" in manifest["fingerprint"]:
            identity |= manifest["fingerprint"]
            if isinstance(manifest.get("samples_per_graph"), int):
                identity.setdefault("samples_per_graph", manifest["samples_per_graph"])
        elif "guidance" in manifest and "guidance" not in identity:
            identity |= config_identity({"guidance": manifest["guidance"] or "none"})
    return identity


def name_differences(records: list[dict], exclude=()) -> list[str]:
    """The settings that differ between ``records`` (their ``settings``, :func:`identity_fields`; ``exclude``: keys
    named otherwise), each copied into every record as a field of its own, so a table names them per run;
    returns their keys."""
    from spread.runtime.fingerprint import differing

    differ = [k for k in differing([r.get("settings") or {} for r in records]) if k not in exclude]
    for r in records:
        r.update({k: (r.get("settings") or {}).get(k) for k in differ})
    return differ


def optional_json(path: Path) -> dict:
    """A JSON object file (read through :func:`spread.io.read_json_object`: a FIFO, device or oversized file is a
    :class:`RunError` naming it), or {} when it is missing."""
    if not path.exists() and not path.is_symlink():
        return {}
    return read_json_object(path, RunError)


def sampling_manifests(path: Path, metrics: dict) -> list[Path]:
    """``sampling.json`` of the run folder itself, then of the sampling run whose scenes it evaluated
    (``metrics.json``'s ``scenes`` = ``<sampling run>/scenes``, as spread-ablate's ``eval/<v>`` folders)."""
    found = [path / "sampling.json"]
    if metrics.get("scenes"):
        found.append(Path(str(metrics["scenes"])).parent / "sampling.json")
    return [p for p in found if p.exists()]


# ---- wandb offline runs --------------------------------------------------------------------------

def wandb_records(path: Path) -> list[bytes]:
    """The raw records of a ``.wandb`` file (LevelDB log framing; module docstring)."""
    data = read_bytes_checked(path, max_bytes=0)
    if data[:4] != b":W&B":
        raise RunError(f"{path}: not a wandb run file (bad header)")
    out, pending, pos = [], b"", WANDB_HEADER
    while pos + 7 <= len(data):
        left = WANDB_BLOCK - pos % WANDB_BLOCK
        if left < 7:  # block trailer padding
            pos += left
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0 and length == 0:
            pos += left
            continue
        chunk = data[pos + 7:pos + 7 + length]
        pos += 7 + length
        if kind == 1:  # full
            out.append(chunk)
        elif kind == 2:  # first
            pending = chunk
        elif kind == 3:  # middle
            pending += chunk
        elif kind == 4:  # last
            out.append(pending + chunk)
            pending = b""
    return out


def apply_items(tree: dict, items, remove: bool = False) -> None:
    """Fold wandb config/summary items (``key`` or ``nested_key`` path, ``value_json``) into ``tree``."""
    for item in items:
        keys = list(item.nested_key) or [item.key]
        node = tree
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        if remove:
            node.pop(keys[-1], None)
        else:
            node[keys[-1]] = json.loads(item.value_json)


def read_wandb_file(path: Path) -> dict:
    """``{"id", "name", "project", "config", "summary"}`` of a ``.wandb`` file."""
    from wandb.proto import wandb_internal_pb2 as pb

    run = {"id": None, "name": None, "project": None, "config": {}, "summary": {}}
    for raw in wandb_records(path):
        record = pb.Record()
        record.ParseFromString(raw)
        kind = record.WhichOneof("record_type")
        if kind == "run":
            r = record.run
            run.update(id=r.run_id, name=r.display_name or r.run_id, project=r.project)
            apply_items(run["config"], r.config.update)
            apply_items(run["summary"], r.summary.update)
        elif kind == "config":
            apply_items(run["config"], record.config.update)
            apply_items(run["config"], record.config.remove, remove=True)
        elif kind == "summary":
            apply_items(run["summary"], record.summary.update)
            apply_items(run["summary"], record.summary.remove, remove=True)
    return run


def read_wandb_run(path: str | Path) -> dict:
    """One record of a wandb offline run folder (settings of its config, summary metrics)."""
    path = Path(path)
    files = path / "files"
    if (files / "wandb-summary.json").exists():  # older wandb: plain files
        from omegaconf import OmegaConf

        raw = OmegaConf.to_container(OmegaConf.create(read_text_checked(files / "config.yaml"))) \
            if (files / "config.yaml").exists() else {}
        config = {k: v.get("value") if isinstance(v, dict) and "value" in v else v for k, v in raw.items()}
        run = {"id": path.name.rsplit("-", 1)[-1], "name": None, "config": config,
               "summary": read_json_object(files / "wandb-summary.json", RunError)}
    else:
        found = sorted(path.glob("*.wandb"))
        if not found:
            raise RunError(f"{path}: no .wandb file and no files/wandb-summary.json (not a wandb run folder)")
        run = read_wandb_file(found[0])
    from spread.metrics.registry import in_stored_units

    summary = in_stored_units(run["summary"])  # the trackers' display units (asd_mm) back to metrics.json's
    if not any(k in summary for k in metric_names()):
        raise RunError(f"{path}: the wandb run has no registered metric in its summary (not an evaluation run)")
    from spread.runtime.fingerprint import config_identity, tracked_identity, upgraded

    measured = tracked_identity(run["config"].get("spread_identity"))  # what it measured with, as metrics.json says
    identity = upgraded(measured) if measured is not None else config_identity(run["config"])
    record = {"run": run.get("name") or run["id"], "source": str(path), "kind": "wandb", **identity_fields(identity)}
    record.update({k: summary.get(k) for k in record_metrics()})
    bounds = [f"{m}_{b}" for m in record_metrics() for b in ("lo", "hi")]
    record.update({k: summary.get(k) for k in (*bounds, *CI_SETTINGS) if k in summary})
    return record


# ---- discovery -----------------------------------------------------------------------------------

def search(folder: Path) -> tuple[list[Path], list[Path], list[Path]]:
    """(run folders, wandb runs, unfinished run folders) under ``folder``; a run folder's own wandb runs
    are not listed again (they hold the same numbers)."""
    runs, wandb_runs, unfinished = [], [], []
    evaluated = set()  # sampling folders whose scenes a run folder evaluated: finished, not open runs
    for metrics in sorted(folder.rglob("metrics.json")):
        if is_eval_metrics(metrics):
            runs.append(metrics.parent)
            scenes = read_json_object(metrics).get("scenes")
            if scenes:
                evaluated.add(Path(str(scenes)).parent.resolve())
    inside = tuple(runs)
    for candidate in sorted(folder.rglob("*run-*")):
        if is_wandb_run(candidate) and not any(r in candidate.parents for r in inside) and is_eval_wandb_run(candidate):
            wandb_runs.append(candidate)
    for marker in UNFINISHED_MARKERS:
        for hit in folder.rglob(marker):
            parent = hit.parent
            if (is_unfinished_run(parent) and parent not in unfinished and parent.resolve() not in evaluated
                    and not any(r in parent.parents for r in inside)):
                unfinished.append(parent)
    return runs, wandb_runs, sorted(unfinished)


def find_runs(entries: str | Iterable[str]) -> tuple[list[tuple[str, Path]], list[Path]]:
    """Expand ``runs`` (paths, globs, sweep folders) into ``[("folder" | "wandb", path)]`` and the unfinished
    run folders found inside sweep folders or by globs. A named path that is missing, a glob matching nothing,
    a named run folder without ``metrics.json`` or a folder with no run at all raise :class:`RunError`."""
    if isinstance(entries, (str, Path)):
        entries = [entries]
    found: list[tuple[str, Path]] = []
    unfinished: list[Path] = []
    for entry in [str(e) for e in entries]:
        pattern = glob.has_magic(entry)
        paths = [Path(p) for p in sorted(glob.glob(entry))] if pattern else [Path(entry)]
        if not paths:
            raise RunError(f"runs: {entry}: the pattern matches nothing")
        for path in paths:
            if not path.exists():
                raise RunError(f"runs: {path}: no such folder")
            if is_wandb_run(path):
                if pattern and not is_eval_wandb_run(path):  # a glob's training or ablation run: not a result
                    continue
                found.append(("wandb", path))
            elif (path / "metrics.json").exists():
                found.append(("folder", path))
            elif path.is_dir() and is_unfinished_run(path):
                if not pattern:  # named explicitly: an error; matched by a glob: skipped, like in a sweep folder
                    raise RunError(f"runs: {path}: {why_unfinished(path)}")
                unfinished.append(path)
            elif path.is_dir():
                runs, wandb_runs, open_runs = search(path)
                if not runs and not wandb_runs:
                    raise RunError(f"runs: {path}: no metrics.json, and no run folders or wandb offline runs under it")
                found += [("folder", p) for p in runs] + [("wandb", p) for p in wandb_runs]
                unfinished += open_runs
            else:
                raise RunError(f"runs: {path}: not a folder")
    unique, seen = [], set()
    for kind, path in found:
        if path.resolve() not in seen:
            seen.add(path.resolve())
            unique.append((kind, path))
    return latest_wandb_folders(unique), unfinished


def latest_wandb_folders(found: list[tuple[str, Path]]) -> list[tuple[str, Path]]:
    """``found`` with one folder per wandb run id, its latest (``offline-run-<time>-<id>``): a relaunch that
    continues a run (:mod:`spread.tracking.continuation`) writes it offline into a second folder of the same id, and
    the run was read as two runs (a mean over seeds counted its seed twice)."""
    def run_id(path: Path) -> str:
        return path.name.rsplit("-", 1)[-1]

    latest: dict[str, Path] = {}
    for kind, path in found:
        if kind == "wandb" and (run_id(path) not in latest or path.name > latest[run_id(path)].name):
            latest[run_id(path)] = path
    return [(kind, path) for kind, path in found if kind != "wandb" or latest[run_id(path)] == path]


def read_runs(entries) -> tuple[list[dict], list[Path]]:
    """Records of every run :func:`find_runs` lists (sorted by the settings that differ between them, then
    name), and the unfinished folders."""
    from spread.runtime.fingerprint import differing

    found, unfinished = find_runs(entries)
    records = [read_run_folder(p) if kind == "folder" else read_wandb_run(p) for kind, p in found]
    names = [r["run"] for r in records]
    for r in records:  # two runs with one name (e.g. two sweeps): name them by their path
        if names.count(r["run"]) > 1:
            r["run"] = r["source"]
    differ = differing([r["settings"] for r in records])
    records.sort(key=lambda r: (*[sort_key(r["settings"].get(k)) for k in differ], r["run"]))
    return records, unfinished


def sort_key(value) -> tuple:
    """Orders a column of settings: numbers by value, then text, missing last."""
    if value is None:
        return (2, 0.0, "")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (0, float(value), "")
    return (1, 0.0, str(value))
