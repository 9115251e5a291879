"""Sampling a checkpoint on a split's graphs: scene files out, Ray fan-out, resume (DESIGN §5 ``spread-sample``).

| module | job |
|---|---|
| :mod:`~spread.sampling.plan` | graphs, per-sample seeds from (seed, scene id, k), fixed batches, resume checks |
| :mod:`~spread.sampling.worker` | one model + encoder: a batch → generated scene files (provenance extras) |
| :mod:`~spread.sampling.run` | one run: :func:`run_sampling` (Ray actors or in-process, renders, sampling.json) |

torch, Lightning and Ray are imported inside the functions that use them.
"""

from spread.sampling.plan import BatchPlan, Graph, SampleItem, batch_seed, plan_batches, sample_seed  # noqa: F401
from spread.sampling.run import SamplingConfig, SamplingResult, list_graphs, run_sampling  # noqa: F401
