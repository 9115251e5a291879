"""Independent stages of an ablation or comparison at the same time, as Ray tasks (``max_concurrent`` at once).

A **chain** is a list of steps ``(name, method, key, needs)`` that must run in order (a row's ``sample/<v>``
then its ``evaluate/<v>``; a training stage ``train/<t>`` alone; ``runner.<method>(key)`` builds the step's
stage); chains are independent of one another. A **job** is a chain with the runner (a
:class:`~spread.experiments.stages.StageEngine`) whose stages it runs: :func:`run_jobs` takes the jobs of one
runner or of several (a seeded ablation's seeds share one pool). Each chain runs as one Ray task, at most
``max_concurrent`` at a time, in the order given, with ``resources`` per task: sample → evaluate chains take
``num_cpus=0`` (the task only drives its commands; their sampling actors and evaluation tasks reserve the
CPUs/GPUs, on any node of the cluster); a training stage takes what one training needs
(``stages.train_cpus`` / ``stages.train_gpus``: on a multi-GPU node each training task gets a GPU of its own,
Ray sets its ``CUDA_VISIBLE_DEVICES``), so the training stages of a whole study run side by side. A task that
asks for more than the whole cluster has would wait for ever: its steps fail instead, saying so.

A stage that holds Ray actors while it waits for more (``Stage.exclusive``: sampling with ``workers`` > 0)
takes the pool's one **slot** for its work: two such stages side by side could each hold part of the CPUs/GPUs
and wait for the rest forever. Stages of in-process sampling (``workers=0``) and evaluations (Ray tasks, which
never hold resources while they wait) run side by side freely.

The ledger stays the driver's: a task decides re-use against a snapshot of the ledger's entries
(:class:`LedgerView`) and returns what it would record; the driver records it. Each entry carries the wall-clock
``started_at`` / ``ended_at`` (Unix seconds) of the stage's work. A task that dies (its worker killed) fails
its chain's steps (a stage's own error is caught in the task and reported like in this process), and the
other chains go on. Workers run in the driver's working directory, so relative ``out_dir`` paths mean the same
in both.
"""

from __future__ import annotations

import contextlib
import os
import time

from spread.experiments.begun import mark_begun, read_begun

Step = tuple  # (name, method: str, key: str, needs: list[str])


class LedgerView:
    """A stand-in for :class:`~spread.experiments.stages.Ledger` inside a task: reads the driver's entries,
    collects the records (:func:`merge` writes them in the driver's ledger); a stage's begun-with inputs it writes
    itself (one file per stage, :mod:`spread.experiments.begun`), so a driver stopped mid-task
    leaves them."""

    def __init__(self, stages: dict, path=None):
        self.data = {"stages": stages}
        self.records: list[dict] = []
        self.path = path

    def begin(self, name: str, inputs: dict) -> None:
        if self.path is not None:
            mark_begun(self.path, name, inputs)

    def begun(self, name: str) -> dict | None:
        return None if self.path is None else read_begun(self.path, name)

    def inputs(self, name: str) -> dict | None:
        entry = self.data["stages"].get(name)
        return None if entry is None else entry["inputs"]

    def record(self, name: str, inputs: dict, seconds: float | None, reason: str | None = None, **more) -> None:
        from spread.runtime.fingerprint import run_tags

        self.records.append({"name": name, "inputs": inputs, "seconds": seconds, "reason": reason,
                             "tags": run_tags(), **more, "ended_at": more.get("ended_at") or time.time()})


class Slot:
    """A Ray actor lent to one holder at a time (:func:`held`)."""

    def __init__(self):
        self.holder = None

    def take(self, holder: str) -> bool:
        if self.holder is None:
            self.holder = holder
        return self.holder == holder

    def give_back(self, holder: str) -> None:
        if self.holder == holder:
            self.holder = None


@contextlib.contextmanager
def held(slot):
    """``slot`` held for the block (polled every 0.2 s); ``None``: nothing to hold."""
    if slot is None:
        yield
        return
    import ray

    me = f"{os.getpid()}:{time.time()}"
    while not ray.get(slot.take.remote(me)):
        time.sleep(0.2)
    try:
        yield
    finally:
        ray.get(slot.give_back.remote(me))


def run_chain(runner, chain: list[Step], cwd: str) -> dict:
    """One chain in a Ray task: every step through ``runner.attempt`` against a view of the ledger."""
    os.chdir(cwd)
    runner.ledger = LedgerView(runner.ledger.data["stages"], getattr(runner.ledger, "path", None))
    names = [step[0] for step in chain]
    for step in chain:
        attempt(runner, *step)
    return {"status": {n: runner.status[n] for n in names if n in runner.status},
            "errors": {n: runner.errors[n] for n in names if n in runner.errors},
            "records": runner.ledger.records, "state": runner.worker_state(names)}


