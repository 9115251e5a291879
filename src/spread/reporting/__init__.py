"""Reporting: what the platform shows of finished runs — the one table writer, plots, intervals, run folders read
back, the HTML report and ``spread-report``'s body.

| module | what |
|---|---|
| :mod:`~spread.reporting.tables` | the one table writer: Markdown, CSV, LaTeX, HTML and wandb rows, each metric in its registered display unit |
| :mod:`~spread.reporting.plots` | bar charts, metric-vs-setting plots, parallel coordinates (display units on the axes) |
| :mod:`~spread.reporting.intervals` | bootstrap intervals of a run folder's per-scene lines, per row and per group |
| :mod:`~spread.reporting.runs` | run folders, wandb runs and MLflow stores read back as records with their identity |
| :mod:`~spread.reporting.report` | ``spread-report``: tables and plots of many runs, every differing setting named per run |
| :mod:`~spread.reporting.html_report` | the self-contained ``report.html`` |
| :mod:`~spread.reporting.wandb_table` | the ablation table on wandb |
"""
