"""Training (``spread-train``, ``spread-train-ray``; DESIGN §5, §7): fit one variant or baseline with Lightning.

| module | job |
|---|---|
| :mod:`~spread.training.fit` | :func:`train`: data module + model + trainer from the config, loggers, run folder, summary |
| :mod:`~spread.training.checkpoints` | atomic checkpoint writes, the final checkpoint, which one a run resumes |
| :mod:`~spread.training.clock` | steps, scenes seen and training seconds of every checkpoint (``clock.jsonl``, wandb) |
| :mod:`~spread.training.monitors` | learning rate and gradient norm curves |
| :mod:`~spread.training.renders` | sampled validation scenes as images every few epochs (MLflow, wandb) |
| :mod:`~spread.training.ray_train` | the same :func:`train` on Ray Train workers (``RayDDPStrategy``) |

Lightning and Ray are imported by the modules that need them; ``import spread.training`` stays light.
"""


def __getattr__(name: str):
    if name in ("train", "run_folder", "set_threads"):
        from spread.training import fit

        return getattr(fit, name)
    raise AttributeError(f"module 'spread.training' has no attribute '{name}'")
