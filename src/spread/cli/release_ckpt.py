"""``spread-release-ckpt ckpt=PATH [use_ema=true] [out=PATH] [model.<key>=VALUE ...]``: load the SPREAD
authors' ``ckpt.pth`` into the release's network (``experiment=release``: conf/model/release.yaml, whose keys
``model.*=`` overrides change, e.g. ``model.bounds=[...]``) and report it; refuses a file whose weights do not
fit, naming the keys, and one whose weights are not finite numbers, not tensors, or under other keys than
weight names (:func:`check_release_weights`), in one line. With ``out=``, also write a platform checkpoint of
:class:`~spread.methods.release.ReleaseDiffusion` (``{"hyper_parameters": {"method": "release", ...},
"state_dict", "datamodule_hyper_parameters"}``, loadable with ``weights_only=True``) that ``spread-sample
ckpt=OUT`` samples and ``spread-evaluate`` scores.

Refused in one line before anything is read or written: an ``out=`` that is the checkpoint itself (under any
spelling: a symbolic link, ``..``, a hard link), an existing folder or a path through a file
(:func:`out_problem`); a ``model.*`` override that names no key or does not parse (Hydra's composition error),
or whose value the network cannot be built with (:func:`check_model`: ``model.config.attn_dim=abc``,
``model.bounds=[nan,0,0,1,1,1]``)."""

from __future__ import annotations

import sys


def parse(argv: list[str]) -> dict:
    """``key=value`` arguments: ``ckpt`` (required), ``use_ema`` (default true), ``out``, ``model.*`` overrides."""
    args = {"use_ema": "true", "out": None, "overrides": []}
    if any(a in ("-h", "--help") for a in argv):  # the usage, as spread-view and the Hydra commands print theirs
        print(__doc__.strip())
        raise SystemExit(0)
    for arg in argv:
        key, sep, value = arg.partition("=")
        if sep and key.startswith("model."):
            args["overrides"].append(arg)
            continue
        if not sep or key not in ("ckpt", "use_ema", "out"):
            raise SystemExit(f"spread-release-ckpt: unknown argument {arg!r} (usage: ckpt=PATH [use_ema=true|false] "
                             f"[out=PATH] [model.<key>=VALUE ...])")
        args[key] = value
    if "ckpt" not in args:
        raise SystemExit("spread-release-ckpt: ckpt=PATH is required (the release's ckpt.pth)")
    if args["use_ema"].lower() not in ("true", "false"):
        raise SystemExit(f"spread-release-ckpt: use_ema={args['use_ema']!r}: expected true or false")
    args["use_ema"] = args["use_ema"].lower() == "true"
    return args


def model_hparams(overrides: list[str]) -> dict:
    """``experiment=release``'s model keys (no ``_target_``), with ``model.*`` overrides, checked
    (:func:`check_model`). ``ValueError`` naming an override of a key the model does not have (:func:`check_key`)
    or one that does not parse; Hydra's composition error for one it cannot apply otherwise (both user errors:
    :func:`spread.cli.errors.user_error_types`)."""
    from hydra.errors import OverrideParseException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from spread.configs import compose

    overrides = list(overrides)
    for override in overrides:
        check_key(override.partition("=")[0], override)
    try:
        cfg = compose("train", ["experiment=release", "data.root=/unused", *overrides])
    except OverrideParseException as exc:  # Hydra's message does not name the override
        raise ValueError(f"{exc.override}: {str(exc.message).strip().splitlines()[0]} (override grammar: "
                         f"https://hydra.cc/docs/advanced/override_grammar/basic)") from None
    try:
        model = OmegaConf.to_container(cfg.model, resolve=True)
    except OmegaConfBaseException as exc:  # an interpolation in an override that does not resolve
        key = getattr(exc, "full_key", None) or "model"
        raise ValueError(f"{shown(key, '?', overrides)}: {str(exc).strip().splitlines()[0]}") from None
    hp = {k: v for k, v in model.items() if not k.startswith("_")}
    check_model(hp, overrides)
    return hp


