"""Multi-run studies over the platform's commands (DESIGN §5): the ablation, the comparison (Table 1) and the
sweep, and the resumable stage engine the ablation and the comparison each hold. Sits between the command bodies
(:mod:`spread.commands`, which run a study with their commands injected) and reporting (:mod:`spread.reporting`).

| module | job |
|---|---|
| :mod:`~spread.experiments.stages` | the stage engine: stages, the ledger, resume by the done-check, failures that block only what needs them |
| :mod:`~spread.experiments.stage_pool` | the rows' independent stage chains as Ray tasks, ``max_concurrent`` at a time |
| :mod:`~spread.experiments.ablation` | the ablation's rows (base, +geometry, +guidance, one term at a time), its table and figures |
| :mod:`~spread.experiments.ablation_seeds` | the ablation over several training seeds: mean ± sd beside the bootstrap |
| :mod:`~spread.experiments.compare` | Table 1: the registered methods as rows, budgets, per-room-type layout |
| :mod:`~spread.experiments.sweep` | sweeps on Ray Tune: the plan, trials, the results table |
| :mod:`~spread.experiments.tuning` | sweep searchers and trial schedulers by registered name or ``module:Class`` |
| :mod:`~spread.experiments.points` | a sweep point's ``point.json``: its identity and the done-check's decision |

matplotlib, wandb, torch and Ray are imported inside the functions that use them.
"""
