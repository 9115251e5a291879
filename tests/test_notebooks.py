"""The notebooks run from a fresh clone: each is executed top to bottom in a fresh kernel in its fast mode
(``SPREAD_NOTEBOOK_FAST=1``: a dozen rooms, a few training steps, 4 sampling steps), writing under a temporary
folder; a cell that raises fails the test with the cell's traceback.

* ``01_quickstart``: generate, train, sample, evaluate.
* ``02_results``: makes a tiny ablation and a 3-point guidance sweep itself (fast mode), then shows the table,
  the sweep report's plots, the sweep queried through ``spread.results`` (importance, Pareto front, a paired
  difference), before/after-physics renders (top-down and 3D) and one graph's rows in 3D with
  their relation matrices."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def execute(name: str, out: Path) -> "object":
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    env = {"SPREAD_NOTEBOOK_FAST": "1", "SPREAD_NOTEBOOK_OUT": str(out), "WANDB_MODE": "disabled"}
    old = {k: os.environ.get(k) for k in [*env, "MPLBACKEND"]}
    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend, so figures become outputs
    os.environ.update(env)  # the kernel inherits this process's environment
    try:
        NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(out)}}).execute()
    finally:
        for k, v in old.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
    return nb


def outputs_text(nb) -> str:
    return "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))


@pytest.fixture(scope="module")
def quickstart(tmp_path_factory):
    out = tmp_path_factory.mktemp("notebooks")
    return execute("01_quickstart.ipynb", out), out


@pytest.mark.slow  # ~60 s on 2 cores (a kernel that generates, trains, samples, evaluates): make test-slow runs it
def test_quickstart_runs_and_evaluates_generated_scenes(quickstart):
    nb, out = quickstart
    text = outputs_text(nb)
    assert "global step 4" in text
    assert (out / "quickstart" / "samples" / "sampling.json").exists()
    for name in ("ground_truth", "generated"):
        assert (out / "quickstart" / "eval" / name / "metrics.json").exists()
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) >= 5  # the 2D/3D room, the loss curve, ground truth | generated, 3D card, before | after
    renders = out / "quickstart" / "samples" / "renders"
    assert len(list(renders.glob("*_3d.png"))) == 1 and len(list(renders.glob("*_physics.png"))) == 1


def image_outputs(cell) -> list:
    return [o for o in cell.get("outputs", []) if "image/png" in o.get("data", {})]


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_results_notebook_runs_on_a_fresh_tiny_ablation_and_sweep(tmp_path):
    from spread.reporting.tables import read_csv

    nb = execute("02_results.ipynb", tmp_path)
    out = tmp_path / "results"
    rows = read_csv(out / "ablate_tiny" / "ablation.csv")
    assert [r["variant"] for r in rows] == ["base", "geometry", "guidance"]
    assert all(r["status"] == "ok" and r["n_scenes"] >= 1 for r in rows), rows
    assert all((out / "ablate_tiny" / f"ablation.{s}").exists() for s in ("md", "tex", "png"))
    assert len(read_csv(out / "report" / "report.csv")) == 3  # the three sweep points
    assert len(list((out / "report" / "plots").glob("*_vs_*.png"))) >= 1
    assert len(list((out / "renders").glob("*_before_after.png"))) >= 2
    assert len(list((out / "renders").glob("*_physics_3d.png"))) == 2  # geometry and guidance rows, in 3D
    assert all((out / "ablate_tiny" / f"ablation_{k}.png").exists() for k in ("truth", "base", "geometry", "guidance"))
    text = outputs_text(nb)
    assert "+Guidance" in "\n".join(o.get("data", {}).get("text/markdown", "") for c in nb.cells
                                    for o in c.get("outputs", []))
    assert "best: c" in text
    assert "Pareto front (Col_mesh ↓, GRecall ↑)" in text and "importance (η², GRecall)" in text  # spread.results
    cells = [c for c in nb.cells if c.cell_type == "code"]
    before_after = [c for c in cells if "render_before_after(" in c.source]
    assert before_after and image_outputs(before_after[0])  # the before | after sheet, inline
    assert sum(len(image_outputs(c)) for c in cells) >= 4  # bar plot, sweep plots, before/after, gt | geometry | guidance
