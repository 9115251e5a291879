"""``spread-ablate`` on a composed ``conf/ablate.yaml``: the :class:`~spread.experiments.ablation.AblationSpec`,
the stages run in-process (:class:`~spread.commands.in_process.InProcessCommands`; training through
``train.launcher``, ``stages.train_concurrent`` stages at a time; the rows ``stages.max_concurrent`` at a time), the table on wandb (offline by default) and on
the console. The stages and their resume rules are :mod:`spread.experiments.ablation`. ``spread-compare``
(:mod:`spread.commands.compare`) is the same command over methods: both build their spec's shared
fields with :func:`spec_fields` and run with :func:`run_stages_command`.
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


def spec_fields(cfg: DictConfig, kind: str) -> dict:
    """The :class:`~spread.experiments.stages.StagesSpec` fields of a composed ``conf/ablate.yaml`` or
    ``conf/compare.yaml`` (``kind``: ``ablate`` or ``compare``, the wandb group's prefix); ``stages``:
    ``max_concurrent``, ``train_concurrent`` with each training stage's ``train_cpus`` / ``train_gpus``, and
    where their Ray tasks run (``address``, ``num_cpus``)."""
    from spread.checks import whole_number
    from spread.runtime.ray import RaySettings

    root = cfg.data.root
    stages = cfg.get("stages") or {}
    return dict(
        out_dir=Path(str(cfg.out_dir)), data_root=None if root in (None, "") else Path(str(root)),
        split=str(cfg.data.split), generate=strings(cfg.data.generate) + strings(cfg.data.get("extra")),
        train=strings(cfg.train.overrides) + strings(cfg.train.get("extra")),
        ckpt={k: (None if v in (None, "") else str(v)) for k, v in (cfg.train.get("ckpt") or {}).items()},
        sample=strings(cfg.sample.overrides) + strings(cfg.sample.get("extra")),
        evaluate=strings(cfg.evaluate.overrides) + strings(cfg.evaluate.get("extra")),
        title=str(cfg.get("title") or ""), group=f"{kind}_{cfg.name}",
        max_concurrent=whole_number(stages.get("max_concurrent"), "stages.max_concurrent", 1, null="1") or 1,
        train_concurrent=whole_number(stages.get("train_concurrent"), "stages.train_concurrent", 1, null="1") or 1,
        train_cpus=float(1 if stages.get("train_cpus") is None else stages.get("train_cpus")),
        train_gpus=float(stages.get("train_gpus") or 0),
        ray=RaySettings(address=stages.get("address"), num_cpus=stages.get("num_cpus")))


def ablation_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.AblationSpec` of a composed ``conf/ablate.yaml``; with ``recipe``, the
    rows' sampler and the guidance row's guidance come from that training experiment's ``sampling`` block."""
    from spread.checks import true_or_false
    from spread.experiments.ablation import AblationSpec

    sampler, guidance = recipe_sampling(str(cfg.recipe)) if cfg.get("recipe") else ([], [])
    fields = spec_fields(cfg, "ablate")
    return AblationSpec(**{**fields, "sample": sampler + fields["sample"]},
                        variants=tuple(str(v) for v in cfg.variants),
                        train_variant={v: strings(cfg.train.get(v)) for v in ("base", "geometry")},
                        sample_variant={v: strings(cfg.sample.get(v)) for v in ("base", "geometry") if cfg.sample.get(v)},
                        guidance=guidance + strings(cfg.sample.guidance),
                        figures=true_or_false(cfg.get("figures", True), "figures"))


def run_stages_command(cfg: DictConfig, spec, command: str, name: str, body, prepare=None):
    """The frame of ``spread-ablate`` and ``spread-compare``: torch threads, ``out_dir``'s lock (a second run
    on the folder is refused, never mixed), ``prepare(commands)`` (the study built: its checks of the stage lists
    and the ledger), the config recorded — after those checks, so a refused relaunch leaves the folder's record as
    it was —, the MLflow run (``name``: the parent run of every stage's MLflow run,
    :func:`spread.tracking.parent.nest_under`); then ``body(commands, logger, config, run)`` (``commands``:
    :func:`launcher_commands`) gives the result."""
    from spread.commands.common import record_config
    from spread.io import run_lock
    from spread.tracking import mlflow_store as mlflow_log
    from spread.tracking.loggers import as_logger_config
    from spread.tracking.parent import nest_under
    from spread.runtime.threads import set_threads

    from spread.experiments.stages import check_data_split

    set_threads(cfg.get("threads"))
    check_data_split(spec)  # before the folder's record: a refused relaunch leaves it as it was
    from spread.io import check_folder_kind

    check_folder_kind(spec.out_dir, f"spread-{command}", {"ablation" if command == "ablate" else "comparison"})
    with run_lock(spec.out_dir, f"spread-{command}"):
        commands = launcher_commands(cfg)
        if prepare is not None:
            prepare(commands)
        record_config(cfg, spec.out_dir)()
        logger = as_logger_config(cfg.logger)
        config = OmegaConf.to_container(cfg, resolve=True)
        kind = {"ablate": "ablation"}.get(command, command)
        with mlflow_log.tracked(logger, kind, spec.out_dir, config, spec.group, name=name) as run:
            with nest_under(run, {"ablate": "ablation"}.get(command, "comparison"), str(cfg.name), spec.out_dir):
                return body(commands, logger, config, run)  # the stages' runs: nested under `run`


def ablate(cfg: DictConfig):
    """The ablation of ``cfg``; returns the :class:`~spread.experiments.AblationResult`."""
    from spread.tracking import mlflow_store as mlflow_log

    spec = ablation_spec(cfg)
    name = f"ablation/{cfg.name}"
    from spread.checks import is_whole, listed_once

    seeds = list(OmegaConf.to_container(cfg.seeds, resolve=True) if cfg.get("seeds") else [])
    if not all(is_whole(x) and x >= 0 for x in seeds):  # a training seed is Lightning's, in [0, 2**32); never 1.5 as 1
        raise ValueError(f"seeds={seeds}: a seed is a whole number ≥ 0")
    seeds = [int(x) for x in seeds]
    listed_once(seeds, f"seeds={seeds}", each="training seed")

    def body(commands, logger, config, run):
        def log_table(records, png):
            if logger.wandb:
                from spread.reporting.wandb_table import log_ablation

                log_ablation(records, png, spec.out_dir, logger, name=name, group=spec.group, config=config)
            if run is not None:
                mlflow_log.log_table(run, records, "variant", sorted(Path(png).parent.glob(Path(png).stem + ".*")))

        logged = log_table if logger.wandb or run is not None else None
        if seeds:
            from spread.experiments.ablation_seeds import run_seeded_ablation

            return run_seeded_ablation(spec, commands, seeds, logged, ablations=prepared["ablations"])
        return prepared["ablation"].run(logged)

    prepared = {}

    def prepare(commands):  # every check of the stage lists and the ledger, before the folder's record
        from spread.experiments.ablation import Ablation
        from spread.experiments.ablation_seeds import seed_spec

        if seeds:
            prepared["ablations"] = {seed: Ablation(seed_spec(spec, seed), commands) for seed in seeds}
        else:
            prepared["ablation"] = Ablation(spec, commands)

    return run_stages_command(cfg, spec, "ablate", name, body, prepare)


def launcher_commands(cfg: DictConfig):
    """The stages' commands: in this process, or training stages through a launcher (``train.launcher``)."""
    from spread.commands.in_process import InProcessCommands

    launcher = str((cfg.get("train") or {}).get("launcher") or "inprocess")
    if launcher == "inprocess":
        return InProcessCommands()
    from spread.commands.launch import LaunchedCommands

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

    from spread.experiments.stages import carried_note
    from spread.reporting.intervals import table_note

    console = Console()
    console.print()
    console.print(console_table(result, f"ablation {cfg.name} ({cfg.out_dir}, {result.seconds / 60:.1f} min)"))
    for note in (table_note(result.records), carried_note(result.records)):
        if note:
            console.print(note)
    fid = {r.get("fid_status") for r in result.records if r.get("fid") is None and r.get("fid_status")}
    for status in sorted(fid):
        console.print(f"FID: {status}")
    console.print("stages: " + ", ".join(f"{k} {v}" for k, v in result.stages.items()))
    console.print("table: " + ", ".join(str(p) for p in result.tables.values()))
    for message in result.errors.values():
        console.print(f"[red]✗ {message}[/red]")
