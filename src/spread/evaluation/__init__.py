"""Evaluation (``spread-evaluate``, DESIGN §5, §6): scene files → per-scene records → ``metrics.json``.

| module | job |
|---|---|
| :mod:`~spread.evaluation.protocol` | :class:`EvalProtocol`, :class:`FIDConfig`: every parameter behind a value; versions |
| :mod:`~spread.evaluation.work` | worker side: scene file → per-scene record with metric states |
| :mod:`~spread.evaluation.fanout` | items in chunks as Ray tasks, retries, splitting of failed chunks |
| :mod:`~spread.evaluation.resume` | ``per_scene.jsonl``: finished scenes, deduplicated, torn line dropped |
| :mod:`~spread.evaluation.aggregate` | records → metrics through torchmetrics ``merge_state`` |
| :mod:`~spread.evaluation.bootstrap` | confidence intervals: a bootstrap over scenes of the pooled ratios |
| :mod:`~spread.evaluation.run` | one run: :class:`EvaluationConfig`, :func:`run_evaluation` writes ``metrics.json`` etc. |

Ray, wandb and pybullet are imported inside the functions that use them.
"""

from spread.lazy import lazy_names

#: Every public name and the module that defines it, imported on first access (PEP 562): the protocol
#: (:class:`EvalProtocol`) loads without torch and torchmetrics.
_EXPORTS = {
    "spread.evaluation.bootstrap": ("bootstrap_intervals", "interval_note"),
    "spread.evaluation.protocol": ("STABILITY_SUBSTEPS", "EvalProtocol", "FIDConfig", "versions"),
    "spread.evaluation.run": ("EvaluationConfig", "EvaluationResult", "run_evaluation"),
}
__getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
