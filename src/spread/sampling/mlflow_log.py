"""A sampling run's MLflow tags (conventions: :mod:`spread.runtime.mlflow_log`): variant and method (from the
checkpoint's hyperparameters, read without loading its weights), sampler, guidance mode and weights, seed,
dataset fingerprint, and the training run of the checkpoint (lineage). Known before any work starts, so the
run opens first."""

from __future__ import annotations


def sampling_run_tags(command) -> dict:
    """Tags of a ``spread-sample`` command (a :class:`~spread.sampling.SamplingConfig` with its extras)."""
    from spread.runtime.mlflow_log import dataset_fingerprint, training_lineage
    from spread import readonce
    from spread.sampling.run import guidance_settings
    from spread.sampling.worker import sampler_label

    hp = readonce.checkpoint(command.ckpt).get("hyper_parameters", {})
    guidance = guidance_settings(command.guidance)
    tags = {"spread.variant": hp.get("variant"), "spread.method": hp.get("method", "spread"),
            "spread.sampler": sampler_label(command.sampler), "spread.seed": command.seed,
            "spread.guidance": guidance["mode"] if guidance else "none",
            "spread.dataset_fingerprint": dataset_fingerprint(command.data.root),
            "spread.checkpoint": str(command.ckpt), "spread.split": command.data.split}
    if guidance:
        tags |= {f"spread.guidance.{k}": f"{guidance[k]:g}" for k in ("collision", "gravity", "relation")}
    return tags | training_lineage(command.ckpt)
