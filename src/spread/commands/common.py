"""What every command body shares: its config recorded beside its outputs (``.hydra/``), its wandb run
finished as failed when it raises, the config as plain data."""

from __future__ import annotations

import contextlib
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


@contextlib.contextmanager
def failed_on_error(wandb_run):
    """The body of a command's wandb run (None: no run): if it raises, the run is finished as failed (exit code 1)
    before the error goes on."""
    try:
        yield
    except BaseException:
        if wandb_run is not None:
            wandb_run.finish(exit_code=1)
        raise


def save_config(cfg: DictConfig, folder: Path, overrides: list[str]) -> None:
    """``folder/.hydra/config.yaml`` and ``overrides.yaml``, as the command's own Hydra run would leave them."""
    from spread.io import write_text_atomic

    write_text_atomic(folder / ".hydra" / "config.yaml", OmegaConf.to_yaml(cfg))
    write_text_atomic(folder / ".hydra" / "overrides.yaml", OmegaConf.to_yaml(OmegaConf.create(list(overrides))))


def hydra_overrides() -> list[str]:
    """The command line's overrides inside a running Hydra app (``[]`` outside one)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def record_config(cfg: DictConfig, folder, overrides: list[str] | None = None):
    """A callback that writes the run's config into ``folder/.hydra`` (run by a stage once its checks passed)."""
    return lambda: save_config(cfg, Path(folder), hydra_overrides() if overrides is None else overrides)


def record_in_log_folder(cfg: DictConfig) -> None:
    """Record the config in Hydra's log folder (commands whose ``out_dir`` is a dataset folder, which stays
    the dataset); nothing outside a running Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        record_config(cfg, HydraConfig.get().runtime.output_dir)()


def plain(cfg: DictConfig) -> dict:
    """The composed config as plain data (what wandb records as the run's config)."""
    return OmegaConf.to_container(cfg, resolve=True)
