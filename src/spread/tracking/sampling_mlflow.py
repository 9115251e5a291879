"""A sampling run's MLflow tags (conventions: :mod:`spread.tracking.mlflow_store`): variant and method (from the
checkpoint's hyperparameters, read without loading its weights), sampler (its label), guidance (its label, and
``spread.guidance.<term>`` for the weight of every registered term that acts: built-ins, PhyScene's, a plugin's),
seed, dataset fingerprint, and the training run of the checkpoint (lineage). Known before any work starts, so
the run opens first."""

from __future__ import annotations


def sampling_run_tags(command) -> dict:
    """Tags of a ``spread-sample`` command (a :class:`~spread.sampling.SamplingConfig` with its extras)."""
    from spread.tracking.mlflow_store import dataset_fingerprint, training_lineage
    from spread import readonce
    from spread.runtime.fingerprint import guidance_run, sampler_label
    from spread.safe_load import checkpoint_identity

    held = checkpoint_identity(readonce.checkpoint(command.ckpt))
    guidance = guidance_run(command.ckpt, command.guidance)  # what runs: the release's paper is its refinement
    tags = {"spread.variant": held["variant"], "spread.method": held["method"],
            "spread.sampler": sampler_label(command.ckpt, command.sampler), "spread.seed": command.seed,
            "spread.guidance": guidance.mode if guidance.active else "none", "spread.guidance_label": guidance.label,
            "spread.dataset_fingerprint": dataset_fingerprint(command.data.root),
            "spread.checkpoint": str(command.ckpt), "spread.split": command.data.split}
    if guidance.active:
        tags |= {f"spread.guidance.{name}": f"{weight:g}" for name, weight in guidance.weights(nonzero=True).items()}
    return tags | training_lineage(command.ckpt)
