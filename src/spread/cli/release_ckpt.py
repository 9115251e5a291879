"""``spread-release-ckpt ckpt=PATH [use_ema=true] [out=PATH] [model.<key>=VALUE ...]``: load the SPREAD
authors' ``ckpt.pth`` into the release's network (``experiment=release``: conf/model/release.yaml, whose keys
``model.*=`` overrides change, e.g. ``model.bounds=[...]``) and report it; refuses a file whose weights do not
fit, naming the keys, and one whose weights are not finite numbers, not tensors, or under other keys than
weight names (:func:`check_release_weights`), in one line. With ``out=``, also write a platform checkpoint of
:class:`~spread.methods.release.ReleaseDiffusion` (``{"hyper_parameters": {"method": "release", ...},
"state_dict", "datamodule_hyper_parameters"}``, loadable with ``weights_only=True``) that ``spread-sample
ckpt=OUT`` samples and ``spread-evaluate`` scores."""

from __future__ import annotations

import sys


def parse(argv: list[str]) -> dict:
    """``key=value`` arguments: ``ckpt`` (required), ``use_ema`` (default true), ``out``, ``model.*`` overrides."""
    args = {"use_ema": "true", "out": None, "overrides": []}
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
    """``experiment=release``'s model keys (no ``_target_``), with ``model.*`` overrides."""
    from omegaconf import OmegaConf

    from spread.configs import compose

    cfg = compose("train", ["experiment=release", "data.root=/unused", *overrides])
    return {k: v for k, v in OmegaConf.to_container(cfg.model, resolve=True).items() if not k.startswith("_")}


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
    for name, tensor in weights.items():
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
    try:
        check_release_weights(args["ckpt"], args["use_ema"])
        if args["out"]:
            net = convert(args["ckpt"], args["out"], args["use_ema"], args["overrides"]).network
        else:
            config = {k: v for k, v in model_hparams(args["overrides"])["config"].items() if k != "num_points"}
            net = load_release_checkpoint(args["ckpt"], config, use_ema=args["use_ema"])
    except (ReleaseCheckpointError, UnsafeFileError, FileNotFoundError) as exc:
        raise SystemExit(f"spread-release-ckpt: {' '.join(str(exc).split())}") from None
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
