"""Sampling (``spread-sample``, DESIGN §5): a checkpoint on a split's graphs → scene files; Ray fan-out, resume.

| module | job |
|---|---|
| :mod:`~spread.sampling.pipeline` | :class:`ScenePipeline`: encode → sample with callbacks (guidance) → decode poses |
| :mod:`~spread.sampling.plan` | graphs, per-sample seeds from (seed, scene id, k), fixed batches, resume checks |
| :mod:`~spread.sampling.worker` | one pipeline per worker: a batch → generated scene files (provenance extras) |
| :mod:`~spread.sampling.run` | one run: :class:`SamplingConfig`, :func:`run_sampling` (Ray actors or in-process) |

torch, Lightning and Ray are imported by the modules and functions that use them.
"""

from spread.sampling.plan import BatchPlan, Graph, SampleItem, batch_seed, plan_batches, sample_seed  # noqa: F401
from spread.sampling.run import DataSplit, SamplingConfig, SamplingResult, list_graphs, run_sampling  # noqa: F401
