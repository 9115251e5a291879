"""Where features meet (issue 31): small things a user trips on, each where the user meets it."""

import warnings
from types import SimpleNamespace

import pytest

from spread.guidance import GuidanceConfig
from spread.sampling.worker import warn_graph_guidance


@pytest.mark.parametrize("method, warned", [("diffuscene", True), ("atiss", True), ("spread", False),
                                            ("instructscene", False)])
def test_relation_guidance_on_a_method_not_trained_with_graphs_is_said(method, warned):
    model = SimpleNamespace(hparams={"method": method})
    guided = GuidanceConfig(mode="paper", relation=1e-3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_graph_guidance(guided, model, "x.ckpt")
        warn_graph_guidance(GuidanceConfig(mode="paper", relation=0.0), model, "x.ckpt")  # no relation: silent
    said = [w for w in caught if "not trained with the graphs" in str(w.message)]
    assert len(said) == (1 if warned else 0)
    if warned:
        assert f"'{method}'" in str(said[0].message) and "guidance.relation=0" in str(said[0].message)


def _shown_ticks(axis):
    low, high = sorted(axis.get_view_interval())
    return [t for t, at in zip(axis.get_ticklabels(), axis.get_majorticklocs())
            if t.get_visible() and t.get_text() and low - 1e-12 <= at <= high + 1e-12]


@pytest.mark.parametrize("weights", [[0.0075], [0.0075, 0.0075], [0.0, 0.0025, 0.005, 0.0075, 0.01, 0.0125, 0.015]])
def test_metric_vs_weight_plots_have_plain_non_overlapping_tick_labels_even_for_one_point(tmp_path, weights,
                                                                                           monkeypatch):
    import spread.reporting.plots as plots
    from spread.reporting.tables import value_column

    kept = {}
    real_save = plots.save
    monkeypatch.setattr(plots, "save", lambda fig, path, dpi=110: kept.setdefault("fig", fig) and real_save(fig, path))
    runs = [{"guidance.collision": w, "asd": 0.0123 + 0.001 * i} for i, w in enumerate(weights)]
    asd = value_column("asd")
    points = plots.metric_vs_weight(runs, asd, "guidance.collision", tmp_path / "vs.png")
    assert len(points) == len(weights)
    fig = kept["fig"]
    ax = fig.axes[0]
    fig.canvas.draw()
    for axis in (ax.xaxis, ax.yaxis):
        assert axis.get_offset_text().get_text() == ""  # no "1e-3 +" or "×10⁻³" corner text
        ticks = _shown_ticks(axis)
        labels = [t.get_text() for t in ticks]
        assert 2 <= len(labels) <= 6 and len(set(labels)) == len(labels), labels  # distinct, readable ticks
        boxes = [t.get_window_extent(fig.canvas.get_renderer()) for t in ticks]
        assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:]), labels
    low, high = ax.get_xlim()
    assert low < min(weights) <= max(weights) < high and high - low > 0
    assert (tmp_path / "vs.png").stat().st_size > 0


def test_a_hydra_launcher_whose_plugin_is_missing_is_named_with_the_package_to_install(monkeypatch):
    import importlib.util
    import sys

    from spread.cli.errors import LAUNCHERS, command, launcher_problem

    assert all(launcher_problem(name) is None for name in LAUNCHERS)  # make installs both
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == LAUNCHERS["parallel"][0] else real(name, *a))
    monkeypatch.setattr(sys, "argv", ["spread-sample", "-m", "hydra/launcher=parallel", "seed=1,2"])
    ran = []
    with pytest.raises(SystemExit, match=r"spread-sample: hydra/launcher=parallel needs the Hydra launcher plugin "
                                         r"hydra-joblib-launcher.*pip install -e '\.\[launchers\]'"):
        command("spread-sample")(lambda: ran.append(1))()
    assert not ran
