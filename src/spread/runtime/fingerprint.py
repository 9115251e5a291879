"""Fingerprints of results: what a sampled-and-evaluated number depends on, so that a result is re-used only
when everything it was made from is the same (a re-launched sweep never reports old numbers as new ones).

A **point fingerprint** (:func:`point_fingerprint`) is a plain dict over a ``spread-sample`` config:

* ``ckpt_sha256`` — the checkpoint's bytes (hashed once per process while the file is unchanged: :mod:`spread.readonce`);
* ``data`` — the dataset's content: the sha256 of every scene file of the conditioning split and of the
  evaluation's reference split, of ``assets/index.json`` and ``stats.json`` (:func:`dataset_digest`);
* ``sampling`` — sampler, seed, batch size, samples per graph, EMA, graph scale, device, split;
* ``guidance`` — every guidance setting when guidance is on (``None`` when it is off: weights of an unguided
  run change nothing);
* ``evaluation`` — ``evaluate``, the protocol, the FID settings and the reference split;
* ``numbers_version`` — :data:`NUMBERS_VERSION`, bumped by a code change that changes scenes or metrics.

:func:`short` is its 8-hex-digit name (sweep point folders end with it, so two settings never share a
folder); :func:`changed_keys` names what differs (the reason recorded when a point is redone).
:func:`run_tags` are the facts of where a run ran (job id, world size, node list, git SHA), recorded
beside results but never compared. Units: none; all digests are hex sha256.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import socket
import subprocess
from pathlib import Path

#: Bump when a code change changes sampled scenes or metrics (every earlier result is then redone).
NUMBERS_VERSION = 1


def canonical(obj) -> str:
    """One JSON text per value (sorted keys, paths and tuples as JSON sees them)."""
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))


def digest(obj) -> str:
    return hashlib.sha256(canonical(obj).encode()).hexdigest()


def short(fingerprint: dict, n: int = 8) -> str:
    """The fingerprint's short name (first ``n`` hex digits of its sha256)."""
    return digest(fingerprint)[:n]


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


def dataset_digest(root, splits) -> str:
    """The content of a dataset folder as far as a run reads it: the splits' scene files, the asset index and
    the normalisation statistics."""
    root = Path(str(root))
    parts = {f"split:{s}": tree_digest(root / s) for s in sorted({str(s) for s in splits if s})}
    parts["assets"] = file_digest(root / "assets" / "index.json")
    parts["stats"] = file_digest(root / "stats.json")
    return digest(parts)


def changed_keys(before: dict, now: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ (nested dicts compared key by key)."""
    out = []
    for k in sorted(set(before) | set(now)):
        a, b = before.get(k), now.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += changed_keys(a, b, f"{prefix}{k}.")
        elif canonical(a) != canonical(b):
            out.append(f"{prefix}{k}")
    return out


def _plain(node):
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


def _get(cfg, dotted: str, default=None):
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        node = OmegaConf.select(cfg, dotted, default=None, throw_on_missing=False)
        return default if node is None or node == "???" else _plain(node)
    node = cfg
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
        if node is None:
            return default
    return node


def point_fingerprint(cfg) -> dict:
    """The fingerprint (module docstring) of a ``spread-sample`` config (a ``DictConfig``, Hydra's root too,
    or a plain dict of the same keys)."""
    guidance = _get(cfg, "guidance") or {}
    if isinstance(guidance, str):
        guidance = {"mode": guidance}
    weights = [float(guidance.get(k, 0) or 0) for k in ("collision", "gravity", "relation")]
    guided = guidance.get("mode", "none") != "none" and any(w > 0 for w in weights)
    split = _get(cfg, "data.split", "test")
    evaluate = bool(_get(cfg, "evaluate", False))
    reference = _get(cfg, "evaluation.reference_split", split) if evaluate else None
    root = _get(cfg, "data.root")
    return {
        "ckpt_sha256": file_digest(_get(cfg, "ckpt")),
        "data": dataset_digest(root, [split, reference]) if root else None,
        "sampling": {"sampler": _get(cfg, "sampler"), "seed": _get(cfg, "seed"), "batch_size": _get(cfg, "batch_size"),
                     "samples_per_graph": _get(cfg, "samples_per_graph"), "use_ema": _get(cfg, "use_ema"),
                     "graph_scale": _get(cfg, "graph_scale"), "device": _get(cfg, "device"), "split": split,
                     # bf16 sampling changes the numbers (float32, the default, keeps older fingerprints)
                     **({"precision": str(_get(cfg, "precision"))} if str(_get(cfg, "precision", "32")) != "32" else {})},
        "guidance": guidance if guided else None,
        "evaluation": {"evaluate": evaluate, "reference_split": reference,
                       "protocol": _get(cfg, "evaluation.protocol") if evaluate else None,
                       "fid": _get(cfg, "evaluation.fid") if evaluate else None},
        "numbers_version": NUMBERS_VERSION,
    }


def point_short(*, _root_) -> str:
    """OmegaConf resolver ``${point_fp:}``: the short point fingerprint of the config it sits in."""
    return short(point_fingerprint(_root_))


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


def register_resolvers() -> None:
    """``${point_fp:}`` (the short point fingerprint), ``${launch_id:}`` (unique per launching process) and
    ``${wandb_mode:}`` (:func:`spread.runtime.logger_config.wandb_mode`)."""
    from omegaconf import OmegaConf

    from spread.runtime.logger_config import wandb_mode

    if not OmegaConf.has_resolver("point_fp"):
        OmegaConf.register_new_resolver("point_fp", point_short, use_cache=False)
    if not OmegaConf.has_resolver("launch_id"):
        OmegaConf.register_new_resolver("launch_id", launch_id)
    if not OmegaConf.has_resolver("wandb_mode"):
        OmegaConf.register_new_resolver("wandb_mode", wandb_mode, use_cache=False)


@functools.cache
def launch_id() -> str:
    """``<UTC time>_<host>_<pid>``: two launches into one sweep folder never share their launch records."""
    import time

    return f"{time.strftime('%Y-%m-%d_%H-%M-%S', time.gmtime())}_{socket.gethostname()}_{os.getpid()}"