#: the keys of conf/model/release.yaml a ``model.<key>=`` override may set (``config`` through its own keys)
MODEL_KEYS = ("bounds", "config", "method", "weights")


def check_key(key: str, override: str) -> None:
    """``ValueError`` naming an override of a ``model.`` key the release's model does not have (Hydra's own error
    would suggest ``+model...``, which adds a key the network has no use for)."""
    import dataclasses

    from spread.methods.release_network import ReleaseNetworkConfig

    parts = key.split(".")
    if len(parts) >= 2 and parts[1] not in MODEL_KEYS:
        raise ValueError(f"{override}: the release's model has no key {parts[1]!r} (known: "
                         f"{', '.join(f'model.{k}' for k in MODEL_KEYS)}, model.config.<key>)")
    if len(parts) >= 3 and parts[1] == "config":
        known = sorted([*(f.name for f in dataclasses.fields(ReleaseNetworkConfig)), "num_points"])
        if parts[2] not in known:
            raise ValueError(f"{override}: the release's network has no setting {parts[2]!r} (known: "
                             f"{', '.join(known)})")


#: ``model.config.*`` keys that may be 0 (a count of layers); every other whole-number size is at least 1
MAY_BE_ZERO = {"self_per_cross"}


def shown(key: str, value, overrides: list[str]) -> str:
    """``key=value`` as the user typed it (the last override of ``key``), else as composed."""
    typed = [o.partition("=")[2] for o in overrides if o.partition("=")[0] == key]
    return f"{key}={typed[-1] if typed else value}"


