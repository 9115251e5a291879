"""Independent stages of an ablation or comparison at the same time, as Ray tasks (``max_concurrent`` at once).

A **chain** is a list of steps ``(name, method, key, needs)`` that must run in order (a row's ``sample/<v>``
then its ``evaluate/<v>``; ``runner.<method>(key)`` builds the step's stage); chains are independent of one
another. :func:`run_chains` runs each chain as one Ray task
(``num_cpus=0``: the task only drives its commands; their sampling actors and evaluation tasks reserve the
CPUs/GPUs, on any node of the cluster), at most ``max_concurrent`` chains at a time, in the order given.

The ledger stays the driver's: a task decides re-use against a snapshot of the ledger's entries
(:class:`LedgerView`) and returns what it would record; the driver records it. Each entry carries the wall-clock
``started_at`` / ``ended_at`` (Unix seconds) of the stage's work. A task that dies (its worker killed) fails
its chain's steps that had not reported, and the other chains go on. Workers run in the driver's working
directory, so relative ``out_dir`` paths mean the same in both.
"""

from __future__ import annotations

import os
import time
Step = tuple  # (name, method: str, key: str, needs: list[str])


class LedgerView:
    """A stand-in for :class:`~spread.experiments.ablation.Ledger` inside a task: reads the driver's entries,
    collects the records (:meth:`replay` writes them in the driver)."""

    def __init__(self, stages: dict):
        self.data = {"stages": stages}
        self.records: list[dict] = []

    def inputs(self, name: str) -> dict | None:
        entry = self.data["stages"].get(name)
        return None if entry is None else entry["inputs"]

    def record(self, name: str, inputs: dict, seconds: float | None, reason: str | None = None, **more) -> None:
        from spread.runtime.fingerprint import run_tags

        self.records.append({"name": name, "inputs": inputs, "seconds": seconds, "reason": reason,
                             "tags": run_tags(), **more, "ended_at": more.get("ended_at") or time.time()})


def run_chain(runner, chain: list[Step], cwd: str) -> dict:
    """One chain in a Ray task: every step through ``runner.attempt`` against a view of the ledger."""
    os.chdir(cwd)
    runner.ledger = LedgerView(runner.ledger.data["stages"])
    names = [step[0] for step in chain]
    for step in chain:
        attempt(runner, *step)
    return {"status": {n: runner.status[n] for n in names if n in runner.status},
            "errors": {n: runner.errors[n] for n in names if n in runner.errors},
            "records": runner.ledger.records, "state": runner.worker_state(names)}


def attempt(runner, name: str, method: str, key: str, needs: list[str]) -> bool:
    return runner.attempt(name, lambda: getattr(runner, method)(key), needs)


def run_chains(runner, chains: list[list[Step]], max_concurrent: int, ray_settings=None) -> dict:
    """Run ``chains`` (module docstring) for ``runner`` (an :class:`~spread.experiments.ablation.Ablation`):
    one after another in this process when ``max_concurrent`` ≤ 1 (all chains' first steps, then their
    second steps), else as Ray tasks. Returns ``{"mode", "max_concurrent", ...}`` (the cluster when on Ray)."""
    chains = [c for c in chains if c]
    if int(max_concurrent) <= 1 or len(chains) <= 1:
        for depth in range(max((len(c) for c in chains), default=0)):
            for chain in chains:
                if depth < len(chain):
                    attempt(runner, *chain[depth])
        return {"mode": "sequential", "max_concurrent": 1}
    import ray

    from spread.runtime.ray import RaySettings, ray_session

    with ray_session(ray_settings or RaySettings()) as cluster:
        task = ray.remote(num_cpus=0, max_retries=0)(run_chain)
        queue, running, cwd = list(chains), {}, os.getcwd()
        while queue or running:
            while queue and len(running) < int(max_concurrent):
                chain = queue.pop(0)
                running[task.remote(runner, chain, cwd)] = chain
            done, _ = ray.wait(list(running), num_returns=1)
            chain = running.pop(done[0])
            try:
                merge(runner, ray.get(done[0]))
            except Exception as exc:  # noqa: BLE001 - the task itself died: its steps fail, the rest go on
                for name, *_ in chain:
                    runner.status.setdefault(name, "failed")
                    runner.errors.setdefault(name, f"{name}: its task died: {type(exc).__name__}: {exc}")
    return {"mode": "ray", "max_concurrent": int(max_concurrent), **cluster}


def merge(runner, result: dict) -> None:
    """A chain's outcome into the driver: statuses, errors, ledger entries, the runner's own state."""
    runner.status.update(result["status"])
    runner.errors.update(result["errors"])
    for record in result["records"]:
        runner.ledger.record(**record)
    runner.merge_worker_state(result["state"])


def overlap(entries: dict, a: str, b: str) -> float:
    """Seconds during which ledger entries ``a`` and ``b`` ran at the same time (0 when one after the other)."""
    ea, eb = entries[a], entries[b]
    return max(0.0, min(ea["ended_at"], eb["ended_at"]) - max(ea["started_at"], eb["started_at"]))

