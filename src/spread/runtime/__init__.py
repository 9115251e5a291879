"""What every stage needs to run: a Ray session for one command run, the identities of results and the one
done-check, quiet logs.

| module | job |
|---|---|
| :mod:`~spread.runtime.ray` | :class:`RaySettings` and :func:`ray_session`: start or join Ray, leave it as found, stop what a killed run left |
| :mod:`~spread.runtime.fingerprint` | identities of samples, evaluations and sweep points; the done-check; the settings reports name |
| :mod:`~spread.runtime.quiet` | known noise of Ray, Lightning and wandb silenced at its source |

Experiment tracking (wandb, MLflow, CSV) is :mod:`spread.tracking`. Ray is imported inside the functions that use it.
"""

from spread.runtime.ray import RaySettings, ray_session  # noqa: F401
