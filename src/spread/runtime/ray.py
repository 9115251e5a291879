"""Ray for one command run: start a local in-process cluster, or join one; always leave it as found.

* ``address=None`` (or ``"local"``): ``ray.init(num_cpus=...)`` starts a private local cluster for this
  process (its own raylet and workers, no dashboard) and ``ray.shutdown()`` stops exactly that at the end.
* ``address="auto"`` or ``"HOST:PORT"``: join a running cluster (``ray start`` on the nodes, or
  ``ray.cluster_utils.Cluster`` in tests); the end only disconnects this driver, the cluster stays.
* Ray already initialised by the caller (a notebook, a test): used as is and left running.

Workers must import ``spread`` and read the scene and dataset folders: on a real cluster, install the
project on every node and keep the folders on a shared filesystem.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator


@dataclass
class RaySettings:
    """address: None / "local" (start one), "auto" or "HOST:PORT" (join); num_cpus: CPUs of a started
    cluster (None: all); max_retries: re-runs of a task whose worker or node dies; scheduling_strategy:
    "SPREAD" (chunks over all nodes) or "DEFAULT" (pack); log_to_driver: echo worker output here;
    object_store_memory: bytes for a started cluster; num_gpus_per_worker: GPUs of each sampling actor.
    The defaults are ``conf/ray/local.yaml``'s (registered as the ``ray`` group's base, :mod:`spread.configs`)."""

    address: str | None = None
    num_cpus: int | None = None
    max_retries: int = 3
    scheduling_strategy: str = "SPREAD"
    log_to_driver: bool = False
    object_store_memory: int | None = 256 * 1024 * 1024  # bytes, for a started cluster
    num_gpus_per_worker: float = 0.0  # GPUs each sampling actor reserves (evaluation tasks use none)

    @property
    def starts_cluster(self) -> bool:
        return self.address in (None, "", "local")


def _start(settings: RaySettings) -> None:
    import ray

    if settings.starts_cluster:
        # address="local": always a new private cluster, never one that another process on this machine
        # started (ray.init() without an address would join the newest one it finds in /tmp/ray)
        ray.init(address="local", num_cpus=settings.num_cpus, include_dashboard=False,
                 log_to_driver=settings.log_to_driver, object_store_memory=settings.object_store_memory)
    else:
        ray.init(address=settings.address, log_to_driver=settings.log_to_driver)


@contextlib.contextmanager
def ray_session(settings: RaySettings) -> Iterator[dict]:
    """Ray initialised for the block (module docstring); yields ``{"address", "nodes", "cpus"}``."""
    import ray

    from spread.runtime.quiet import quiet_ray_start

    owned = not ray.is_initialized()
    if owned:
        with quiet_ray_start():
            _start(settings)
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        yield {"address": settings.address or "local", "nodes": len(nodes),
               "cpus": float(sum(n.get("Resources", {}).get("CPU", 0.0) for n in nodes))}
    finally:
        if owned:
            ray.shutdown()


def scheduling_strategy(settings: RaySettings):
    """Where a run's tasks and actors go: ``settings.scheduling_strategy``, except inside a placement group
    (a Ray Tune trial of ``spread-sweep``), where they go into that group's bundles (the trial's reserved
    CPUs/GPUs; outside them every CPU may be reserved by other trials)."""
    from ray.util import get_current_placement_group

    group = get_current_placement_group()
    if group is None:
        return settings.scheduling_strategy
    from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

    return PlacementGroupSchedulingStrategy(group, placement_group_capture_child_tasks=True)
