"""``spread-sweep +sweep=guidance_grid ckpt=... data.root=... max_concurrent=2 out_dir=D``: a sweep on Ray Tune
(:mod:`spread.commands.sweep`, :mod:`spread.experiments.sweep`; keys: ``conf/sweep_run.yaml``). Not a Hydra app: Hydra's sweep syntax on the
command line is the search space, not a multirun."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> None:
    from spread.commands.sweep import sweep

    args = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help") for a in args):
        from spread.configs import conf_dir

        from spread.io import read_text_checked

        print(read_text_checked(f"{conf_dir()}/sweep_run.yaml"))
        return
    import logging

    handler = logging.StreamHandler(sys.stderr)  # the driver's own lines (a resumed search); trials log in Ray
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger = logging.getLogger("spread.sweep")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        result = sweep(args)
    except KeyboardInterrupt:  # Ctrl-C: no table of the points finished so far; a relaunch goes on from them
        from spread.cli.errors import verbose

        if verbose():
            raise
        print("spread-sweep: interrupted (Ctrl-C); a relaunch goes on from the points recorded", file=sys.stderr,
              flush=True)
        raise SystemExit(130) from None
    except Exception as exc:  # noqa: BLE001 - a bad setting, refused before any trial: one line
        from spread.cli.errors import user_error
        from spread.configs import error_message

        cause = user_error(exc)
        if cause is None:
            raise
        message = error_message(cause)
        raise SystemExit(message if message.startswith("spread-sweep") else f"spread-sweep: {message}") from None
    from spread.io import read_text_checked

    print(read_text_checked(result.md))
    stopped = [r for r in result.rows if r.get("status") == "stopped"]
    print(f"spread-sweep: {len(result.rows)} trials" + (f" ({len(result.points)} points)" if len(result.points) !=
                                                        len(result.rows) else "")
          + (f", {len(stopped)} stopped early by the trial scheduler" if stopped else "")
          + f" in {result.seconds:.1f} s → {result.csv}")
    failed = [r for r in result.rows if r.get("status") not in ("ok", "stopped")]
    if failed:
        raise SystemExit(f"spread-sweep: {len(failed)} trial(s) failed: " + "; ".join(str(r.get("error")) for r in failed))


if __name__ == "__main__":
    main()
