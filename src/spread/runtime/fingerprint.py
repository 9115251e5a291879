"""The one "already done with the same inputs?" of the platform: what a number depends on, and the one rule that
re-uses, resumes or redoes work by it (a re-launched run never reports old numbers as new ones).

**Identities** are plain dicts built from the typed settings (each setting asked, never re-derived):

* :func:`sampling_identity` — what a generated scene file depends on (``sampling.json``): the checkpoint's bytes
  (``ckpt_sha256``, hashed once per process by path, size and mtime), the split (``split``) and its content
  (``data``: :func:`dataset_digest`), ``sampling`` (the :class:`~spread.model.Sampler`'s fingerprint, seed, batch
  size, EMA, graph scale, device), ``guidance`` (:meth:`spread.guidance.GuidanceConfig.fingerprint`: the mode, λ of
  every registered term that acts — built-ins, PhyScene's, a plugin's — and every other setting; ``None``
  unguided), ``numbers_version``;
* :func:`evaluation_identity` — what a per-scene line depends on besides its scene file (``protocol.json``):
  the protocol, the FID settings, the asset library's index, ``numbers_version``;
* :func:`point_identity` — a ``spread-sample evaluate=true`` run (a sweep point, ``point.json``): both, the
  samples per graph and the reference split's content.

:data:`NUMBERS_VERSION` is the code's version of the numbers, bumped by a change that changes scenes or metrics.
:func:`short` is an identity's 8-hex-digit name (sweep point folders end with it).

**The done-check** (:func:`done_check`) compares the identity recorded with some outputs with this run's, by
:func:`changed_keys` (the one), and says ``reuse`` (finished with the same inputs), ``resume`` (same inputs,
unfinished), ``redo`` (other inputs, or none recorded: from scratch, with the reason) or ``new``. Sampling,
evaluation, sweep points and the ablation's and comparison's stages all decide by it.

:func:`settings` turns an identity into the flat, readable settings tables and reports name per run
(``guidance.iterations``, ``guidance.floor_push``, ``sampler``, ``protocol.stability_runs``, ...), and
:func:`differing` names the settings that differ between runs. :func:`run_tags` are the facts of where a run
ran (job id, world size, node list, git SHA), recorded beside results but never compared. Units: none; all
digests are hex sha256.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

#: Bump when a code change changes sampled scenes or metrics (every earlier result is then redone).
NUMBERS_VERSION = 2


def canonical(obj) -> str:
    """One JSON text per value (sorted keys, paths and tuples as JSON sees them)."""
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))


def digest(obj) -> str:
    return hashlib.sha256(canonical(obj).encode()).hexdigest()


def short(fingerprint: dict, n: int = 8) -> str:
    """The fingerprint's short name (first ``n`` hex digits of the sha256 of what it holds but :data:`WHERE`: a
    point folder's name stays when its dataset moves)."""
    return digest({k: v for k, v in fingerprint.items() if k not in WHERE})[:n]


def file_digest(path) -> str:
    """sha256 of a file's bytes (``missing:<path>`` when it is not a file); hashed once per process while the
    file is unchanged (:func:`spread.readonce.file_sha256`, the hash a sampling run records too)."""
    from spread import readonce

    p = Path(str(path))
    if not p.is_file():
        return f"missing:{path}"
    return readonce.file_sha256(p)


def tree_digest(folder, pattern: str = "*.npz") -> str:
    """sha256 over the sorted (name, sha256) of the folder's files matching ``pattern`` (``empty`` if none)."""
    folder = Path(str(folder))
    files = sorted(folder.glob(pattern)) if folder.is_dir() else []
    if not files:
        return f"empty:{folder}"
    return digest([(f.name, file_digest(f)) for f in files])


def dataset_digest(root, splits, placeless_markers: bool = False) -> str:
    """The content of a dataset folder as far as a run reads it: the splits' scene files, the asset index and
    the normalisation statistics (a split or file that is not there names its path: ``empty:`` / ``missing:``; runs
    recorded these digests, so they stay as they are; ``placeless_markers``: without those paths, :func:`placeless`,
    as a checkpoint records its training data, :func:`spread.training.fit.data_digest`)."""
    root = Path(str(root))
    parts = {f"split:{s}": tree_digest(root / s) for s in sorted({str(s) for s in splits if s})}
    parts["assets"] = file_digest(root / "assets" / "index.json")
    parts["stats"] = file_digest(root / "stats.json")
    if placeless_markers:
        parts = {k: placeless(v) for k, v in parts.items()}
    return digest(parts)


