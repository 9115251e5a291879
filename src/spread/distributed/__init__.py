"""Ray fan-out of the evaluation with retries and resume (DESIGN §5 ``spread-evaluate``, §7).

| module | job |
|---|---|
| :mod:`~spread.distributed.protocol` | :class:`EvalProtocol`: every parameter behind a metric value, versions |
| :mod:`~spread.distributed.work` | worker side: scene file → per-scene record with metric states |
| :mod:`~spread.distributed.fanout` | scenes in chunks as Ray tasks, retries, splitting of failed chunks |
| :mod:`~spread.distributed.session` | start / join Ray for one run and leave it as found |
| :mod:`~spread.distributed.resume` | ``per_scene.jsonl``: finished scenes, deduplicated, torn line dropped |
| :mod:`~spread.distributed.aggregate` | records → metrics through torchmetrics ``merge_state`` |
| :mod:`~spread.distributed.evaluation` | one run: :func:`run_evaluation` writes ``metrics.json`` etc. |
| :mod:`~spread.distributed.wandb_report` | metrics and a per-scene table with renders on wandb |

Ray, wandb and pybullet are imported inside the functions that use them.
"""

from spread.distributed.evaluation import EvaluationConfig, EvaluationResult, run_evaluation  # noqa: F401
from spread.distributed.protocol import STABILITY_SUBSTEPS, EvalProtocol, versions  # noqa: F401
from spread.distributed.session import RaySettings, ray_session  # noqa: F401
