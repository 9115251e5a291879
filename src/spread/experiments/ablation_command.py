"""``spread-ablate`` on a composed ``conf/ablate.yaml``: the :class:`~spread.experiments.ablation.AblationSpec`,
the stages run in-process (:class:`~spread.experiments.commands.InProcessCommands`), the table on wandb (offline
by default) and on the console. The stages and their resume rules are :mod:`spread.experiments.ablation`.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf


def strings(node) -> list[str]:
    return [str(x) for x in (OmegaConf.to_container(node, resolve=True) if node is not None else [])]


def recipe_sampling(experiment: str) -> tuple[list[str], list[str]]:
    """(sampler overrides, guidance overrides) of a training experiment's ``sampling`` block."""
    from spread.configs import compose

    sampling = compose("train", [f"experiment={experiment}", "data.root=/unused"]).get("sampling")
    if sampling is None:
        raise ValueError(f"recipe={experiment}: conf/experiment/{experiment}.yaml has no `sampling` block")
    return strings(sampling.get("sampler")), strings(sampling.get("guidance"))


def ablation_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.AblationSpec` of a composed ``conf/ablate.yaml``; with ``recipe``, the
    rows' sampler and the guidance row's guidance come from that training experiment's ``sampling`` block."""
    from spread.experiments.ablation import AblationSpec

    sampler, guidance = recipe_sampling(str(cfg.recipe)) if cfg.get("recipe") else ([], [])
    root = cfg.data.root
    variant_lists = {v: strings(cfg.train.get(v)) for v in ("base", "geometry")}
    return AblationSpec(
        out_dir=Path(str(cfg.out_dir)), data_root=None if root in (None, "") else Path(str(root)),
        split=str(cfg.data.split), variants=tuple(str(v) for v in cfg.variants),
        generate=strings(cfg.data.generate) + strings(cfg.data.get("extra")),
        train=strings(cfg.train.overrides) + strings(cfg.train.get("extra")), train_variant=variant_lists,
        ckpt={k: (None if v in (None, "") else str(v)) for k, v in (cfg.train.get("ckpt") or {}).items()},
        sample=sampler + strings(cfg.sample.overrides) + strings(cfg.sample.get("extra")),
        guidance=guidance + strings(cfg.sample.guidance),
        evaluate=strings(cfg.evaluate.overrides) + strings(cfg.evaluate.get("extra")),
        title=str(cfg.get("title") or ""), figures=bool(cfg.get("figures", True)), group=f"ablate_{cfg.name}")


def ablate(cfg: DictConfig):
    """The ablation of ``cfg``; returns the :class:`~spread.experiments.AblationResult`."""
    from spread.experiments.ablation import run_ablation
    from spread.experiments.commands import record_config
    from spread.runtime import mlflow_log
    from spread.runtime.tracking import as_logger_config
    from spread.training.fit import set_threads

    set_threads(cfg.get("threads"))
    spec = ablation_spec(cfg)
    from spread.io import run_lock

    with run_lock(spec.out_dir, "spread-ablate"):  # a second spread-ablate on this folder is refused, never mixed
        record_config(cfg, spec.out_dir)()
        logger = as_logger_config(cfg.logger)
        config = OmegaConf.to_container(cfg, resolve=True)
        seeds = [int(x) for x in (OmegaConf.to_container(cfg.seeds, resolve=True) if cfg.get("seeds") else [])]
        commands = launcher_commands(cfg)
        with mlflow_log.tracked(logger, "ablation", spec.out_dir, config, spec.group, name=f"ablation/{cfg.name}") as run:
            def log_table(records, png):
                if logger.wandb:
                    from spread.experiments.wandb_table import log_ablation

                    log_ablation(records, png, spec.out_dir, logger, name=f"ablation/{cfg.name}", group=spec.group,
                                 config=config)
                if run is not None:
                    mlflow_log.log_table(run, records, "variant", sorted(Path(png).parent.glob(Path(png).stem + ".*")))

            logged = log_table if logger.wandb or run is not None else None
            if seeds:
                from spread.experiments.ablation_seeds import run_seeded_ablation

                return run_seeded_ablation(spec, commands, seeds, logged)
            return run_ablation(spec, commands, logged)


def launcher_commands(cfg: DictConfig):
    """The stages' commands: in this process, or training stages through a launcher (``train.launcher``)."""
    from spread.experiments.commands import InProcessCommands

    launcher = str(cfg.train.get("launcher") or "inprocess")
    if launcher == "inprocess":
        return InProcessCommands()
    from spread.experiments.launch import LaunchedCommands

    return LaunchedCommands(launcher, int(cfg.train.get("nproc") or 1), int(cfg.train.get("nnodes") or 1))


def console_table(result, title: str):
    """The ablation table for the console: value ± half-width of its bootstrap interval per cell."""
    from rich.table import Table

    from spread.experiments.ablation import table_columns

    table = Table(title=title)
    columns = table_columns()
    for c in columns:
        table.add_column(c.label + c.arrow, justify="left" if c.digits is None else "right")
    for r in result.records:
        table.add_row(*[c.cell(r) for c in columns])
    return table


def print_ablation(result, cfg: DictConfig) -> None:
    from rich.console import Console

    from spread.experiments.intervals import table_note

    console = Console()
    console.print()
    console.print(console_table(result, f"ablation {cfg.name} ({cfg.out_dir}, {result.seconds / 60:.1f} min)"))
    note = table_note(result.records)
    if note:
        console.print(note)
    fid = {r.get("fid_status") for r in result.records if r.get("fid") is None and r.get("fid_status")}
    for status in sorted(fid):
        console.print(f"FID: {status}")
    console.print("stages: " + ", ".join(f"{k} {v}" for k, v in result.stages.items()))
    console.print("table: " + ", ".join(str(p) for p in result.tables.values()))
    for message in result.errors.values():
        console.print(f"[red]✗ {message}[/red]")
