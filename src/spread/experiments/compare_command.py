"""``spread-compare`` on a composed ``conf/compare.yaml``: the :class:`~spread.experiments.compare.CompareSpec`,
the stages run in-process (:class:`~spread.experiments.commands.InProcessCommands`), Table 1 on wandb (offline by
default) and on the console. The stages and their resume rules are :mod:`spread.experiments.compare` (the
ablation's machinery).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from spread.experiments.ablation_command import strings


def compare_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.compare.CompareSpec` of a composed ``conf/compare.yaml``."""
    from spread.experiments.compare import CompareSpec, registered, spec_of, trained_methods

    root = cfg.data.root
    return CompareSpec(
        out_dir=Path(str(cfg.out_dir)), data_root=None if root in (None, "") else Path(str(root)),
        split=str(cfg.data.split), methods=tuple(str(m) for m in cfg.methods),
        generate=strings(cfg.data.generate) + strings(cfg.data.get("extra")),
        train=strings(cfg.train.overrides) + strings(cfg.train.get("extra")),
        train_method={m: strings(cfg.train.get(m)) if m in cfg.train else list(spec_of(m).train)
                      for m in trained_methods()},
        ckpt={k: (None if v in (None, "") else str(v)) for k, v in (cfg.train.get("ckpt") or {}).items()},
        sample=strings(cfg.sample.overrides) + strings(cfg.sample.get("extra")),
        sample_method={m: strings(cfg.sample.get(m)) if m in cfg.sample else list(spec_of(m).sample)
                       for m in registered()},
        evaluate=strings(cfg.evaluate.overrides) + strings(cfg.evaluate.get("extra")),
        layout=str(cfg.layout), title=str(cfg.get("title") or ""), group=f"compare_{cfg.name}")


def compare(cfg: DictConfig):
    """The comparison of ``cfg``; returns the :class:`~spread.experiments.compare.CompareResult`."""
    from spread.experiments.commands import InProcessCommands, record_config
    from spread.experiments.compare import log_table1, run_comparison
    from spread.runtime.tracking import as_logger_config
    from spread.training.fit import set_threads

    set_threads(cfg.get("threads"))
    spec = compare_spec(cfg)
    from spread.io import run_lock

    with run_lock(spec.out_dir, "spread-compare"):  # a second spread-compare on this folder is refused, never mixed
        record_config(cfg, spec.out_dir)()
        from spread.runtime import mlflow_log

        logger = as_logger_config(cfg.logger)
        config = OmegaConf.to_container(cfg, resolve=True)
        with mlflow_log.tracked(logger, "compare", spec.out_dir, config, spec.group, name=f"table1/{cfg.name}") as run:
            def log_table(records, columns):
                if logger.wandb:
                    log_table1(records, columns, spec.out_dir, logger, name=f"table1/{cfg.name}", group=spec.group,
                               config=config)
                if run is not None:
                    mlflow_log.log_table(run, records, "method_key", sorted(Path(spec.out_dir).glob("table1*.*")))

            from spread.experiments.ablation_command import launcher_commands

            commands = launcher_commands(cfg) if cfg.get("train") is not None and cfg.train.get("launcher") else \
                InProcessCommands()  # train.launcher=local|torchrun|srun: training stages as their own processes (DDP)
            return run_comparison(spec, commands, log_table if logger.wandb or run is not None else None)


def print_comparison(result) -> None:
    from rich.console import Console

    console = Console()
    console.print()
    md = result.tables.get("md")
    if md is not None and md.exists():
        console.print(md.read_text())
    console.print(f"layout {result.layout}; {result.seconds / 60:.1f} min")
    console.print("stages: " + ", ".join(f"{k} {v}" for k, v in result.stages.items()))
    console.print("table: " + ", ".join(str(p) for p in result.tables.values()))
    for message in result.errors.values():
        console.print(f"[red]✗ {message}[/red]")
