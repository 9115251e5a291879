"""Hostile inputs, round 4 (docs/robustness.md, issue 32): plug-ins that lie or edit, readers that hang or leak,
servers and sweeps that never stop. Each test is one or more of the issue's broken cases, run through the console
script where a user meets it, plus a variant of the same class of input that the issue does not name.

The hostile plug-ins are real entry points: ``tests/data/hostile_plugin`` holds a module and its
``hostile_metrics-0.1.dist-info`` (what pip writes), put on ``PYTHONPATH`` of the command only.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import free_port, make_dataset

PLUGIN = Path(__file__).parent / "data" / "hostile_plugin"
SCRIPTS = Path(sys.executable).parent
#: A small library: the dataset is only the ground for plug-ins, reports and servers.
CATEGORIES = ["bed", "nightstand", "wardrobe", "desk", "chair", "dining_table", "shelf", "book", "mug"]
BUILT_INS = ["col_mesh", "grecall", "asd", "stability"]


def run(name: str, *args: str, timeout: int = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """A console script as a user runs it (no HYDRA_FULL_ERROR: user errors are one line), wandb disabled."""
    base = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    base.update(WANDB_MODE="disabled", OMP_NUM_THREADS="1", **(env or {}))
    return subprocess.run([str(SCRIPTS / name), *args], env=base, capture_output=True, text=True, timeout=timeout)


def one_line_error(proc: subprocess.CompletedProcess, command: str) -> str:
    """The single stderr line a refused command ends with (no traceback)."""
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert lines and lines[-1].startswith(f"{command}: "), proc.stderr[-3000:]
    return lines[-1]


def refused_in_process(main, argv: list[str], capsys=None) -> str:
    """The one-line refusal of a console script's ``main`` called in this process with ``argv`` (the same code the
    script runs, without a process start: for the variants; the issue's own cases run the scripts)."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    message = str(stop.value.code)
    assert stop.value.code not in (0, None) and "\n" not in message and "Traceback" not in message, message
    return message


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("round4"), rooms=10, seed=3, max_objects=5, categories=CATEGORIES)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The hostile plug-ins as an installed distribution, in a folder of their own."""
    folder = tmp_path_factory.mktemp("hostile_site")
    shutil.copytree(PLUGIN, folder, dirs_exist_ok=True)
    return folder


# ---- 1. metrics are isolated -----------------------------------------------------------------------------------

@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_lying_editing_and_broken_metric_plugins_fail_alone_and_never_change_the_built_ins(dataset, site, tmp_path):
    """High: a plug-in whose compute() also returns ``grecall`` replaced GRecall everywhere (0.999 shown, true 0.195);
    a plug-in listed first that moves the objects changed Stability; medium: a ``to_dict()`` holding a numpy array
    crashed the evaluation with no metrics.json; a plug-in module calling sys.exit stopped the command; a plug-in
    named ``scene_id`` collapsed every record; low: ``fid`` silently replaced, ``grecall`` silently skipped,
    ``SPREAD_MAX_INPUT_MB=inf`` an OverflowError. Variants: one that returns ``stability``, one that erases the
    graph in place, one that rebinds its copy's arrays, a set in ``to_dict()``, a metric that raises on one scene,
    one that returns inf, a BaseException on import, plug-ins named ``file`` and ``fid_status``."""
    from spread.evaluation.aggregate import summary_values
    from spread.evaluation.protocol import EvalProtocol
    from spread.evaluation.work import evaluate_scene, worker_library
    from spread.scene import list_scene_files

    files = list_scene_files(dataset / "test")
    assert len(files) >= 2
    fail_scene = files[0].stem
    hostile = ["mover", "spatial_eraser", "rebinder"]  # listed before the built-ins: they see the scene first
    tail = ["liar", "liar2", "arrayed", "setty", "raiser", "infinite", "honest"]
    out = tmp_path / "eval"
    proc = run("spread-evaluate", f"scenes={dataset / 'test'}", f"reference={dataset}", f"out_dir={out}",
               f"metrics=[{','.join(hostile + BUILT_INS + tail)}]", "logger=none", "protocol.stability_runs=1",
               "fid.enabled=false", "renders=0", "progress=false", "ray.num_cpus=1", "bootstrap_resamples=50",
               env={"PYTHONPATH": str(site), "HOSTILE_FAIL_SCENE": fail_scene, "SPREAD_MAX_INPUT_MB": "inf"})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    metrics = json.loads((out / "metrics.json").read_text())
    lines = {r["scene_id"]: r for r in map(json.loads, (out / "per_scene.jsonl").read_text().splitlines())}

    # the truth: the built-ins alone, in this process, on the same files
    protocol = EvalProtocol(stability_runs=1, metrics=BUILT_INS)
    library = worker_library(str(dataset / "assets"))
    alone = [evaluate_scene(p, library, protocol) for p in files]
    truth = summary_values(alone, protocol)
    for name in (*BUILT_INS, "still_fraction", "displacement_ok_fraction"):
        assert metrics[name] == truth[name], name
    assert metrics["n_colliding_objects"] == truth["n_colliding_objects"]
    for r in alone:
        line = lines[r["scene_id"]]
        assert line["grecall"] == r["grecall"] and line["stability"] == r["stability"], r["scene_id"]
        assert line["file"] == r["file"] and not set(BUILT_INS) & set(line.get("metric_errors") or {})
    assert metrics["n_evaluated"] == len(files) and metrics["n_failed"] == 0  # no scene lost to a plug-in

    n = len(files)
    assert metrics["metric_failures"] == {**{m: 0 for m in BUILT_INS}, "mover": n, "spatial_eraser": n, "rebinder": 0,
                                          "liar": n, "liar2": n, "arrayed": n, "setty": n, "raiser": 1,
                                          "infinite": n, "honest": 0}
    why = {(f["metric"], f["scene_id"]): f["error"] for f in metrics["failed_metrics"]}
    assert len(why) == metrics["n_metric_failures"] == 7 * n + 1
    some = files[-1].stem
    assert "compute() returned 'grecall'" in why["liar", some]
    assert "compute() returned 'stability'" in why["liar2", some]
    assert "read-only" in why["mover", some] and "read-only" in why["spatial_eraser", some]
    assert "not JSON" in why["arrayed", some] and "ndarray" in why["arrayed", some]
    assert "not JSON" in why["setty", some]
    assert why["raiser", fail_scene] == f"RuntimeError: cannot measure {fail_scene}"
    assert "inf" in why["infinite", some]
    objects = {p.stem: lines[p.stem]["num_objects"] for p in files}
    assert metrics["honest"] == pytest.approx(sum(objects.values()) / n)
    assert metrics["rebinder"] == metrics["honest"]  # its own copy, rebound: allowed, and nobody else sees it
    assert metrics["raiser"] == pytest.approx((sum(objects.values()) - objects[fail_scene]) / (n - 1))
    assert metrics["liar"] is None and metrics["infinite"] is None
    assert metrics["honest_lo"] <= metrics["honest"] <= metrics["honest_hi"]
    assert "metric failures" in proc.stdout and f"raiser failed on {fail_scene}" in proc.stdout

    # plug-ins that may not register are listed as failed, loudly, and the command went on
    for name, words in (("scene_id", "a field of every per_scene.jsonl record"),
                        ("file", "a field of every per_scene.jsonl record"), ("fid", "a field of metrics.json"),
                        ("fid_status", "a field of metrics.json"), ("grecall", "is taken by"),
                        ("stability", "is taken by"), ("exiter", "SystemExit: 3"), ("base_exiter", "Abort")):
        assert f"metric plugin '{name}'" in proc.stderr and words in proc.stderr, name


def test_a_plugin_that_exits_on_import_leaves_every_registry_usable_and_listed_as_failed(site):
    """Medium: a module calling ``sys.exit`` on import stopped every command that reads a registry (Registry.load
    caught Exception only). Variant: the methods registry, and a BaseException that is not an Exception."""
    code = ("import json, warnings\nwarnings.simplefilter('ignore')\n"
            "from spread.metrics.registry import METRICS\nfrom spread.methods.registry import METHODS\n"
            "print(json.dumps({'metrics': METRICS.failed(), 'methods': METHODS.failed(), "
            "'names': METRICS.names(), 'method_names': METHODS.names()}))")
    proc = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(site)},
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen["metrics"]["exiter"].endswith("failed to load: SystemExit: 3")
    assert "Abort: plugin aborts its import" in seen["metrics"]["base_exiter"]
    assert seen["methods"]["exiter"].endswith("failed to load: SystemExit: 3")
    assert {"col_mesh", "grecall", "honest", "liar"} <= set(seen["names"]) and "exiter" not in seen["names"]
    assert "spread" in seen["method_names"] and "exiter" not in seen["method_names"]


def test_metric_names_that_collide_with_record_fields_or_other_metrics_are_refused_at_registration():
    """Low: a plug-in named ``fid`` was silently replaced by FID; the name space of metrics, records and
    metrics.json is one. Variants: ``n_*`` (counts), ``_lo`` (intervals), a ratio named like another metric."""
    import importlib
    import sys as _sys

    from spread.metrics.registry import METRICS, spec_of_class
    from spread.registry import RegistryError

    METRICS.load()  # the built-ins and installed plugins first: a name is checked against all of them
    _sys.path.insert(0, str(PLUGIN))
    try:
        honest = importlib.import_module("hostile_metrics").Honest
        liar = importlib.import_module("hostile_metrics").counting("grecall_twin")
    finally:
        _sys.path.remove(str(PLUGIN))
    for name, words in (("scene_id", "a field of every per_scene.jsonl record"), ("error", "per_scene.jsonl"),
                        ("fid", "a field of metrics.json"), ("n_things", "the 'n_' prefix names counts"),
                        ("grecall_lo", "interval")):
        with pytest.raises(RegistryError, match=words):
            METRICS.register(name, spec_of_class(name, honest))
        assert name not in METRICS
    liar.ratios = {"grecall": ("objects", "scenes")}  # reports another metric's name
    with pytest.raises(RegistryError, match=r"would report \['grecall'\], which metric 'grecall' reports"):
        METRICS.register("grecall_twin", spec_of_class("grecall_twin", liar))
    assert "grecall_twin" not in METRICS


# ---- 2. every reader through one door --------------------------------------------------------------------------

def png_bytes(colour=(200, 30, 30)) -> bytes:
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (8, 8), colour).save(buffer, format="PNG")
    return buffer.getvalue()


def fake_run(folder: Path, **values) -> Path:
    """A finished evaluation run folder: a hand-written metrics.json (a user's, or a tampered one)."""
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps({"n_scenes": 2, "n_evaluated": 2, "n_failed": 0, **values}))
    return folder


