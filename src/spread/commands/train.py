"""``spread-train``'s body: one training run (:func:`spread.training.fit.train`) with its config recorded."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from spread.commands.common import record_config


def train(cfg: DictConfig, run_dir: Path | None = None, overrides: list[str] | None = None) -> dict:
    """``spread-train``: fit into ``run_dir`` (default: Hydra's output folder, else ``cfg.out_dir``). The launching
    process holds the folder's run lock (:func:`spread.io.run_lock`; the other ranks of DDP, torchrun, SLURM or MPI,
    which have a non-zero rank variable, do not take it), so a second training run into the same folder is refused.
    Data without scenes to train on is refused before torch and Lightning load
    (:func:`spread.data.splits.check_fit_config`)."""
    import contextlib
    import os

    from spread.data.splits import check_fit_config

    check_fit_config(cfg)
    from spread.io import run_lock
    from spread.training.fit import run_folder
    from spread.training.fit import train as fit

    run_dir = Path(run_dir) if run_dir is not None else run_folder(cfg)
    ranks = ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID", "OMPI_COMM_WORLD_RANK", "PMI_RANK")
    launcher = all(os.environ.get(v, "0") in ("", "0") for v in ranks)  # rank 0 of every launcher we know
    with run_lock(run_dir, "spread-train") if launcher else contextlib.nullcontext():
        return fit(cfg, run_dir=run_dir, before_work=record_config(cfg, run_dir, overrides))