def check_model(hp: dict, overrides: list[str] = ()) -> None:
    """``ValueError`` in one line naming the ``model.*`` key and value the release's network cannot be built with:
    a ``config`` key it does not have, a size that is not a whole number ≥ 1, a dropout outside [0, 1), a
    ``bounds`` that is not 6 finite numbers with each max above its min, another ``method``."""
    import dataclasses
    import math

    from spread.checks import is_whole
    from spread.methods.release_network import ReleaseNetworkConfig

    overrides = list(overrides)
    if hp.get("method", "release") != "release":
        raise ValueError(f"{shown('model.method', hp.get('method'), overrides)}: this command converts the "
                         f"release's network only (method 'release')")
    config = hp.get("config")
    if not isinstance(config, dict):
        raise ValueError(f"{shown('model.config', config, overrides)}: expected the network's settings "
                         f"(model.config.<key>=VALUE)")
    fields = {f.name: f for f in dataclasses.fields(ReleaseNetworkConfig)}
    for key, value in config.items():
        name = f"model.config.{key}"
        if key != "num_points" and key not in fields:
            raise ValueError(f"{shown(name, value, overrides)}: the release's network has no setting {key!r} "
                             f"(known: {', '.join(sorted([*fields, 'num_points']))})")
        kind = "float" if key != "num_points" and fields[key].type in (float, "float") else "int"
        if kind == "int":
            least = 0 if key in MAY_BE_ZERO else 1
            if not is_whole(value) or value < least:
                raise ValueError(f"{shown(name, value, overrides)}: expected a whole number ≥ {least}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or \
                not (0 <= value < 1 if key == "dropout" else value > 0):
            raise ValueError(f"{shown(name, value, overrides)}: expected "
                             + ("a number in [0, 1)" if key == "dropout" else "a finite number > 0"))
    heads, width = config.get("n_heads"), config.get("attn_dim")
    if isinstance(heads, int) and isinstance(width, int) and width % heads:
        raise ValueError(f"{shown('model.config.n_heads', heads, overrides)} does not divide "
                         f"{shown('model.config.attn_dim', width, overrides)} (the attention's heads split its width)")
    bounds = hp.get("bounds")
    numbers = isinstance(bounds, (list, tuple)) and len(bounds) == 6 and all(
        isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds)
    if not numbers or not all(hi > lo for lo, hi in zip(bounds[:3], bounds[3:])):
        raise ValueError(f"{shown('model.bounds', bounds, overrides)}: expected 6 finite numbers [min x, y, z, "
                         f"max x, y, z] (metres), each max above its min")


def out_problem(ckpt: str, out: str) -> str | None:
    """Why ``out=`` cannot take the converted checkpoint, or None: it is ``ckpt`` itself (any spelling of the path,
    a symbolic or hard link: converting would replace the authors' weights), an existing folder or other
    non-file, or a path through a file."""
    import os
    from pathlib import Path

    src, dst = Path(ckpt).expanduser(), Path(out).expanduser()
    same = dst.resolve() == src.resolve()
    if not same and dst.exists() and src.exists():
        try:
            same = os.path.samefile(dst, src)
        except OSError:
            same = False
    if same:
        return (f"out={out} is the checkpoint being converted (ckpt={ckpt}); writing it would replace the authors' "
                f"weights: give another out= path")
    if dst.is_dir():
        return f"out={out}: is a folder; give a file path (e.g. out={dst / 'release.ckpt'})"
    if dst.exists() and not dst.is_file():
        return f"out={out}: exists and is not a regular file; give another path"
    parent = dst.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"out={out}: {parent} is not a folder, so the file cannot be written there"
    return None


def convert(ckpt: str, out: str, use_ema: bool = True, overrides: list[str] = ()) -> "object":
    """Write the platform checkpoint of ``ckpt`` at ``out`` (atomically); returns the ReleaseDiffusion."""
    from pathlib import Path

    import torch

    from spread.io import atomic_path
    from spread.methods.release_network import load_release_checkpoint
    from spread.methods.release import ReleaseDiffusion

    hp = model_hparams(list(overrides))
    hp.update(weights="ema" if use_ema else "raw", source=str(ckpt))
    module = ReleaseDiffusion(**hp)
    net = load_release_checkpoint(ckpt, module.network.config, use_ema=use_ema)
    module.network.load_state_dict(net.state_dict(), strict=True)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        torch.save({"hyper_parameters": dict(module.hparams), "state_dict": module.state_dict(),
                    "datamodule_hyper_parameters": {"num_points": module.config.num_points, "seed": 0}}, tmp)
    return module


def check_release_weights(path: str, use_ema: bool = True) -> int:
    """The number of weights the release file at ``path`` gives the network, once each is a floating-point tensor
    of finite numbers under a weight name; :class:`~spread.methods.release_network.ReleaseCheckpointError` in one line naming
    the first that is not (``{"model": [1, 2, 3]}``, an int key, an int ``shadow_params``, an all-NaN tensor).
    Read with the platform's loader (weights only, tensors memory-mapped)."""
    import torch

    from spread.methods.release_network import ReleaseCheckpointError, release_state_dict
    from spread.safe_load import load_checkpoint

    ckpt = load_checkpoint(path, mmap=True)
    model = ckpt.get("model")
    if "model" in ckpt and not isinstance(model, dict):
        raise ReleaseCheckpointError(f"{path}: key 'model' holds {type(model).__name__}, expected a dict of weight "
                                     f"name → tensor")
    for key, value in (model or {}).items():
        if not isinstance(key, str):
            raise ReleaseCheckpointError(f"{path}: 'model' has the key {key!r} ({type(key).__name__}); weight names "
                                         f"are strings")
        if not isinstance(value, torch.Tensor):
            raise ReleaseCheckpointError(f"{path}: 'model[{key!r}]' holds {type(value).__name__}, not a tensor")
    ema = ckpt.get("ema_states")
    if use_ema and ema is not None:
        shadow = ema.get("shadow_params") if isinstance(ema, dict) else None
        if not isinstance(ema, dict) or (shadow is not None and not isinstance(shadow, (list, tuple))):
            key, what = ("ema_states.shadow_params", "a list of tensors") if isinstance(ema, dict) else \
                ("ema_states", "a dict")
            held = type(shadow if isinstance(ema, dict) else ema).__name__
            raise ReleaseCheckpointError(f"{path}: '{key}' holds {held}, expected {what}")
        for i, tensor in enumerate(shadow or []):
            if not isinstance(tensor, torch.Tensor):
                raise ReleaseCheckpointError(f"{path}: 'ema_states.shadow_params[{i}]' holds {type(tensor).__name__}, "
                                             f"not a tensor")
    weights = release_state_dict(ckpt, str(path), use_ema)
    from spread.methods.loading import storage_problem

    for name, tensor in weights.items():
        problem = tensor.layout == torch.strided and storage_problem(name, tensor)
        if problem:  # before any op reads it: a meta tensor has no values, an expanded one allocates its full size
            raise ReleaseCheckpointError(f"{path}: {problem}")
        if tensor.layout != torch.strided:  # a sparse or otherwise laid-out tensor: torch's ops on it raise deep down
            raise ReleaseCheckpointError(f"{path}: weight '{name}' is a {str(tensor.layout).removeprefix('torch.')} "
                                         f"tensor, expected a dense one")
        if not tensor.is_floating_point():
            raise ReleaseCheckpointError(f"{path}: weight '{name}' is {tensor.dtype}, expected floating point")
        bad = int((~torch.isfinite(tensor)).sum())
        if bad:
            raise ReleaseCheckpointError(f"{path}: weight '{name}' {tuple(tensor.shape)} holds {bad} of "
                                         f"{tensor.numel()} values that are NaN or infinite "
                                         f"({'EMA' if use_ema else 'raw'} weights); refused")
    return len(weights)


def main(argv: list[str] | None = None) -> None:
    from spread.methods.release_network import ReleaseCheckpointError, load_release_checkpoint
    from spread.safe_load import UnsafeFileError

    args = parse(sys.argv[1:] if argv is None else argv)
    problem = out_problem(args["ckpt"], args["out"]) if args["out"] else None
    if problem:
        raise SystemExit(f"spread-release-ckpt: {problem}")
    try:
        hp = model_hparams(args["overrides"])  # settings first: a bad one is refused before the file is read
        check_release_weights(args["ckpt"], args["use_ema"])
        if args["out"]:
            net = convert(args["ckpt"], args["out"], args["use_ema"], args["overrides"]).network
        else:
            config = {k: v for k, v in hp["config"].items() if k != "num_points"}
            net = load_release_checkpoint(args["ckpt"], config, use_ema=args["use_ema"])
    except (ReleaseCheckpointError, UnsafeFileError, FileNotFoundError) as exc:
        raise SystemExit(f"spread-release-ckpt: {' '.join(str(exc).split())}") from None
    except Exception as exc:  # noqa: BLE001 — only user errors (a bad setting, an unwritable out=) become one line
        from spread.cli.errors import user_error, verbose
        from spread.configs import error_message

        cause = user_error(exc)
        if cause is None or verbose():
            raise
        raise SystemExit(f"spread-release-ckpt: {error_message(cause)}") from None
    c = net.config
    params = sum(p.numel() for p in net.parameters())
    print(f"{args['ckpt']}: the release's network, {'EMA' if args['use_ema'] else 'raw'} weights, {params:,} parameters "
          f"(width {c.attn_dim}, {c.n_layers} blocks, {c.num_latents} × {c.attn_dim} perceiver latents, edge width "
          f"{c.attn_dim // 4}); no missing or unexpected keys")
    if args["out"]:
        print(f"wrote {args['out']} (method 'release'): spread-sample ckpt={args['out']} data.root=<imported dataset> "
              f"out_dir=<dir> sampler=ddpm")


if __name__ == "__main__":
    main()
