"""``spread-dashboard [tracking_uri=URI] [port=5000] [host=127.0.0.1] [paths.runs_dir=runs]``: MLflow's web UI
over the runs that ``logger=mlflow`` wrote (every command's runs, their metrics, curves, artifacts; compare
runs, parallel coordinates over a sweep).

It runs the real ``mlflow server`` with that backend store (default ``sqlite:///<paths.runs_dir>/mlflow.db``,
the store ``conf/logger/mlflow.yaml`` writes to) and prints the URL. It listens on localhost only; on a
cluster, run it on the login node and forward the port (``ssh -L 5000:localhost:5000 login-node``,
jobs/README.md). Stop it with Ctrl-C.
"""

from __future__ import annotations

import os
import sys

KEYS = {"tracking_uri": None, "port": "5000", "host": "127.0.0.1", "paths.runs_dir": "runs", "workers": "1"}


def parse(argv: list[str]) -> dict:
    """``key=value`` arguments over :data:`KEYS`; an unknown key or a bare word is refused by name."""
    values = dict(KEYS)
    for arg in argv:
        key, eq, value = arg.partition("=")
        if not eq or key.lstrip("+") not in KEYS:
            raise SystemExit(f"spread-dashboard: argument {arg!r}: expected key=value with key in {sorted(KEYS)}")
        values[key.lstrip("+")] = value
    if not values["port"].isdigit():
        raise SystemExit(f"spread-dashboard: port={values['port']}: not a port number")
    return values


def server_command(values: dict) -> tuple[list[str], str]:
    """(the ``mlflow server`` command line, the store URI); creates the store when it does not exist yet."""
    from spread.runtime.mlflow_log import artifact_root, quiet, resolve_tracking_uri

    uri = resolve_tracking_uri(values["tracking_uri"] or f"sqlite:///{values['paths.runs_dir']}/mlflow.db")
    if uri.startswith("sqlite:///"):
        from mlflow import MlflowClient

        quiet()
        MlflowClient(tracking_uri=uri).search_experiments(max_results=1)  # creates the tables of a new store
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", uri, "--host", values["host"],
               "--port", values["port"], "--workers", values["workers"]]
    root = artifact_root(uri)
    if root is not None:
        command += ["--artifacts-destination", root]
    return command, uri


def main(argv: list[str] | None = None) -> None:
    values = parse(sys.argv[1:] if argv is None else argv)
    command, uri = server_command(values)
    print(f"spread-dashboard: store {uri}\nspread-dashboard: open http://{values['host']}:{values['port']}/ "
          f"(Ctrl-C stops it)", flush=True)
    os.execv(command[0], command)


if __name__ == "__main__":
    main()
