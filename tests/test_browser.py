"""The dashboard, the HTML report and the scene viewer as a person sees them: Debian's headless chromium
(``tests/browser.py``, over the DevTools protocol) loads each page. Slow (a browser and an MLflow server
start); ``make test-slow`` installs chromium when missing. ``SPREAD_SCREENSHOTS=DIR`` keeps a screenshot
of each page there (docs/images/ holds the ones the docs show)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from browser import Browser, chromium_binary
from test_dashboard import Dashboard, free_port, get, store  # noqa: F401  (store: the shared fixture)

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(chromium_binary() is None, reason="needs chromium (make browser installs it)")]


CLICK_MODEL_TRAINING = ("(() => { const el = Array.from(document.querySelectorAll('*')).find(e => "
                        "e.childElementCount === 0 && e.textContent.trim() === 'Model training'); "
                        "if (el) el.click(); return !!el; })()")


def shot(tmp_path: Path, name: str) -> Path:
    folder = os.environ.get("SPREAD_SCREENSHOTS")
    return Path(folder) / name if folder else tmp_path / name


def test_dashboard_page_shows_the_training_and_sampling_runs(store, tmp_path):  # noqa: F811
    uri = store[1]
    server = Dashboard(uri)
    try:
        _, body = get(server.url + "/api/2.0/mlflow/experiments/search", {"max_results": 100})
        ids = {e["name"]: e["experiment_id"] for e in json.loads(body)["experiments"]}
        _, body = get(server.url + "/api/2.0/mlflow/runs/search", {"experiment_ids": [ids["quick"]]})
        train_id = json.loads(body)["runs"][0]["info"]["run_id"]
        with Browser() as browser:
            browser.open(f"{server.url}/#/experiments/{ids['tiny_sample']}")
            browser.wait_text("tiny_sample")
            browser.evaluate(CLICK_MODEL_TRAINING)  # MLflow 3's UI opens on its GenAI pages
            browser.open(f"{server.url}/#/experiments/{ids['tiny_sample']}/runs")
            browser.wait_for("Array.from(document.querySelectorAll('a')).some(a => a.textContent.trim() === 'sample')")
            browser.screenshot(shot(tmp_path, "dashboard_runs.png"))
            browser.open(f"{server.url}/#/experiments/{ids['quick']}/runs?compareRunsMode=CHART")
            browser.wait_text("quick/train", "train/loss", "train/grad_norm")
            browser.open(f"{server.url}/#/experiments/{ids['quick']}/runs/{train_id}")
            browser.wait_text("spread.variant", "val/grecall")  # the run's tags and metrics
            browser.screenshot(shot(tmp_path, "dashboard_training.png"))
    finally:
        server.stop()


def test_html_report_loads_without_console_errors(store, tmp_path):  # noqa: F811
    from spread.reporting.report import run_report

    run_report([str(store[3]), str(store[2])], tmp_path / "R")
    with Browser() as browser:
        browser.open((tmp_path / "R" / "report.html").resolve().as_uri())
        browser.wait_text("Training curves", "Per room type", "Evaluated runs")
        browser.wait_for("Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)")
        browser.pump(1)
        assert browser.errors == []
        assert browser.evaluate("document.images.length") >= 3
        browser.screenshot(shot(tmp_path, "report.png"))


def test_scene_viewer_page_renders_the_scene(store, tmp_path):  # noqa: F811
    from spread.render.viewer import SceneViewer, collect

    items, library = collect(store[3])
    viewer = SceneViewer(items, library, port=free_port())
    try:
        with Browser() as browser:
            browser.open(f"http://127.0.0.1:{viewer.server.get_port()}/")
            browser.wait_for("document.querySelector('canvas') !== null")
            browser.wait_text("ground truth beside", items[0].name)
            browser.pump(4)  # meshes arrive over the websocket
            widths = browser.evaluate("Array.from(document.querySelectorAll('canvas')).map(c => c.width)")
            assert max(widths) > 600, widths  # the 3D view's WebGL canvas fills the page
            browser.screenshot(shot(tmp_path, "viewer.png"))
    finally:
        viewer.server.stop()
