"""``spread-dashboard [tracking_uri=URI] [port=5000] [host=127.0.0.1] [paths.runs_dir=runs]``: MLflow's web UI
over the runs that ``logger=mlflow`` wrote (every command's runs, their metrics, curves, artifacts; compare
runs, parallel coordinates over a sweep).

It runs the real ``mlflow server`` with that backend store (default ``sqlite:///<paths.runs_dir>/mlflow.db``,
the store ``conf/logger/mlflow.yaml`` writes to) and prints the URL. It listens on localhost only; on a
cluster, run it on the login node and forward the port (``ssh -L 5000:localhost:5000 login-node``,
jobs/README.md). Another host needs ``allow_remote=true`` (the UI has no authentication: a warning says so).
Before it starts, the port (1–65535, free), the host and the store (a regular SQLite file that opens: not
corrupt, truncated or locked; no ``?``, ``#`` or ``%`` in its path) are checked: otherwise it exits non-zero
in one line (:mod:`spread.cli.serve`). Stop it with Ctrl-C.
"""

from __future__ import annotations

import os
import sys

KEYS = {"tracking_uri": None, "port": "5000", "host": "127.0.0.1", "paths.runs_dir": "runs", "workers": "1",
        "allow_remote": "false"}


def parse(argv: list[str]) -> dict:
    """``key=value`` arguments over :data:`KEYS`; an unknown key or a bare word is refused by name."""
    values = dict(KEYS)
    if any(a in ("-h", "--help") for a in argv):  # the usage, as spread-view and the Hydra commands print theirs
        print(__doc__.strip())
        raise SystemExit(0)
    for arg in argv:
        key, eq, value = arg.partition("=")
        if not eq or key.lstrip("+") not in KEYS:
            raise SystemExit(f"spread-dashboard: argument {arg!r}: expected key=value with key in {sorted(KEYS)}")
        values[key.lstrip("+")] = value
    if not values["workers"].isdigit() or not 1 <= int(values["workers"]) <= 64:
        raise SystemExit(f"spread-dashboard: workers={values['workers']}: expected 1 to 64")
    return values


def other_store_problem(uri: str) -> str | None:
    """Why ``mlflow server`` cannot serve a store that is not SQLite, or None (a database whose driver is
    installed: the server names what it cannot reach). Each of these printed the dashboard's URL, then a traceback."""
    scheme = uri.split(":", 1)[0].lower()
    if scheme in ("file", "") or "://" not in uri:
        return ("a file store, which MLflow keeps in maintenance mode and its server refuses; the platform's stores "
                "are SQLite (tracking_uri=sqlite:///<path>/mlflow.db)")
    if scheme in ("http", "https", "databricks"):
        return "an MLflow server already: open it in the browser, it needs no dashboard"
    try:
        import sqlalchemy

        sqlalchemy.create_engine(uri)  # imports the database's driver; connects to nothing yet
    except ModuleNotFoundError as exc:
        return f"its database driver is not installed (no module named '{exc.name}'); pip install it, or use SQLite"
    except Exception as exc:  # noqa: BLE001 - an URI SQLAlchemy cannot read
        return f"not a database URI ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})"
    return None


def server_command(values: dict) -> tuple[list[str], str]:
    """(the ``mlflow server`` command line, the store URI); creates the store when it does not exist yet; a store
    that cannot be opened is one line naming it."""
    from spread.tracking.mlflow_store import StoreError, artifact_root, open_store, resolve_tracking_uri

    try:
        uri = resolve_tracking_uri(values["tracking_uri"] or f"sqlite:///{values['paths.runs_dir']}/mlflow.db")
        if uri.startswith("sqlite:///"):
            open_store(uri)  # creates the tables of a new store; names a corrupt, truncated or locked one
        else:
            problem = other_store_problem(uri)
            if problem:
                raise SystemExit(f"spread-dashboard: tracking_uri={uri}: {problem}")
    except (StoreError, OSError) as exc:
        raise SystemExit(f"spread-dashboard: {' '.join(str(exc).split())}") from None
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", uri, "--host", values["host"],
               "--port", values["port"], "--workers", values["workers"]]
    root = artifact_root(uri)
    if root is not None:
        command += ["--artifacts-destination", root]
    return command, uri


def main(argv: list[str] | None = None) -> None:
    from spread.cli.serve import check_host, check_port

    values = parse(sys.argv[1:] if argv is None else argv)
    check_host("spread-dashboard", values["host"], values["allow_remote"])
    values["port"] = str(check_port("spread-dashboard", values["port"], values["host"]))
    command, uri = server_command(values)
    print(f"spread-dashboard: store {uri}\nspread-dashboard: open http://{values['host']}:{values['port']}/ "
          f"(Ctrl-C stops it)", flush=True)
    # MLflow's job runner (huey consumer processes for its GenAI jobs) serves nothing the dashboard shows: off, unless
    # the user's environment turns it on
    os.environ.setdefault("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")
    os.execv(command[0], command)


if __name__ == "__main__":
    main()
