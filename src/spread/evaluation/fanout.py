"""Scenes in chunks as Ray tasks; records handed to the driver as each task finishes.

Failure handling, in three layers:

1. A scene that cannot be measured is not a failure of the task: the worker returns a record with its
   ``error`` (:mod:`spread.evaluation.work`).
2. A task whose worker process or node dies is re-run by Ray up to ``max_retries`` times (the chunk starts
   over; nothing it did was kept, since results only come back when the whole task returns).
3. A chunk that still fails is split into one task per scene, so one scene that kills its worker (a
   physics engine crash, say) takes only itself down; a single-scene task that fails gets the record
   ``failure_record(item, exception)`` makes of it (the evaluation's says the worker died on that scene).

Each scene therefore yields exactly one record, given to ``on_record`` once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

from spread.runtime.ray import RaySettings


def chunks(items: Sequence, size: int) -> list[list]:
    """Consecutive chunks of at most ``size`` items (size ≥ 1)."""
    size = max(1, int(size))
    return [list(items[i:i + size]) for i in range(0, len(items), size)]


def task_options(settings: RaySettings) -> dict:
    """``.options(...)`` of an evaluation task: one CPU, retries on worker death, the scheduling strategy."""
    from spread.runtime.ray import scheduling_strategy

    return {"num_cpus": 1, "max_retries": int(settings.max_retries), "retry_exceptions": False,
            "scheduling_strategy": scheduling_strategy(settings)}


@dataclass
class FanOutStats:
    """tasks: tasks submitted; split_chunks: chunks that failed after retries and were split."""

    tasks: int = 0
    split_chunks: int = 0


def fan_out(paths: Sequence[str], chunk_size: int, settings: RaySettings, task: Callable, task_args: tuple,
            on_record: Callable[[dict], None], failure_record: Callable[[str, BaseException], dict]) -> FanOutStats:
    """Run ``task(chunk, *task_args) -> list[record]`` as Ray tasks over ``paths`` (module docstring).

    ``on_record`` is called on the driver for every record as its task's result arrives;
    ``failure_record(path, exception)`` makes the record of an item whose single-item task failed.
    """
    import ray

    remote = ray.remote(task).options(**task_options(settings))
    pending: dict = {}
    stats = FanOutStats()

    def submit(chunk: list[str]) -> None:
        pending[remote.remote(chunk, *task_args)] = chunk
        stats.tasks += 1

    for chunk in chunks(list(paths), chunk_size):
        submit(chunk)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            chunk = pending.pop(ref)
            try:
                records = ray.get(ref)
            except ray.exceptions.RayError as exc:
                if len(chunk) > 1:
                    stats.split_chunks += 1
                    for path in chunk:
                        submit([path])
                    continue
                records = [failure_record(chunk[0], exc)]
            for record in records:
                on_record(record)
    return stats


def run_tasks(items: Sequence, chunk_size: int, settings: RaySettings, task: Callable, task_args: tuple) -> list:
    """Results of ``task(chunk, *task_args)`` for every chunk of ``items``, with Ray's retries (no splitting)."""
    import ray

    remote = ray.remote(task).options(**task_options(settings))
    return ray.get([remote.remote(chunk, *task_args) for chunk in chunks(list(items), chunk_size)])
