"""The ``logger`` config (:class:`LoggerConfig`), on its own floor of ``spread.runtime`` so that the wandb and MLflow
writers (:mod:`spread.tracking.loggers`, :mod:`spread.tracking.mlflow_store`) both read it without importing each
other. Conventions: :mod:`spread.tracking.loggers`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

NAMES = ("wandb", "mlflow", "csv", "none")


def wandb_mode() -> str:
    """wandb's mode when the config does not name one (``${wandb_mode:}`` in ``conf/logger/``): ``WANDB_MODE``
    when set; ``online`` inside a ``wandb agent`` (it sets ``WANDB_SWEEP_ID`` for the runs it starts: their
    metrics must reach the sweep's controller); else ``offline`` (this platform never needs the network)."""
    env = os.environ
    if env.get("WANDB_MODE"):
        return env["WANDB_MODE"]
    return "online" if env.get("WANDB_SWEEP_ID") else "offline"


@dataclass
class LoggerConfig:
    """name: ``wandb`` | ``mlflow`` | ``csv`` | ``none``, or several joined by ``+`` (``wandb+mlflow``);
    mode: wandb's mode (``offline``, ``online``, ``disabled``); project: wandb project; run_name: the run's
    name (None: the command picks one); tags: extra tags; tracking_uri: the MLflow store (None:
    ``sqlite:///runs/mlflow.db`` under the working directory; ``conf/logger/mlflow.yaml`` sets
    ``<paths.runs_dir>/mlflow.db``); a plain path is taken as a SQLite file."""

    name: str = "wandb"
    mode: str = "offline"
    project: str = "spread"
    run_name: str | None = None
    tags: list[str] = field(default_factory=list)
    tracking_uri: str | None = None

    def __post_init__(self) -> None:
        unknown = [n for n in self.names if n not in NAMES]
        if unknown or not self.names:
            raise ValueError(f"logger: key 'name' is {self.name!r}, choose from {NAMES} (several: joined by '+')")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n.strip() for n in str(self.name).split("+") if n.strip())

    @property
    def wandb(self) -> bool:
        return "wandb" in self.names

    @property
    def mlflow(self) -> bool:
        return "mlflow" in self.names


def as_logger_config(logger) -> LoggerConfig:
    """A LoggerConfig from itself, a mapping (a Hydra node), or None (``none``)."""
    if logger is None:
        return LoggerConfig(name="none")
    if isinstance(logger, LoggerConfig):
        return logger
    return LoggerConfig(**dict(logger))


def previous_wandb_id(run_dir: Path) -> str | None:
    """The id of the newest wandb run in ``<run folder>/wandb`` (``latest-run`` → ``…-run-<time>-<id>``)."""
    latest = Path(run_dir) / "wandb" / "latest-run"
    return latest.resolve().name.rsplit("-", 1)[-1] if latest.exists() else None


def room_type_scalars(metrics: dict) -> dict:
    """The per-room-type breakdown of an evaluation's ``metrics.json`` as flat scalars, ``room/<type>/<entry>``, the
    same keys for wandb and MLflow. A room type is any text a scene file holds (an importer's, a user's): one that is
    not a plain name (``[A-Za-z0-9._-]``: ``Küche (groß)``, ``kitchen: open-plan``, ``a/b``) goes in as
    :func:`spread.io.safe_name` makes it (unsafe characters ``_``, a hash of the text appended, so two types never
    share a key), which every tracker accepts as part of a metric name; each value in its display unit, keyed so
    (``room/<type>/asd_mm``)."""
    from spread.io import safe_name
    from spread.metrics.registry import in_display_units

    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    return {f"room/{safe_name(str(room))}/{k}": v for room, values in (metrics.get("per_room_type") or {}).items()
            for k, v in in_display_units({k: v for k, v in (values or {}).items() if number(v)}).items()}
