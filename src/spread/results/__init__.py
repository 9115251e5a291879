"""Results a researcher can query: any run, sweep, ablation or comparison folder, or an MLflow store, as one
pandas DataFrame, and the questions asked of it.

| function | answers |
|---|---|
| :func:`load` (:mod:`~spread.results.load`) | one row per run: every setting of its identity a column, every metric with its interval (stored units) |
| :func:`display` | the same frame in display units (ASD in mm, ``asd_mm``) |
| :func:`over_seeds` (:mod:`~spread.results.stats`) | per point: mean over seeds, 95 % Student-t interval, n seeds |
| :func:`paired_difference` | is point A better than B: paired per-scene difference on the same graphs and seeds, bootstrap interval |
| :func:`importance` | which setting explains the metric's variance over a sweep (one-way η²) |
| :func:`pareto` | the Pareto front over two metrics (Col_mesh ↓ vs GRecall ↑) |
| :func:`stopped_trials` (:mod:`~spread.results.tune`) | the trials ASHA stopped early, with the step |
| :mod:`~spread.results.analysis` | the analysis section ``spread-report`` adds for a sweep folder |

Reads only what the commands wrote (through :mod:`spread.reporting.runs`); imports no command, study or CLI.
"""

from __future__ import annotations

from spread.results.frame import display
from spread.results.load import load
from spread.results.stats import importance, over_seeds, paired_difference, pareto
from spread.results.tune import stopped_trials, trials

__all__ = ["display", "importance", "load", "over_seeds", "paired_difference", "pareto", "stopped_trials", "trials"]