def placeless(value: str) -> str:
    """A digest without the path its ``empty:`` / ``missing:`` marker names: what the data is, not where (a moved
    dataset without a val split, or without statistics, is the same data)."""
    return value.split(":", 1)[0] if value.startswith(("empty:", "missing:")) else value


def changed_keys(before: dict, now: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ (nested dicts compared key by key; JSON-equal values are equal)."""
    out = []
    for k in sorted(set(before) | set(now)):
        a, b = before.get(k), now.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += changed_keys(a, b, f"{prefix}{k}.")
        elif canonical(a) != canonical(b):
            out.append(f"{prefix}{k}")
    return out


def described_changes(before: dict, now: dict, held_only: bool = False) -> list[str]:
    """``key: old -> new`` for each of :func:`changed_keys` (nested keys dotted; a key one side lacks: None).
    ``held_only``: keys ``before`` does not hold (settings added after it was recorded, at their defaults) are not
    compared."""
    def held(record, shape):
        return {k: held(v, shape[k]) if isinstance(v, dict) and isinstance(shape.get(k), dict) else v
                for k, v in record.items() if k in shape}

    if held_only:
        now = held(now, before)
    def value(record, key):
        for part in key.split("."):
            record = record.get(part) if isinstance(record, dict) else None
        return record

    return [f"{k}: {value(before, k)!r} -> {value(now, k)!r}" for k in changed_keys(before, now)]


def normalised(obj):
    """A JSON round trip (tuples → lists, paths → str), as an identity is recorded on disk."""
    return json.loads(canonical(obj))


# ---- the done-check ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Decision:
    """The done-check's answer (module docstring): ``action`` is ``reuse``, ``resume``, ``redo`` or ``new``;
    ``reason`` says why a redo (``changed: guidance.iterations``, ``resume=false``, ...)."""

    action: str
    reason: str | None = None

    @property
    def reuse(self) -> bool:
        return self.action == "reuse"

    @property
    def fresh(self) -> bool:
        """Redo from scratch: what is there was made with other inputs (or unknown ones)."""
        return self.action == "redo"


def done_check(before: dict | None, now: dict, *, present: bool, finished: bool = False, resume: bool = True,
               unknown: str = "its outputs have no fingerprint") -> Decision:
    """Already done with the same inputs? ``before``: the identity recorded with the outputs (None: none),
    ``now``: this run's; ``present``: outputs of some run are there; ``finished``: they are complete; ``resume``:
    False redoes what is there; ``unknown``: the reason when outputs are there without an identity."""
    if not present:
        return Decision("new")
    if not resume:
        return Decision("redo", "resume=false")
    if not isinstance(before, dict):
        return Decision("redo", unknown)
    changed = identity_changes(before, now)
    if changed:
        return Decision("redo", f"changed: {', '.join(changed)}")
    return Decision("reuse" if finished else "resume")


def identity_changes(before: dict, now: dict) -> list[str]:
    """The done-check's comparison (:func:`done_check`): the dotted keys in which the identity ``before`` (recorded,
    read in today's spelling by :func:`upgraded`) differs from ``now``, where the inputs lie left out (:data:`WHERE`:
    the data's content is its own key, so a moved or copied dataset resumes). A sampling ``device`` an earlier
    version recorded as ``auto`` matches the device this run records: the record does not say where it ran (in the
    process, or on Ray's workers, which see no GPU unless given one)."""
    now = normalised(now)
    return [k for k in changed_keys(auto_as_now(upgraded(before), now), now) if not says_where(k)]


def says_where(key: str) -> bool:
    """Whether the dotted identity key says where an input lies, not what it is (:data:`WHERE`, :data:`WHERE_PATHS`)."""
    return key.split(".")[0] in WHERE or any(key == p or key.startswith(p + ".") for p in WHERE_PATHS)


def auto_as_now(before, now):
    """``before`` with each ``sampling.device: auto`` it holds given ``now``'s device at the same place."""
    if not isinstance(before, dict) or not isinstance(now, dict):
        return before
    out = {}
    for key, value in before.items():
        other = now.get(key)
        if key == "sampling" and isinstance(value, dict) and isinstance(other, dict) and value.get("device") == "auto" \
                and isinstance(other.get("device"), str):
            value = {**value, "device": other["device"]}
        out[key] = auto_as_now(value, other)
    return out


def upgraded(record: dict) -> dict:
    """An identity recorded by an earlier version in today's spelling, normalised, so that what it recorded is
    compared, not how, wherever the part sits (a stage's inputs nest identities): a disabled FID's other settings,
    which change nothing, dropped; guidance settings its mode does not read dropped; a ``protocol.metrics`` list as
    a set in the registry's order; a sampling ``device`` recorded as asked — ``cuda:N`` as ``cuda``; ``auto`` is kept
    as written (where such a run sampled is not known: the done-check lets it match this run's,
    :func:`identity_changes`)."""
    def walk(node):
        if not isinstance(node, dict):
            return node
        out = {}
        for key, value in node.items():
            if key == "fid" and isinstance(value, dict) and value.get("enabled") is False:
                value = {"enabled": False}
            elif key == "protocol" and isinstance(value, dict) and isinstance(value.get("metrics"), list):
                value = {**value, "metrics": metric_set(value["metrics"])}
            elif key == "sampling" and isinstance(value, dict) and isinstance(value.get("device"), str):
                device = value["device"]
                value = {**value, "device": "cuda" if device.startswith("cuda:") else device}
            elif key == "guidance" and isinstance(value, dict) and isinstance(value.get("mode"), str):
                from spread.guidance.config import without_unread

                value = without_unread(value)  # recorded before the settings a mode does not read were left out
            out[key] = walk(value)
        return out

    return walk(normalised(record))


def metric_set(names: list) -> list:
    """A recorded ``protocol.metrics`` as :class:`~spread.evaluation.EvalProtocol` now spells it: a set, in the
    registry's order (an evaluation recorded ``[grecall, col_mesh]`` as given)."""
    from spread.metrics.registry import METRICS

    rank = {name: i for i, name in enumerate(METRICS.names())}
    return sorted(names, key=lambda name: rank.get(name, len(rank)) if isinstance(name, str) else len(rank))


def auto_device() -> str:
    """What ``device=auto`` resolves to in this process: ``cuda`` when it sees a GPU, else ``cpu``."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


# ---- identities ----------------------------------------------------------------------------------------------

#: Sampling settings added after runs were recorded: spelled in an identity only where they differ from these
#: defaults (so the runs made before keep their fingerprints), and filled back in by :func:`settings` (so a table
#: still sees them differ). precision: "bf16" changes the numbers; geometry_scale: classifier-free guidance on the
#: geometry features (:class:`~spread.sampling.SamplingConfig`); graphs_over_limit: the split's graphs a run leaves out
#: for its object limit (``max_objects``; none at the default limit on most data).
SAMPLING_DEFAULTS = {"precision": "32", "geometry_scale": 1.0, "graphs_over_limit": []}


def unspelled_defaults_dropped(values: dict) -> dict:
    """``values`` without the :data:`SAMPLING_DEFAULTS` they hold at their defaults (compared as the default's
    type: a recorded ``geometry_scale: 1`` is the default 1.0)."""
    def at_default(key, value) -> bool:
        default = SAMPLING_DEFAULTS[key]
        try:
            return type(default)(value) == default
        except (TypeError, ValueError):
            return False

    return {k: v for k, v in values.items() if not (k in SAMPLING_DEFAULTS and at_default(k, v))}


#: Training settings added after runs were recorded (dotted keys of a composed ``spread-train`` config): left out of a
#: training identity where they hold these defaults, so the stages and points trained before keep their identities.
#: data.max_objects: the object limit of the training rooms (null: none).
TRAINING_DEFAULTS = {"data.max_objects": None}


def training_config_identity(config: dict) -> dict:
    """A composed ``spread-train`` config (a plain dict) as a training identity holds it: without the
    :data:`TRAINING_DEFAULTS` it holds at their defaults (a copy; ``config`` is left as it was)."""
    out = dict(config)
    for dotted, default in TRAINING_DEFAULTS.items():
        section, _, key = dotted.rpartition(".")
        node = out.get(section)
        if isinstance(node, dict) and key in node and node[key] == default:
            out[section] = {k: v for k, v in node.items() if k != key}
    return out


def init_weights_digest(config: dict) -> str | None:
    """The content of the weights a composed ``spread-train`` config (a plain dict) starts from (``model.init_from``;
    None when it names none): other weights at the same path are another training. Taken when a training is
    planned and recorded with it (a training stage's inputs, a sweep point's identity), never recomputed from the
    file as it is later."""
    model = config.get("model")
    if isinstance(model, dict) and isinstance(model.get("init_from"), str) and model["init_from"]:
        return file_digest(model["init_from"])
    return None


def unread_sampling(ckpt) -> dict:
    """The sampling settings the method of checkpoint ``ckpt`` does not read, with the values its runs record
    (:attr:`spread.methods.registry.MethodSpec.ignores`); {} when the file does not load here (the run
    refuses it in its own words) or its method reads them all. The checkpoint is read once per process
    (:func:`spread.readonce.checkpoint`)."""
    from spread import readonce
    from spread.methods import checkpoint_method, method_spec

    try:
        checkpoint = readonce.checkpoint(ckpt)
        return method_spec(checkpoint_method(checkpoint.get("hyper_parameters") or {})).ignores.copy()
    except (OSError, ValueError, RuntimeError):
        return {}


def sampler_label(ckpt, sampler) -> str:
    """What samples with checkpoint ``ckpt``: the :class:`~spread.model.Sampler`'s label, or what its method's own
    loop records instead (:func:`unread_sampling`: ATISS's ``"one pass per object"``) — the one label of the
    run's ``sampling.json``, its scenes' provenance and its tracker tags."""
    return str(unread_sampling(ckpt).get("sampler", sampler.label))


def guidance_run(ckpt, guidance):
    """The guidance that runs when checkpoint ``ckpt`` samples with ``guidance``: its method's own realisation of the
    mode (:attr:`spread.methods.registry.MethodSpec.guidance_modes`: the authors' network runs ``paper`` as
    ``release``), else ``guidance`` — the one guidance of the run's identity, ``sampling.json`` and tracker tags."""
    from spread import readonce
    from spread.methods import checkpoint_method, method_spec

    if not getattr(guidance, "active", False):
        return guidance
    try:
        checkpoint = readonce.checkpoint(ckpt)
        spec = method_spec(checkpoint_method(checkpoint.get("hyper_parameters") or {}))
    except (OSError, ValueError, RuntimeError):
        return guidance
    return spec.guidance_run(guidance)


def sampling_identity(cfg) -> dict:
    """What a generated scene file depends on (module docstring); ``cfg``: a typed
    :class:`~spread.sampling.SamplingConfig` (its ``sampler`` a Sampler, its ``guidance`` a GuidanceConfig).
    ``samples_per_graph`` is not part of it (more samples only add files); ``data_root`` says where the data
    lies (``spread-view`` reads it). A setting the checkpoint's method does not read holds the value its runs record
    (:func:`unread_sampling`: ATISS's ``sampler`` is ``"one pass per object"``), and the guidance is the one that
    runs (:func:`guidance_run`: the authors' network's ``paper`` is ``release``)."""
    unread = unread_sampling(cfg.ckpt)
    return {"ckpt_sha256": file_digest(cfg.ckpt), "data": dataset_digest(cfg.data.root, [cfg.data.split]),
            "data_root": str(Path(str(cfg.data.root)).resolve()), "split": str(cfg.data.split),
            "sampling": {"sampler": unread.get("sampler", cfg.sampler.fingerprint()), "seed": int(cfg.seed),
                         "batch_size": int(cfg.batch_size), "use_ema": bool(cfg.use_ema),
                         "graph_scale": float(unread.get("graph_scale", cfg.graph_scale)),
                         "device": cfg.sampling_device() if hasattr(cfg, "sampling_device") else str(cfg.device),
                         **unspelled_defaults_dropped({
                             "precision": str(unread.get("precision", getattr(cfg, "precision", "32"))),
                             "geometry_scale": float(getattr(cfg, "geometry_scale", 1.0)),
                             "graphs_over_limit": left_out(cfg.graphs_over_limit() if hasattr(cfg, "graphs_over_limit")
                                                           else [])})},
            "guidance": guidance_run(cfg.ckpt, cfg.guidance).fingerprint(), "numbers_version": NUMBERS_VERSION}


#: Most names an identity lists of what a run leaves out; more are spelled by count and digest (an identity travels as
#: a tracker's tag: MLflow cuts a tag at 8,000 characters, and 800 scene ids made it invalid JSON).
NAMES_LISTED = 16


def left_out(names) -> list[str] | str:
    """The sorted ``names`` a run leaves out (graphs, scenes over its object limit), as an identity spells them: the
    list, or above :data:`NAMES_LISTED` ``"<n> names, sha256 <16 hex>"`` (the same set, the same text)."""
    names = sorted(str(n) for n in names)
    if len(names) <= NAMES_LISTED:
        return names
    return f"{len(names)} names, sha256 {hashlib.sha256(json.dumps(names).encode()).hexdigest()[:16]}"


def evaluation_identity(protocol, fid, assets) -> dict:
    """What an evaluation's per-scene line depends on besides its scene file (whose sha256 each line carries):
    the typed protocol's and FID settings' fingerprints, the asset library's index (``assets``: its folder) and
    :data:`NUMBERS_VERSION`."""
    return {"protocol": protocol.fingerprint(), "fid": fid.fingerprint(),
            "assets_sha256": file_digest(Path(str(assets)) / "index.json"), "numbers_version": NUMBERS_VERSION}


def measured_identity(metrics: dict) -> dict | None:
    """What an evaluation's numbers were measured with, as its ``metrics.json`` records it: the scenes' sampling
    identity (``sampled_with``, samples per graph included) and the evaluation's (``evaluated_with``, under
    ``evaluation``), in a sweep point's shape; None when it records neither (an earlier version's). The trackers
    carry it beside the numbers (wandb config ``spread_identity``, MLflow tag ``spread.identity``), so a report of
    tracker records names the checkpoint and data as a report of the folder does."""
    out: dict = {}
    if isinstance(metrics.get("sampled_with"), dict):
        out |= metrics["sampled_with"]
    recorded = metrics.get("evaluated_with")
    if isinstance(recorded, dict) and isinstance(recorded.get("protocol"), dict):
        out["evaluation"] = recorded
    return out or None


def tracked_identity(value) -> dict | None:
    """A :func:`measured_identity` as a tracker gives it back (a dict, or its JSON text), else None."""
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            return None
    return value if isinstance(value, dict) and value else None


def point_identity(command) -> dict:
    """A ``spread-sample`` run's identity (a sweep point's; ``command``: the typed ``SampleCommand``): its
    :func:`sampling_identity`, ``samples_per_graph`` and, with ``evaluate``, the :func:`evaluation_identity` with
    the reference split and its content."""
    evaluation = None
    if command.evaluate:
        ev, root = command.evaluation, Path(str(command.data.root))
        evaluation = {**evaluation_identity(ev.protocol, ev.fid, root / "assets"),
                      "reference_split": str(ev.reference_split), "reference": tree_digest(root / ev.reference_split)}
    return {**sampling_identity(command), "samples_per_graph": int(command.samples_per_graph), "evaluation": evaluation}


def typed_command(cfg):
    """A composed ``spread-sample`` config (a ``DictConfig``, Hydra's root too) as its typed record, parsed once
    here at the boundary (``out_dir`` is not read: it may be named after this identity)."""
    import copy

    from omegaconf import DictConfig, OmegaConf, open_dict

    if not isinstance(cfg, DictConfig):
        return cfg
    node = copy.deepcopy(cfg)
    with open_dict(node):
        node.pop("hydra", None)
        node.out_dir = "."
    return OmegaConf.to_object(node)


def point_fingerprint(cfg) -> dict:
    """:func:`point_identity` of a ``spread-sample`` config (typed, or a composed ``DictConfig``)."""
    return normalised(point_identity(typed_command(cfg)))


def point_short(*, _root_) -> str:
    """OmegaConf resolver ``${point_fp:}``: the short point fingerprint of the config it sits in."""
    return short(point_fingerprint(_root_))


def point_dir(values: str, *, _root_) -> str:
    """OmegaConf resolver ``${point_dir:<sweep folder>/<values>}``: the run folder of the config it sits in,
    ``<values>_<short fingerprint>`` or the folder beside it that holds the same setting (:func:`point_folder`)."""
    fingerprint = point_fingerprint(_root_)
    return str(point_folder(Path(f"{values}_{short(fingerprint)}"), fingerprint))


#: A sweep point's record (``spread.experiments.points``): its fingerprint, short name, status, tags.
POINT = "point.json"


def read_point_record(out_dir) -> dict | None:
    """A folder's ``point.json`` (None: none, or not a readable JSON object)."""
    from spread.io import read_json

    try:
        data = read_json(Path(out_dir) / POINT)
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def point_folder(folder, fingerprint: dict) -> Path:
    """Where a point with ``fingerprint`` lives: ``folder`` (``<values>_<short fingerprint>``), or a folder beside it
    whose ``point.json`` records this very setting by the done-check (:func:`done_check`) — one with the same short
    fingerprint reached through another spelling of the sweep (a swept key kept to one value, a key left at its
    default), or one with the same values named by an earlier version's short fingerprint (one that held where the
    data lay, or the device as asked) — re-used rather than made again under a second name."""
    folder = Path(folder)
    if folder.exists() or not folder.parent.is_dir():
        return folder
    wanted = normalised(fingerprint)
    values, short_name = folder.name.rsplit("_", 1) if "_" in folder.name else ("", folder.name)
    for other in sorted(folder.parent.iterdir()):
        if not other.is_dir() or not (other.name.endswith(f"_{short_name}") or other.name.rsplit("_", 1)[0] == values):
            continue
        record = read_point_record(other)
        if record is None or not isinstance(record.get("fingerprint"), dict):
            continue
        if not done_check(record["fingerprint"], wanted, present=True).fresh:
            return other
    return folder


# ---- what reports name per run --------------------------------------------------------------------------------

#: Identity keys that say where, not what (left out of :func:`settings`).
WHERE = ("data_root",)
#: Dotted identity keys that say where, deeper in: a training sweep point's data folder (its content is the point's
#: ``data`` digest: a moved or copied dataset is the same point).
WHERE_PATHS = ("config.data.root",)


def sampler_setting(value):
    """A recorded sampler as :func:`settings` shows it: a fingerprint (dict) or a sampler's name (an older record's
    string) as its label; any other string as it is (what an own loop records: ATISS's ``"one pass per object"``)."""
    from spread.model.sampler import Sampler

    if isinstance(value, (dict, str)):
        try:
            return Sampler.from_config(value).label
        except (TypeError, ValueError):
            pass
    return value


def settings(identity: dict) -> dict:
    """The flat, readable settings of an identity (module docstring): ``guidance.mode`` and, for every registered
    guidance term, ``guidance.<term>`` (its λ; 0 where it does not act), every other guidance setting of a guided
    run as ``guidance.<key>``, ``sampler`` (its label), the other sampling settings by name, ``ckpt``, ``data``,
    ``assets`` and ``reference`` (12 hex digits of their sha256), ``protocol.<key>`` and ``fid.<key>``, ...; an
    identity that lacks a part (a run recorded before it) gives none of its keys."""
    from spread.guidance.terms import term_names
    from spread.model.sampler import Sampler

    out: dict = {}
    if "guidance" in identity:
        guidance = identity["guidance"] or {"mode": "none"}
        out["guidance.mode"] = guidance.get("mode", "none")
        out |= {f"guidance.{name}": 0.0 for name in term_names()}
        out |= {f"guidance.{k}": v for k, v in guidance.items() if k != "mode" and
                (guidance["mode"] != "none" or k in out)}
    for key, value in identity.items():
        if key in ("guidance", *WHERE):
            continue
        if key == "sampling" and isinstance(value, dict):
            for k, v in {**SAMPLING_DEFAULTS, **value}.items():
                out[k] = sampler_setting(v) if k == "sampler" else v
        elif key == "evaluation" and isinstance(value, dict):
            for k, v in value.items():
                if k in ("protocol", "fid") and isinstance(v, dict):
                    out |= {f"{k}.{f}": w for f, w in v.items()}
                elif k in ("assets_sha256", "reference"):
                    out[k.removesuffix("_sha256")] = str(v)[:12]
                else:
                    out[k] = v
        elif key in ("ckpt_sha256", "data"):
            out[key.removesuffix("_sha256")] = str(value)[:12]
        elif not isinstance(value, dict):
            out[key] = value
    return {k: (",".join(map(str, v)) or "none") if isinstance(v, list) else v for k, v in out.items()}


def unflatten(config: dict) -> dict:
    """``{"a.b": 1}`` (a wandb sweep's flat keys) as ``{"a": {"b": 1}}``; nested keys are kept."""
    out: dict = {}
    for key, value in (config or {}).items():
        node = out
        parts = str(key).split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {}) if isinstance(node.get(part, {}), dict) else {}
        if isinstance(value, dict) and isinstance(node.get(parts[-1]), dict):
            node[parts[-1]] = {**node[parts[-1]], **unflatten(value)}
        else:
            node[parts[-1]] = unflatten(value) if isinstance(value, dict) else value
    return out


def config_identity(config: dict) -> dict:
    """The identity parts a run's recorded config gives (``.hydra/config.yaml``, a wandb run's config; flat dotted
    keys too), each setting parsed once into its typed record: ``guidance`` (a
    :class:`~spread.guidance.GuidanceConfig`'s fingerprint), ``sampling`` (the :class:`~spread.model.Sampler`'s,
    seed, ...), ``samples_per_graph``, the evaluation protocol. For runs recorded without fingerprints."""
    from spread.guidance import GuidanceConfig
    from spread.model.sampler import Sampler

    tree = unflatten(config)
    out: dict = {}
    if isinstance(tree.get("guidance"), (dict, str)):
        out["guidance"] = GuidanceConfig.from_config(tree["guidance"]).fingerprint()
    sampling = {k: tree[k] for k in ("seed", "batch_size", "use_ema", "graph_scale", "device", *SAMPLING_DEFAULTS)
                if k in tree and ("ckpt" in tree or "sampler" in tree)}  # a sampling run's (not an evaluation's seed)
    sampling = unspelled_defaults_dropped(sampling)
    if isinstance(tree.get("sampler"), (dict, str)):
        sampling["sampler"] = Sampler.from_config(tree["sampler"]).fingerprint()
    if sampling:
        out["sampling"] = sampling
    if "samples_per_graph" in tree:
        out["samples_per_graph"] = tree["samples_per_graph"]
    protocol = (tree.get("evaluation") or {}).get("protocol") if isinstance(tree.get("evaluation"), dict) \
        else tree.get("protocol")
    if isinstance(protocol, dict):
        out["evaluation"] = {"protocol": protocol}
    return out


def differing(rows: list[dict]) -> list[str]:
    """The settings keys (of :func:`settings` dicts) that take more than one value over ``rows``, values a row
    lacks not counted, in the first row's order then first appearance."""
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    return [k for k in keys if len({canonical(r[k]) for r in rows if r.get(k) is not None}) > 1]


@functools.cache
def git_sha() -> str | None:
    """The checkout's commit (None outside a git checkout or without git); read once per process."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def run_tags() -> dict:
    """Where this run ran: SLURM job id (array task too), world size, node list, host, git SHA."""
    env = os.environ
    job = env.get("SLURM_JOB_ID") or env.get("SPREAD_JOB_ID")
    if job and env.get("SLURM_ARRAY_TASK_ID"):
        job = f"{env.get('SLURM_ARRAY_JOB_ID', job)}_{env['SLURM_ARRAY_TASK_ID']}"
    world = env.get("WORLD_SIZE") or env.get("SLURM_NTASKS")
    return {"job_id": job, "world_size": int(world) if world and world.isdigit() else 1,
            "node_list": env.get("SLURM_JOB_NODELIST") or env.get("SLURM_NODELIST") or socket.gethostname(),
            "host": socket.gethostname(), "git_sha": git_sha()}


@functools.cache
def launch_id() -> str:
    """``<UTC time>_<host>_<pid>``: two launches into one sweep folder never share their launch records."""
    import time

    return f"{time.strftime('%Y-%m-%d_%H-%M-%S', time.gmtime())}_{socket.gethostname()}_{os.getpid()}"
