"""Experiment tracking, in one package: which logger a run uses (wandb, MLflow, CSV, none), and what each command
logs there.

| module | job |
|---|---|
| :mod:`~spread.tracking.config` | :class:`LoggerConfig`: the logger node of every command's config, wandb's default mode, resumed wandb ids |
| :mod:`~spread.tracking.loggers` | the one logger factory: Lightning's loggers of a training run, a command's wandb run and its folder |
| :mod:`~spread.tracking.mlflow_store` | runs in a local MLflow store: tags, params, metrics with intervals, artifacts, lineage; the dashboard's store |
| :mod:`~spread.tracking.sampling_wandb` | a sampling run on wandb: counts, timings, renders, tags |
| :mod:`~spread.tracking.sampling_mlflow` | a sampling run's MLflow tags (variant, sampler, guidance, lineage) |
| :mod:`~spread.tracking.evaluation_wandb` | an evaluation's metrics and per-scene table with renders on wandb |

wandb and MLflow are imported inside the functions that use them.
"""
