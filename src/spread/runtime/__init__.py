"""What every stage needs to run: a Ray session for one command run, and experiment tracking.

| module | job |
|---|---|
| :mod:`~spread.runtime.ray` | :class:`RaySettings` and :func:`ray_session`: start or join Ray, leave it as found |
| :mod:`~spread.runtime.tracking` | :class:`LoggerConfig`, the one logger factory (wandb / MLflow / CSV / none), wandb conventions |
| :mod:`~spread.runtime.mlflow_log` | runs in a local MLflow store: tags, params, metrics with intervals, artifacts, lineage |

Ray, wandb and MLflow are imported inside the functions that use them.
"""

from spread.runtime.ray import RaySettings, ray_session  # noqa: F401
from spread.runtime.tracking import LoggerConfig  # noqa: F401
