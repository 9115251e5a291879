"""``spread-compare`` on a composed ``conf/compare.yaml``: the :class:`~spread.experiments.compare.CompareSpec`,
run as ``spread-ablate`` runs (:func:`~spread.commands.ablate.run_stages_command`), Table 1 on wandb
(offline by default) and on the console. The stages and their resume rules are :mod:`spread.experiments.compare` (the
ablation's machinery).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from spread.commands.ablate import run_stages_command, spec_fields, strings


def compare_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.compare.CompareSpec` of a composed ``conf/compare.yaml``: each method's
    training and sampling overrides are its registered recipe (:meth:`~spread.methods.registry.MethodSpec.recipe`,
    ``recipe``; its ``sample``) unless the config names a list for it (``train.<m>``, ``sample.<m>``)."""
    from spread.experiments.compare import CompareSpec, registered, spec_of, trained_methods

    recipe = str(cfg.get("recipe") or "full")
    return CompareSpec(
        **spec_fields(cfg, "compare"), methods=tuple(str(m) for m in cfg.methods),
        train_method={m: strings(cfg.train.get(m)) if m in cfg.train else list(spec_of(m).recipe(recipe))
                      for m in trained_methods()},
        sample_method={m: strings(cfg.sample.get(m)) if m in cfg.sample else list(spec_of(m).sample)
                       for m in registered()},
        layout=str(cfg.layout))


def compare(cfg: DictConfig):
    """The comparison of ``cfg``; returns the :class:`~spread.experiments.compare.CompareResult`. Training
    stages run through ``train.launcher`` (``local``, ``torchrun``, ``srun``: their own processes, DDP)."""
    from spread.experiments.compare import log_table1
    from spread.tracking import mlflow_store as mlflow_log

    spec = compare_spec(cfg)
    name = f"table1/{cfg.name}"

    def body(commands, logger, config, run):
        def log_table(records, columns):
            if logger.wandb:
                log_table1(records, columns, spec.out_dir, logger, name=name, group=spec.group, config=config)
            if run is not None:
                mlflow_log.log_table(run, records, "method_key", sorted(Path(spec.out_dir).glob("table1*.*")))

        return prepared["comparison"].run(log_table if logger.wandb or run is not None else None)

    prepared = {}

    def prepare(commands):  # every check of the stage lists and the ledger, before the folder's record
        from spread.experiments.compare import Comparison

        prepared["comparison"] = Comparison(spec, commands)

    return run_stages_command(cfg, spec, "compare", name, body, prepare)


def print_comparison(result) -> None:
    from rich.console import Console

    console = Console()
    console.print()
    md = result.tables.get("md")
    if md is not None and md.exists():
        from spread.io import read_text_checked

        console.print(read_text_checked(md), markup=False)
    console.print(f"layout {result.layout}; {result.seconds / 60:.1f} min")
    console.print("stages: " + ", ".join(f"{k} {v}" for k, v in result.stages.items()))
    console.print("table: " + ", ".join(str(p) for p in result.tables.values()))
    for message in result.errors.values():
        console.print(f"[red]✗ {message}[/red]")