def test_spread_report_embeds_only_pngs_inside_the_run_and_never_hangs_on_a_fifo(tmp_path):
    """High: ``renders/x.png`` linking to /etc/passwd was embedded, base64, in the report people share; medium: a
    FIFO named ``renders/x.png`` hung spread-report forever; medium: ``Infinity`` / ``1e308`` in a metrics.json was
    printed bold as the best value; low: a ``|`` in a run folder's name added a Markdown column. Variants: a text
    file named .png inside the run, a link to a real PNG outside the run, a linked ``renders/`` folder, a FIFO
    ``metrics.csv`` of a training run, ``-1e308`` ASD, a newline in a run's name."""
    runs = tmp_path / "runs"
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "private.png").write_bytes(png_bytes((1, 2, 3)))
    good = fake_run(runs / "good", grecall=0.5, col_mesh=0.2, asd=0.01, stability=0.9)
    (good / "renders").mkdir()
    (good / "renders" / "a.png").write_bytes(png_bytes())
    (good / "renders" / "b.png").symlink_to("/etc/passwd")
    os.mkfifo(good / "renders" / "c.png")
    (good / "renders" / "d.png").write_text("not an image, a secret")
    (good / "renders" / "e.png").symlink_to(outside / "private.png")
    fake_run(runs / "in|finite", grecall=float("inf"), col_mesh=0.1, asd=0.02, stability=0.8)
    fake_run(runs / "huge", grecall=1e308, col_mesh=0.3, asd=-1e308, stability=1e308)
    linked = fake_run(runs / "new\nline", grecall=0.4, col_mesh=0.25, asd=0.03, stability=0.7)
    (linked / "renders").symlink_to(outside)
    training = runs / "train" / "csv" / "version_0"
    training.mkdir(parents=True)
    os.mkfifo(training / "metrics.csv")
    proc = run("spread-report", f"runs={runs}", f"out_dir={tmp_path / 'R'}", timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    page = (tmp_path / "R" / "report.html").read_text()
    leaked = [base64.b64encode(Path("/etc/passwd").read_bytes())[:24].decode(),
              base64.b64encode(b"not an image, a secret")[:16].decode(),
              base64.b64encode((outside / "private.png").read_bytes()).decode()]
    assert not any(text in page for text in leaked)
    assert page.count("data:image/png;base64," + base64.b64encode(png_bytes()).decode()) == 1
    refused = json.loads((tmp_path / "R" / "report.json").read_text())["refused"]
    for words in ("b.png: a symbolic link to /etc/passwd", "c.png: not a regular file (a FIFO",
                  "d.png: not a PNG", "e.png: a symbolic link to", "private.png: resolves to", "metrics.csv: not a "
                  "regular file (a FIFO"):
        assert any(words in r for r in refused), (words, refused)
    md = (tmp_path / "R" / "report.md").read_text()
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = [line for line in lines[start:start + 6] if line.startswith("|")]  # the evaluated runs' table
    assert len({len(line.replace("\\|", "").split("|")) for line in rows}) == 1  # every row the header's width
    assert len(rows) == 2 + 4 and any("in\\|finite" in line for line in rows)
    assert "invalid (inf)" in md and "invalid (1e+308)" in md and "invalid (-1e+308)" in md
    assert "**invalid" not in md  # never the best
    good_row = next(line for line in rows if "| good |" in line)
    assert "**0.500**" in good_row and "**10.0**" in good_row  # best valid GRecall, best valid ASD (mm)
    assert any(line.startswith("| new line |") for line in rows)  # a newline in a name stays one cell


def test_spread_view_leaves_a_fifo_among_the_scenes_out_by_name_and_refuses_hosts_and_ports(dataset, tmp_path):
    """Medium: a FIFO among a run's scenes hung spread-view (a bare np.load); low: ``host=0.0.0.0`` was accepted
    silently. Variants: a /dev/zero link among the scenes, a busy port, port 0, ``allow_remote=maybe``."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for path in sorted((dataset / "test").glob("*.npz"))[:1]:
        shutil.copy(path, scenes / path.name)
    os.mkfifo(scenes / "fifo.npz")
    (scenes / "zero.npz").symlink_to("/dev/zero")
    port = free_port()
    proc = subprocess.Popen([str(SCRIPTS / "spread-view"), str(scenes), f"assets={dataset / 'assets'}", f"port={port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    watchdog = threading.Timer(180, os.killpg, (proc.pid, signal.SIGKILL))  # a hang fails the test, never the suite
    watchdog.start()
    try:
        out = ""
        while not out.startswith("spread-view:"):  # viser prints a banner first
            out = proc.stdout.readline()
            assert out, "spread-view ended without serving"
        assert f"1 scene(s) from {scenes}" in out and f":{port}/" in out, out  # it serves the readable scene
    finally:
        watchdog.cancel()
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert "not shown: " in err and "fifo.npz: not a regular file (a FIFO" in err
    assert "zero.npz: a symbolic link to /dev/zero" in err
    line = one_line_error(run("spread-view", str(scenes), "host=0.0.0.0", f"port={free_port()}"), "spread-view")
    assert "host=0.0.0.0 is not a loopback address" in line and "allow_remote=true" in line
    from spread.cli.view import main

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        assert f"port {taken} on 127.0.0.1 is in use" in refused_in_process(main, [str(scenes), f"port={taken}"])
    assert "port=0: not a port number" in refused_in_process(main, [str(scenes), "port=0"])
    assert "allow_remote=maybe: expected true or false" in refused_in_process(
        main, [str(scenes), "host=10.1.2.3", "allow_remote=maybe"])


# ---- 3. servers behave -----------------------------------------------------------------------------------------

@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_spread_dashboard_checks_port_host_and_store_before_serving(tmp_path):
    """Medium: on a busy port spread-dashboard printed the other server's URL and hung; ``port=99999`` gave a
    traceback and hung; ``host=0.0.0.0`` was accepted silently; low: a corrupt, truncated or locked mlflow.db gave
    a 72–82-line traceback; a ``?`` in ``paths.runs_dir`` put the store elsewhere than printed. Variants: port
    -1, a LAN address, a ``#`` in the path, a FIFO as the store, and ``allow_remote=true`` (a warning; tests never
    listen beyond 127.0.0.1, so here the port is then refused)."""
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        line = one_line_error(run("spread-dashboard", f"port={taken}", f"paths.runs_dir={tmp_path / 'r'}", timeout=60),
                              "spread-dashboard")
    assert f"port {taken} on 127.0.0.1 is in use" in line and "open http" not in line
    line = one_line_error(run("spread-dashboard", "port=99999", timeout=60), "spread-dashboard")
    assert "port=99999: not a port number (1-65535)" in line
    line = one_line_error(run("spread-dashboard", "host=0.0.0.0", f"port={free_port()}", timeout=60), "spread-dashboard")
    assert "host=0.0.0.0 is not a loopback address" in line and "no authentication" in line
    line = one_line_error(run("spread-dashboard", f"paths.runs_dir={tmp_path / 'a?b'}", f"port={free_port()}",
                              timeout=60), "spread-dashboard")
    assert f"{tmp_path / 'a?b'}/mlflow.db: the path holds ?" in line

    from spread.cli.dashboard import main
    from spread.tracking.mlflow_store import open_store

    assert "port=-1: not a port number" in refused_in_process(main, ["port=-1"])
    assert "host=192.168.1.10 is not a loopback" in refused_in_process(main, ["host=192.168.1.10"])
    assert "the path holds #" in refused_in_process(main, [f"paths.runs_dir={tmp_path / 'c#d'}",
                                                           f"port={free_port()}"])
    assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists()  # no store written elsewhere

    made = tmp_path / "made" / "mlflow.db"
    open_store(f"sqlite:///{made}")
    stores = {"corrupt": b"\x00garbage" * 512, "truncated": made.read_bytes()[:20000]}
    for name, data in stores.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "mlflow.db").write_bytes(data)
    (tmp_path / "fifo").mkdir()
    os.mkfifo(tmp_path / "fifo" / "mlflow.db")
    (tmp_path / "locked").mkdir()
    shutil.copy(made, tmp_path / "locked" / "mlflow.db")
    holder = sqlite3.connect(tmp_path / "locked" / "mlflow.db", isolation_level=None, check_same_thread=False)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        for name, words in (("corrupt", "file is not a database"), ("truncated", "malformed"),
                            ("locked", "database is locked")):
            line = one_line_error(run("spread-dashboard", f"paths.runs_dir={tmp_path / name}", f"port={free_port()}",
                                      timeout=120), "spread-dashboard")
            assert f"{tmp_path / name}/mlflow.db" in line and words in line, line
    finally:
        holder.close()
    line = refused_in_process(main, [f"paths.runs_dir={tmp_path / 'fifo'}", f"port={free_port()}"])
    assert f"{tmp_path / 'fifo'}/mlflow.db: not a regular file (a FIFO" in line
    proc = run("spread-dashboard", "host=0.0.0.0", "allow_remote=true", "port=99999", timeout=60)
    assert "WARNING: listening on 0.0.0.0 with allow_remote=true — there is no authentication" in proc.stderr
    assert "port=99999: not a port number" in one_line_error(proc, "spread-dashboard")


def test_a_store_path_with_a_question_mark_is_refused_by_every_command_that_logs_to_mlflow(dataset, tmp_path):
    """Low: a ``?`` in ``paths.runs_dir`` put the store elsewhere than printed; every command opens the store through
    the same door (spread-evaluate here), refused before any work."""
    out = tmp_path / "eval"
    line = one_line_error(run("spread-evaluate", f"scenes={dataset / 'test'}", f"reference={dataset}",
                              f"out_dir={out}", "logger=mlflow", f"paths.runs_dir={tmp_path / 'x?y'}",
                              "fid.enabled=false", "protocol.stability_runs=1", "ray.num_cpus=1", "progress=false"),
                          "spread-evaluate")
    assert f"{tmp_path / 'x?y'}/mlflow.db: the path holds ?" in line
    assert not (out / "metrics.json").exists() and not (tmp_path / "x").exists()


# ---- 4. sweeps are bounded and honest --------------------------------------------------------------------------

def test_spread_sweep_refuses_unbounded_empty_and_inert_sweeps_before_any_trial(dataset, tmp_path):
    """Medium: ``num_samples=-1`` started 280 trials and never ended; a sweep over a weight with no effect (guidance
    off) showed identical points and starred one; low: ``range(0,0)`` an empty sweep with rc 0, ``interval(1,0)`` a
    Ray traceback. Variants: ``num_samples=0``, an inert ``interval()`` under random search, a log interval from 0,
    ``trial_cpus=0``."""
    ckpt = tmp_path / "no.ckpt"  # never read: every refusal comes before any trial
    base = [f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={tmp_path / 'sweep'}"]
    from spread.cli.sweep import main

    cases = [  # (the script or its main in this process, arguments, the refusal)
        (True, ["search=random", "num_samples=-1", "seed=0,1"], "num_samples=-1: a whole number ≥ 1"),
        (False, ["search=random", "num_samples=0", "seed=0,1"], "num_samples=0: a whole number ≥ 1"),
        (False, ["trial_cpus=0", "seed=0,1"], "trial_cpus=0: expected a number > 0"),
        (True, ["seed=range(0,0)"], "seed: the sweep over it has no value"),
        (True, ["search=random", "guidance.collision=interval(1,0)"], "interval(1,0): expected finite low < high"),
        (False, ["search=random", "guidance.collision=tag(log,interval(0,1))"], "a log interval needs low > 0"),
        (True, ["guidance.collision=0.0,0.01"], "guidance.collision: its values ['0.0', '0.01'] give every point the "
                                                "same fingerprint"),
        (False, ["search=random", "num_samples=2", "guidance.gravity=interval(0.0,0.01)", "seed=0,1"],
         "guidance.gravity: its values ['0.0', '0.01'] give every point the same fingerprint"),
    ]
    for script, extra, words in cases:
        line = one_line_error(run("spread-sweep", *base, *extra, timeout=180), "spread-sweep") if script \
            else refused_in_process(main, [*base, *extra])
        assert words in line, (extra, line)
        if "fingerprint" in words:
            assert "guidance is off in every point" in line
        assert not (tmp_path / "sweep" / "tune").exists() and not (tmp_path / "sweep" / "results.csv").exists()


def test_spread_sweep_refuses_trials_no_node_can_hold_and_keeps_ray_tune_inside_out_dir(dataset, tmp_path):
    """Medium: ``trial_cpus=64`` on a 2-CPU cluster never started a trial (one Ray warning after 60 s);
    ``name=../../x`` wrote Ray Tune's state outside out_dir. Variants: ``trial_gpus=1`` on a machine without GPUs,
    an absolute path as the name."""
    import ray

    from spread.experiments.sweep import SweepSettings, check_resources

    base = [f"ckpt={tmp_path / 'no.ckpt'}", f"data.root={dataset}", "num_cpus=1"]
    proc = run("spread-sweep", *base, "seed=0,1", f"out_dir={tmp_path / 'big'}", "trial_cpus=64", timeout=240)
    line = one_line_error(proc, "spread-sweep")
    assert "trial_cpus=64: no node of the Ray cluster has that many CPUs (the largest has 1" in line
    assert "Ray instance" not in proc.stderr  # the cluster it would start has num_cpus=1: refused before starting it
    nodes = [{"Alive": True, "Resources": {"CPU": 2.0}}, {"Alive": False, "Resources": {"CPU": 64.0, "GPU": 8.0}}]
    with pytest.MonkeyPatch.context() as patch:  # a 2-CPU node, and a dead one that had everything
        patch.setattr(ray, "nodes", lambda: nodes)
        with pytest.raises(ValueError, match=r"trial_gpus=1: no node of the Ray cluster has that many GPUs \(the "
                                             r"largest has 0, over 1 node"):
            check_resources(SweepSettings(out_dir=str(tmp_path), trial_gpus=1))
        check_resources(SweepSettings(out_dir=str(tmp_path), trial_cpus=2))  # fits: no error
    for name in ("../../escaped", str(tmp_path / "absolute")):  # Ray Tune's folder: one plain name in out_dir
        folder = SweepSettings(out_dir=str(tmp_path), name=name).folder_name
        assert "/" not in folder and not folder.startswith(".")


@pytest.mark.slow  # a Ray Tune run (~60 s on 2 cores): make test-slow runs it; the name's folder is checked above
def test_a_sweep_named_out_of_its_folder_keeps_ray_tune_inside_out_dir(dataset, tmp_path):
    from helpers import FAST_TRAIN, SMALL_MODEL, train_in_process
    from spread.experiments.sweep import SweepSettings, read_results_csv

    train_in_process(tmp_path / "train", f"data.root={dataset}", "experiment=quick", *SMALL_MODEL, *FAST_TRAIN,
                     "trainer.max_steps=2", "trainer.max_time=null")
    base = [f"ckpt={tmp_path / 'train' / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}", "num_cpus=1",
            "sampler.steps=2", "batch_size=2", "renders=0", "figures=0", "logger=none",
            "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false"]
    out = tmp_path / "deep" / "er" / "sweep"
    proc = run("spread-sweep", *base, "seed=0", f"out_dir={out}", "name=../../escaped", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not (tmp_path / "deep" / "escaped").exists() and not (out.parent.parent / "escaped").exists()
    tune = [p.name for p in (out / "tune").iterdir()]
    assert tune == [SweepSettings(out_dir=str(out), name="../../escaped").folder_name] and "/" not in tune[0]
    assert [r["status"] for r in read_results_csv(out / "results.csv")] == ["ok"]


# ---- 5. converters refuse bad weights --------------------------------------------------------------------------

def release_weights(path: Path, model, ema=None) -> Path:
    torch.save({"model": model, **({} if ema is None else {"ema_states": ema})}, path)
    return path


def test_spread_release_ckpt_refuses_non_finite_and_malformed_weights_in_one_line(tmp_path):
    """Medium: an all-NaN checkpoint was converted silently into a 393 MB platform checkpoint; low: ``{"model":
    [1,2,3]}``, int keys and int ``shadow_params`` ended in unnamed AttributeError/TypeError; an UnsafeFileError
    escaped as a traceback. Variants: one infinite value in one EMA tensor, raw NaN weights with use_ema=false, an
    int tensor, a pickled payload."""
    from test_release_checkpoint import FIXTURE

    with np.load(FIXTURE, allow_pickle=False) as f:
        keys = json.loads(str(f["config"]))["key_order"]
        weights = {k: torch.from_numpy(f[f"w/{k}"]) for k in keys}
    model = {f"_orig_mod.network.{k}": v.clone() for k, v in weights.items()}
    nan = {k: torch.full_like(v, float("nan")) for k, v in model.items()}
    shadow = [v.clone() for v in weights.values()]
    shadow[3] = shadow[3].clone()
    shadow[3].view(-1)[0] = float("inf")
    marker = tmp_path / "payload_ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    cases = {
        "all_nan": ((nan, {"shadow_params": list(nan.values())}), [], f"weight '{keys[0]}'",
                    f"holds {weights[keys[0]].numel()} of {weights[keys[0]].numel()} values that are NaN or infinite"),
        "one_inf": ((model, {"shadow_params": shadow}), [], f"weight '{keys[3]}'", "holds 1 of"),
        "raw_nan": ((nan, None), ["use_ema=false"], f"weight '{keys[0]}'", "NaN or infinite (raw weights)"),
        "list": (([1, 2, 3], None), [], "key 'model' holds list", "expected a dict"),
        "int_keys": (({1: torch.zeros(2)}, None), [], "'model' has the key 1 (int)", "weight names are strings"),
        "int_shadow": ((model, {"shadow_params": 7}), [], "'ema_states.shadow_params' holds int", "a list of tensors"),
        "int_tensor": (({k: v.to(torch.int64) for k, v in model.items()}, None), ["use_ema=false"],
                       f"weight '{keys[0]}' is torch.int64", "floating point"),
        # a sparse weight ended in a 105-line NotImplementedError from torch.isfinite (review, stop 72)
        "sparse_ema": ((model, {"shadow_params": [shadow[0].to_sparse(), *shadow[1:]]}), [],
                       f"weight '{keys[0]}' is a sparse_coo tensor", "expected a dense one"),
        "sparse_raw": (({k: (v.to_sparse() if i == 2 else v) for i, (k, v) in enumerate(model.items())}, None),
                       ["use_ema=false"], f"weight '{keys[2]}' is a sparse_coo tensor", "expected a dense one"),
    }
    from spread.cli.release_ckpt import main

    for name, ((m, ema), extra, where, words) in cases.items():
        path = release_weights(tmp_path / f"{name}.pth", m, ema)
        out = tmp_path / f"{name}.ckpt"
        args = [f"ckpt={path}", f"out={out}", *extra]
        line = one_line_error(run("spread-release-ckpt", *args, timeout=120), "spread-release-ckpt") \
            if name in ("all_nan", "list") else refused_in_process(main, args)
        assert f"{path}: {where}" in line and words in line, (name, line)
        assert not out.exists()
    torch.save({"model": Payload()}, tmp_path / "payload.pth")
    line = one_line_error(run("spread-release-ckpt", f"ckpt={tmp_path / 'payload.pth'}", timeout=120),
                          "spread-release-ckpt")
    assert "payload.pth: refused" in line and "pickled Python objects" in line and not marker.exists()


# ---- 6. the read-once cache keys on content identity -----------------------------------------------------------

def test_a_file_replaced_with_the_same_size_and_its_old_mtime_is_read_again(tmp_path):
    """Low: the read-once cache served stale content when a file was replaced with the same size and its old mtime
    (key: path, size, mtime). Variant: rewritten in place (same inode), mtime set back."""
    from spread import readonce

    readonce.clear()
    try:
        path = tmp_path / "x.bin"
        path.write_bytes(b"A" * 64)
        stamp = path.stat().st_mtime_ns
        first = readonce.file_sha256(path)
        other = tmp_path / "y.bin"
        other.write_bytes(b"B" * 64)
        os.utime(other, ns=(stamp, stamp))
        os.replace(other, path)  # another file (inode), same size, same mtime
        assert path.stat().st_mtime_ns == stamp and path.stat().st_size == 64
        second = readonce.file_sha256(path)
        assert second != first and second == readonce.file_sha256(path)
        time.sleep(0.05)  # past the file system's clock tick: a change's ctime differs from the last one's
        with open(path, "r+b") as fh:  # the same inode, rewritten, its mtime put back
            fh.write(b"C" * 64)
        os.utime(path, ns=(stamp, stamp))
        assert readonce.file_sha256(path) not in (first, second)
        assert readonce.counts()["sha256"] == {"reads": 3, "hits": 1}
    finally:
        readonce.clear()


# ---- the small ones: a lock that is a FIFO, a size limit that is inf -------------------------------------------

def test_a_fifo_as_the_run_lock_is_refused_by_name_and_the_size_limit_reads_inf_as_none(dataset, tmp_path, monkeypatch):
    """Low: a FIFO as ``.spread.lock`` gave an OSError with no path; ``SPREAD_MAX_INPUT_MB=inf`` an OverflowError.
    Variants: a folder as the lock; ``nan`` as the limit."""
    from spread.io import InputFileError, check_input_file, max_input_bytes

    out = tmp_path / "eval"
    out.mkdir()
    os.mkfifo(out / ".spread.lock")
    args = [f"scenes={dataset / 'test'}", f"reference={dataset}", f"out_dir={out}", "logger=none", "progress=false"]
    line = one_line_error(run("spread-evaluate", *args), "spread-evaluate")
    assert f"{out / '.spread.lock'}: the run folder's lock is not a regular file (a FIFO" in line
    (out / ".spread.lock").unlink()
    (out / ".spread.lock").mkdir()
    from spread.io import run_lock

    with pytest.raises(IsADirectoryError, match=str(out / ".spread.lock")):
        with run_lock(out, "spread-evaluate"):
            pass
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "inf")
    assert max_input_bytes() == 0
    big = tmp_path / "big.npz"
    big.write_bytes(b"\0" * 1024)
    assert check_input_file(big) == big
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "nan")
    with pytest.raises(InputFileError, match=r"SPREAD_MAX_INPUT_MB='nan': not a number of megabytes"):
        check_input_file(big)


# ---- every reader: no bare open in the platform's readers ------------------------------------------------------

def test_no_module_reads_a_file_without_the_bounded_read_check():
    """The one door (``spread.io.check_input_file``): outside io.py and safe_load.py, no module reads a file with a
    bare ``read_text()``, ``read_bytes()``, ``np.load(path)``, ``json.load``, ``OmegaConf.load`` or ``open()`` for
    reading (a FIFO would block it for ever); reads go through ``read_text_checked``, ``read_bytes_checked``,
    ``read_json``, ``read_json_object``, ``load_npz`` or an ``open(check_input_file(...))``."""
    import re

    import spread

    root = Path(spread.__file__).parent
    bare = re.compile(r"\.read_text\(|\.read_bytes\(|np\.load\((?!io\.BytesIO|check_input_file)|json\.load\(|"
                      r"OmegaConf\.load\(|(?<![\w.])open\((?!check_input_file|tmp|self\.run_dir)|trimesh\.load\("
                      r"(?!check_input_file)")
    allowed = {"io.py", "safe_load.py"}
    offences = []
    for path in sorted(root.rglob("*.py")):
        if path.name in allowed and path.parent == root:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            writes = re.search(r"""["'][wax]b?\+?["']""", code)
            if bare.search(code) and "check_input_file(" not in code and not writes and "# checked:" not in line:
                offences.append(f"{path.relative_to(root)}:{number}: {line.strip()}")
    assert not offences, "\n".join(offences)
