"""``spread-release-ckpt ckpt=PATH [use_ema=true]``: load the SPREAD authors' ``ckpt.pth`` into the release's
network (:mod:`spread.model.release`) and report it; refuses a file whose weights do not fit, naming the keys."""

from __future__ import annotations

import sys


def parse(argv: list[str]) -> dict:
    """``key=value`` arguments: ``ckpt`` (required) and ``use_ema`` (default true)."""
    args = {"use_ema": "true"}
    for arg in argv:
        key, sep, value = arg.partition("=")
        if not sep or key not in ("ckpt", "use_ema"):
            raise SystemExit(f"spread-release-ckpt: unknown argument {arg!r} (usage: ckpt=PATH [use_ema=true|false])")
        args[key] = value
    if "ckpt" not in args:
        raise SystemExit("spread-release-ckpt: ckpt=PATH is required (the release's ckpt.pth)")
    if args["use_ema"].lower() not in ("true", "false"):
        raise SystemExit(f"spread-release-ckpt: use_ema={args['use_ema']!r}: expected true or false")
    return {"ckpt": args["ckpt"], "use_ema": args["use_ema"].lower() == "true"}


def main(argv: list[str] | None = None) -> None:
    from spread.model.release import ReleaseCheckpointError, load_release_checkpoint

    args = parse(sys.argv[1:] if argv is None else argv)
    try:
        net = load_release_checkpoint(args["ckpt"], use_ema=args["use_ema"])
    except (ReleaseCheckpointError, FileNotFoundError) as exc:
        raise SystemExit(f"spread-release-ckpt: {exc}") from exc
    c = net.config
    params = sum(p.numel() for p in net.parameters())
    print(f"{args['ckpt']}: the release's network, {'EMA' if args['use_ema'] else 'raw'} weights, {params:,} parameters "
          f"(width {c.attn_dim}, {c.n_layers} blocks, {c.num_latents} × {c.attn_dim} perceiver latents, edge width "
          f"{c.attn_dim // 4}); no missing or unexpected keys")


if __name__ == "__main__":
    main()
