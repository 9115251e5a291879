"""Experiments over the platform's commands: the commands themselves as library functions, the ablation
table, sweeps and reports (DESIGN §5 ``spread-ablate``, ``spread-report``). Sits between :mod:`spread.cli` and
the stages (:mod:`spread.procgen`, :mod:`spread.training`, :mod:`spread.sampling`, :mod:`spread.evaluation`).

| module | job |
|---|---|
| :mod:`~spread.experiments.commands` | generate / train / sample / evaluate on a composed config; console summaries |
| :mod:`~spread.experiments.ablation` | the ablation's stages (generate … table), ledger, resume |
| :mod:`~spread.experiments.runs` | run folders and wandb offline runs → flat records; ``runs`` argument expansion |
| :mod:`~spread.experiments.report` | records → comparison table (md/csv) and metric-vs-weight plots |
| :mod:`~spread.experiments.html_report` | the report as one self-contained HTML page; training runs' curves |
| :mod:`~spread.experiments.tables` | Markdown / CSV / LaTeX writers, CSV reader (exact round trip) |
| :mod:`~spread.experiments.plots` | bar plot of the ablation, metric-vs-weight scatter plots (Agg) |
| :mod:`~spread.experiments.wandb_table` | the ablation table as a wandb Table (offline by default) |

matplotlib, wandb, torch and Ray are imported inside the functions that use them.
"""

from spread.experiments.ablation import AblationResult, AblationSpec, Commands, run_ablation  # noqa: F401
from spread.experiments.report import ReportResult, print_report, run_report, runs_argument  # noqa: F401
from spread.experiments.runs import RunError, find_runs, is_finished_run, read_runs  # noqa: F401
