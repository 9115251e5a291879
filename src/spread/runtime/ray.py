"""Ray for one command run: start a local in-process cluster, or join one; always leave it as found.

* ``address=None`` (or ``"local"``): ``ray.init(num_cpus=...)`` starts a private local cluster for this
  process (its own raylet and workers, no dashboard) and ``ray.shutdown()`` stops exactly that at the end.
* ``address="auto"`` or ``"HOST:PORT"``: join a running cluster (``ray start`` on the nodes, or
  ``ray.cluster_utils.Cluster`` in tests); the end only disconnects this driver, the cluster stays.
* Ray already initialised by the caller (a notebook, a test): used as is and left running.

Workers must import ``spread`` and read the scene and dataset folders: on a real cluster, install the
project on every node and keep the folders on a shared filesystem.

**Clean stops.** A started cluster is this run's: SIGTERM (and SIGINT) inside the session end the command through
the same ``finally`` that stops it. When the session has an ``owner`` folder (the command's output folder), the
started cluster is recorded there (``.ray-session.json``: the driver's pid, Ray's session folder, the pids of its
raylet, GCS and helpers) and the record is removed at the end. A driver killed outright (SIGKILL) cannot stop its
cluster (its raylet and GCS die with it, the raylet's agents and busy workers do not); its record stays, and the next
session on the same folder first stops what that record names — processes whose command line names the recorded
session folder, and processes started by the recorded raylet (``RAY_RAYLET_PID`` in their environment) that still
write into that folder — never a process found by its name. SIGTERM, then SIGKILL after
``STOP_GRACE`` seconds (a raylet may ignore SIGTERM).
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

#: Name of the record of a started cluster in its owner folder.
RECORD = ".ray-session.json"
#: Seconds between SIGTERM and SIGKILL when stopping a killed run's leftover processes.
STOP_GRACE = 3.0


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

    def __post_init__(self):
        from spread.checks import whole_number

        # ``num_cpus=0`` started a cluster on which no task or actor could ever run: the command waited for ever
        whole_number(self.num_cpus, "ray.num_cpus", 1, null="all of this machine's")
        whole_number(self.max_retries, "ray.max_retries", 0)

    @property
    def starts_cluster(self) -> bool:
        return self.address in (None, "", "local")


#: Seconds a cluster's address has to answer before a join is refused (Ray itself retried for minutes).
CONNECT_TIMEOUT_S = 10.0


def address_problem(address, key: str = "ray.address") -> str | None:
    """Why the cluster at ``address`` (``HOST:PORT`` or ``ray://HOST:PORT``) cannot be joined: nothing accepts a
    connection there within :data:`CONNECT_TIMEOUT_S` (``ray.init`` retried the GCS for minutes, then
    longer: ``127.0.0.1:1`` held a command past 300 s); None where it answers, or for an address this cannot read
    (``auto``, ``local``: Ray says what it makes of it)."""
    import socket

    if not isinstance(address, str) or address in ("", "auto", "local"):
        return None
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S):
            return None
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        return (f"{key}={address}: nothing answers there ({why}); start the cluster's head first (ray start --head) "
                f"and give its address")


def _start(settings: RaySettings) -> None:
    import ray

    if settings.starts_cluster:
        # address="local": always a new private cluster, never one that another process on this machine
        # started (ray.init() without an address would join the newest one it finds in /tmp/ray)
        ray.init(address="local", num_cpus=settings.num_cpus, include_dashboard=False,
                 log_to_driver=settings.log_to_driver, object_store_memory=settings.object_store_memory)
    else:
        problem = address_problem(settings.address)
        if problem:
            raise ValueError(problem)
        ray.init(address=settings.address, log_to_driver=settings.log_to_driver)


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:  # checked: a procfs file, not a user input
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _parent(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat") as f:  # checked: a procfs file, not a user input
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return _cmdline(pid) != "" or os.path.exists(f"/proc/{pid}")


def _raylet_of(pid: int) -> int | None:
    """The ``RAY_RAYLET_PID`` a process was started with (Ray's agents and workers), or None."""
    try:
        with open(f"/proc/{pid}/environ", "rb") as f:  # checked: a procfs file, not a user input
            for item in f.read().split(b"\0"):
                if item.startswith(b"RAY_RAYLET_PID="):
                    return int(item.split(b"=", 1)[1])
    except (OSError, ValueError):
        pass
    return None


def _writes_into(pid: int, folder: str) -> bool:
    """Whether one of the process's open files lies in ``folder`` (a Ray process keeps its session's logs open)."""
    try:
        return any(os.readlink(f"/proc/{pid}/fd/{fd}").startswith(folder) for fd in os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return False


def leftover_processes(record: dict) -> list[int]:
    """The pids of a recorded cluster still running: processes whose command line names the recorded session
    folder (raylet, GCS, helpers), and processes started by the recorded raylet (``RAY_RAYLET_PID``: the dashboard
    and runtime-env agents, workers, which rename themselves ``ray::…``) that still write into that folder."""
    session = str(record.get("session_dir") or "")
    if not session or not os.path.isdir("/proc"):
        return []
    raylets = {int(p) for p in (record.get("pids") or {}).get("raylet", [])}
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        pid = int(entry)
        if session in _cmdline(pid) or (_raylet_of(pid) in raylets and _writes_into(pid, session)):
            found.append(pid)
    return sorted(found)


def stop_processes(pids: list[int], grace: float = STOP_GRACE) -> list[int]:
    """SIGTERM ``pids``, then SIGKILL those alive after ``grace`` seconds; returns the pids signalled."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        alive = [p for p in pids if _alive(p)]
        for p in alive:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(p, sig)
        deadline = time.monotonic() + (grace if sig == signal.SIGTERM else 1.0)
        while time.monotonic() < deadline and any(_alive(p) for p in alive):
            time.sleep(0.05)
            for p in alive:  # reap our own children (a cluster this process started earlier)
                with contextlib.suppress(ChildProcessError, OSError):
                    os.waitpid(p, os.WNOHANG)
    return pids


def stop_leftover(owner: Path) -> list[int]:
    """Stop what a killed run's cluster left running (the record in ``owner``, module docstring); the record goes.
    Returns the pids stopped."""
    from spread.io import read_json

    path = Path(owner) / RECORD
    if not path.is_file():
        return []
    try:
        record = read_json(path)
    except (OSError, ValueError):
        record = {}
    pids = leftover_processes(record) if isinstance(record, dict) else []
    if pids:
        import logging

        logging.getLogger("spread.ray").warning(
            "stopping %d process(es) of Ray session %s, left running by a killed run (driver pid %s) in %s",
            len(pids), record.get("session_dir"), record.get("driver_pid"), owner)
        stop_processes(pids)
    path.unlink(missing_ok=True)
    return pids


def _record(owner: Path) -> None:
    import ray

    from spread.io import write_json_atomic

    node = ray._private.worker._global_node
    pids = {kind: [int(p.process.pid) for p in procs if p.process is not None]
            for kind, procs in node.all_processes.items()}
    write_json_atomic(Path(owner) / RECORD, {"driver_pid": os.getpid(), "session_dir": node.get_session_dir_path(),
                                              "pids": pids, "started": time.time()})


#: The exit status of a command stopped by SIGTERM (128 + 15): what :func:`_terminate` raises in a session.
TERMINATED = 128 + signal.SIGTERM


#: The signals :func:`_terminate` received in this process (Ray's ``wait``/``get`` turn the ``SystemExit`` it raises
#: inside them into ``SystemExit(1)``: :func:`terminated` and :func:`ray_session` still read it as SIGTERM).
_RECEIVED: list[int] = []


def _terminate(signum, frame):
    _RECEIVED.append(signum)
    raise SystemExit(128 + signum)


def terminated(exc: BaseException) -> bool:
    """Whether ``exc`` says the command received SIGTERM — the ``SystemExit(143)`` a session's handler raises, the
    ``SystemExit(15)`` of the handler ``ray.init`` leaves in a driver, or Lightning's ``SIGTERMException`` out of a
    training run in this process (whichever handler was in force) — rather than that one piece of work failed (a
    command's own ``SystemExit`` with a message is that work's failure). Loops that keep going past a failed stage,
    scene or metric re-raise these."""
    import sys

    lightning = sys.modules.get("lightning.pytorch.utilities.exceptions")
    if lightning is not None and isinstance(exc, lightning.SIGTERMException):
        return True
    return isinstance(exc, SystemExit) and (exc.code in (TERMINATED, int(signal.SIGTERM)) or bool(_RECEIVED))


@contextlib.contextmanager
def sigterm_exits() -> Iterator[None]:
    """SIGTERM raises ``SystemExit(143)`` (:data:`TERMINATED`) in the main thread for the block (SIGINT already raises
    KeyboardInterrupt), so a terminated command runs its ``finally`` blocks: a session stops its cluster (set again
    after ``ray.init``, which installs its own), a process pool's ``with`` block terminates its workers. Main thread
    only (where a handler can be set); the handler in force before is set again after the block (the default action
    where it was set outside Python)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


@contextlib.contextmanager
def _terminated_as_143() -> Iterator[None]:
    """A SIGTERM met in the block ends it as :data:`TERMINATED`: inside ``ray.wait`` / ``ray.get`` it comes out of Ray
    as ``SystemExit(1)``, and while ``ray.init`` starts the cluster Ray's own handler raises ``SystemExit(15)``."""
    try:
        yield
    except SystemExit as exc:
        if exc.code != TERMINATED and (_RECEIVED or exc.code == int(signal.SIGTERM)):
            raise SystemExit(TERMINATED) from exc
        raise


@contextlib.contextmanager
def _sigterm_ends_the_start() -> Iterator[None]:
    """While ``ray.init`` starts a cluster, SIGTERM has its default action: the process ends at once (status 143 in a
    shell), and the processes Ray started end with it (Ray starts them sharing its fate: ``PR_SET_PDEATHSIG``). The
    main thread then waits inside Ray's code for the GCS to publish its port (``Node.start_gcs_server``) holding the
    interpreter, so no Python handler runs: a SIGTERM to the command's process group, which also killed that GCS,
    took the wait's 30 s to end the command. The handler the starting node installs (it drains, stops its processes and
    exits 1) is not installed for the start; the session sets its own after it (:func:`ray_session`). Nothing of the
    run needs a ``finally`` then: its lock is an ``flock``, and the run folder resumes as after any stop. Main thread
    only (where a cluster is started)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    import ray._private.utils as ray_utils

    install = getattr(ray_utils, "set_sigterm_handler", None)
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if install is not None:  # the handler the starting node installs (``Node._register_shutdown_hooks``) is left out
        ray_utils.set_sigterm_handler = lambda handler: None
    try:
        yield
    finally:
        if install is not None:
            ray_utils.set_sigterm_handler = install
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def ray_session(settings: RaySettings, owner: Path | str | None = None) -> Iterator[dict]:
    """Ray initialised for the block (module docstring); yields ``{"address", "nodes", "cpus"}``. ``owner``: the
    command's output folder, where a started cluster is recorded (and a killed predecessor's stopped)."""
    import ray

    from spread.runtime.quiet import quiet_ray_start

    owned = not ray.is_initialized()
    recorded = owned and settings.starts_cluster and owner is not None
    if recorded:
        Path(owner).mkdir(parents=True, exist_ok=True)
        stop_leftover(Path(owner))
    with sigterm_exits(), _terminated_as_143():
        if owned:
            with quiet_ray_start(), _sigterm_ends_the_start():
                _start(settings)
            if recorded:
                _record(Path(owner))
            import threading

            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, _terminate)
        try:
            nodes = [n for n in ray.nodes() if n.get("Alive")]
            yield {"address": settings.address or "local", "nodes": len(nodes),
                   "cpus": float(sum(n.get("Resources", {}).get("CPU", 0.0) for n in nodes))}
        finally:
            if owned:
                ray.shutdown()
            if recorded:
                (Path(owner) / RECORD).unlink(missing_ok=True)


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
