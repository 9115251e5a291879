"""``spread-view PATH [assets=DIR] [port=8080] [host=127.0.0.1]``: an interactive 3D viewer in the browser for a
scene file, a folder of them, or a run folder (its ``scenes/``): objects coloured by category with a legend,
the ground truth beside a generated scene, before / after the Stability simulation, the relation matrix, and
the guidance iterations as a timeline when the file carries them (:mod:`spread.render.viewer`).

Listens on localhost only; on a cluster, forward the port (``ssh -L 8080:localhost:8080 login-node``); another
host needs ``allow_remote=true`` (no authentication: a warning says so). The port (1–65535, free) and host are
checked before it starts, and every scene file is checked before it is opened (a FIFO or device among the
scenes is named and left out): otherwise it exits non-zero in one line. Stop it with Ctrl-C.
"""

from __future__ import annotations

import sys
import time

KEYS = {"assets": None, "port": "8080", "host": "127.0.0.1", "allow_remote": "false"}


def parse(argv: list[str]) -> tuple[str, dict]:
    """(the path, ``key=value`` options over :data:`KEYS`); refused by name when unknown or missing."""
    values, paths = dict(KEYS), []
    if any(a in ("-h", "--help") for a in argv):  # the usage, not "--help: no such file or folder"
        print(__doc__.strip())
        raise SystemExit(0)
    for arg in argv:
        key, eq, value = arg.partition("=")
        if not eq:
            paths.append(arg)
        elif key in ("path", "scenes", "run"):
            paths.append(value)
        elif key in KEYS:
            values[key] = value
        else:
            raise SystemExit(f"spread-view: argument {arg!r}: unknown key (known: path, {', '.join(KEYS)})")
    if len(paths) != 1:
        raise SystemExit(f"spread-view: give one scene file, folder or run folder (got {paths or 'none'})")
    return paths[0], values


def main(argv: list[str] | None = None) -> None:
    from spread.cli.serve import check_host, check_port
    from spread.render.viewer import SceneViewer, collect

    path, values = parse(sys.argv[1:] if argv is None else argv)
    check_host("spread-view", values["host"], values["allow_remote"])
    port = check_port("spread-view", values["port"], values["host"])
    refused: list[str] = []
    try:
        items, library = collect(path, values["assets"], refused)
    except (FileNotFoundError, ValueError) as exc:
        message = " ".join(str(exc).split())
        raise SystemExit(message if message.startswith("spread-view") else f"spread-view: {message}") from None
    for why in refused:
        print(f"spread-view: not shown: {why}", file=sys.stderr, flush=True)
    viewer = SceneViewer(items, library, host=values["host"], port=port)
    url = browser_url(values["host"], viewer.server.get_port())
    print(f"spread-view: {len(items)} scene(s) from {path}; open {url} "
          f"(Ctrl-C stops it)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        viewer.server.stop()


def browser_url(host: str, port: int) -> str:
    """The address to open: an IPv6 host in brackets (``http://[::1]:8080/``; ``http://::1:8080/`` opens nothing)."""
    return f"http://{f'[{host}]' if ':' in host else host}:{port}/"


if __name__ == "__main__":
    main()