def attempt(runner, name: str, method: str, key: str, needs: list[str]) -> bool:
    return runner.attempt(name, lambda: getattr(runner, method)(key), needs)


def run_jobs(jobs: list[tuple], max_concurrent: int, ray_settings=None, resources: dict | None = None,
             owner=None) -> dict:
    """Run ``jobs`` (``(runner, chain)`` pairs, module docstring): one after another in this process when
    ``max_concurrent`` ≤ 1 (all chains' first steps, then their second steps), else as Ray tasks with
    ``resources`` each (Ray's ``num_cpus`` / ``num_gpus``; None: ``num_cpus=0``), the Ray session recorded in
    ``owner`` (the study's folder). Returns ``{"mode", "max_concurrent", ...}`` (the cluster when on Ray)."""
    pending = []
    for runner, chain in ((r, c) for r, c in jobs if c):  # steps finished earlier with these inputs: skipped here
        rest = list(chain)
        while rest and int(max_concurrent) > 1 and runner.finished_already(*rest[0]):
            attempt(runner, *rest.pop(0))
        if rest:
            pending.append((runner, rest))
    if int(max_concurrent) <= 1 or len(pending) <= 1:
        for depth in range(max((len(c) for _, c in pending), default=0)):
            for runner, chain in pending:
                if depth < len(chain):
                    attempt(runner, *chain[depth])
        return {"mode": "sequential", "max_concurrent": 1}
    import ray

    from spread.runtime.ray import RaySettings, ray_session

    runners = list({id(r): r for r, _ in pending}.values())
    with ray_session(ray_settings or RaySettings(), owner=owner) as cluster:
        asked = task_resources(resources)
        missing = misfit(asked)
        if missing:  # such a task would wait for ever: its steps fail, named, and the study goes on
            fail(pending, missing)
            return {"mode": "ray", "max_concurrent": int(max_concurrent), **cluster}
        task = ray.remote(max_retries=0, **asked)(run_chain)
        slot = ray.remote(num_cpus=0)(Slot).remote()
        for runner in runners:
            runner.slot = slot
        try:
            drive(pending, task, int(max_concurrent))
        finally:
            ray.kill(slot)
            for runner in runners:
                runner.slot = None
    return {"mode": "ray", "max_concurrent": int(max_concurrent), **cluster}


def task_resources(resources: dict | None) -> dict:
    """Ray's ``num_cpus`` / ``num_gpus`` of one chain task (None or 0 GPUs: none asked)."""
    resources = dict(resources or {"num_cpus": 0})
    out = {"num_cpus": float(resources.get("num_cpus") or 0)}
    if resources.get("num_gpus"):
        out["num_gpus"] = float(resources["num_gpus"])
    return out


def misfit(asked: dict) -> str:
    """Why a task asking ``asked`` (Ray's ``num_cpus`` / ``num_gpus``) cannot run on the cluster as it is
    (more than all its nodes hold together; "" when it fits)."""
    import ray

    total = ray.cluster_resources()
    short = [f"{asked[key]:g} {name}" for key, name in (("num_cpus", "CPU"), ("num_gpus", "GPU"))
             if asked.get(key, 0) > total.get(name, 0.0)]
    if not short:
        return ""
    return (f"each stage asks for {' and '.join(short)} (stages.train_cpus / stages.train_gpus) but the Ray "
            f"cluster has {total.get('CPU', 0.0):g} CPU and {total.get('GPU', 0.0):g} GPU")


def fail(jobs: list[tuple], message: str) -> None:
    """Every step of ``jobs`` failed with ``message``."""
    for runner, chain in jobs:
        for name, *_ in chain:
            runner.status[name] = "failed"
            runner.errors[name] = f"{name}: {message}"


def drive(jobs: list[tuple], task, max_concurrent: int) -> None:
    """Keep ``max_concurrent`` chain tasks running until every job ``(runner, chain)`` has reported."""
    import ray

    queue, running, cwd = list(jobs), {}, os.getcwd()
    while queue or running:
        while queue and len(running) < max_concurrent:
            runner, chain = queue.pop(0)
            running[task.remote(runner, chain, cwd)] = (runner, chain)
        done, _ = ray.wait(list(running), num_returns=1)
        runner, chain = running.pop(done[0])
        try:
            merge(runner, ray.get(done[0]))
        except Exception as exc:  # noqa: BLE001 - the task itself died: its steps fail, the rest go on
            for name, *_ in chain:
                runner.status.setdefault(name, "failed")
                runner.errors.setdefault(name, f"{name}: its task died: {type(exc).__name__}: {exc}")


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

