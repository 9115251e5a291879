"""``spread-ablate +preset=quick``: train / sample / evaluate base, geometry and guidance → the ablation table.

The stages and their resume rules are :mod:`spread.experiments.ablation`; this file maps ``conf/ablate.yaml``
to an :class:`~spread.experiments.AblationSpec`, runs each stage's command in this process (its config
composed from ``conf/<command>.yaml`` with the stage's overrides, then the command's library function),
logs the table to wandb (offline by default) and prints it. Exit status 1 when a stage failed (the table
is still written, with the failed rows empty).
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir

log = logging.getLogger("spread.ablate")


def compose_command(name: str, overrides: list[str]) -> DictConfig:
    """``conf/<name>.yaml`` composed with ``overrides`` (inside a Hydra app or not)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose(config_name=name, overrides=list(overrides))
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def save_config(cfg: DictConfig, folder: Path, overrides: list[str]) -> None:
    """``folder/.hydra/config.yaml`` and ``overrides.yaml``, as the command's own run would leave them."""
    from spread.io import write_text_atomic

    write_text_atomic(folder / ".hydra" / "config.yaml", OmegaConf.to_yaml(cfg))
    write_text_atomic(folder / ".hydra" / "overrides.yaml", OmegaConf.to_yaml(OmegaConf.create(list(overrides))))


class InProcessCommands:
    """:class:`~spread.experiments.Commands` backed by the commands' library functions."""

    def __init__(self, progress: bool = True):
        self.progress = progress

    def generate(self, overrides: list[str]) -> None:
        from spread.cli.generate import dataset_config
        from spread.procgen.dataset import generate_dataset

        cfg = compose_command("generate", overrides)
        generate_dataset(cfg.out_dir, dataset_config(cfg), progress=bool(cfg.progress))

    def train(self, overrides: list[str], run_dir: Path) -> None:
        from spread.cli.train import train

        cfg = compose_command("train", overrides)
        save_config(cfg, run_dir, overrides)
        train(cfg, run_dir=run_dir)

    def sample(self, overrides: list[str]) -> None:
        from spread.cli.sample import sampling_config
        from spread.sampling import run_sampling

        if any(o.startswith("guidance=") for o in overrides) and not (Path(conf_dir()) / "guidance").is_dir():
            raise RuntimeError("the guidance row needs spread-sample's guidance support (conf/guidance/ and "
                               "SamplingConfig.guidance), which this checkout does not have yet")
        cfg = compose_command("sample", overrides)
        save_config(cfg, Path(str(cfg.out_dir)), overrides)
        run_sampling(sampling_config(cfg))

    def evaluate(self, overrides: list[str]) -> dict:
        from spread.cli.evaluate import evaluation_config
        from spread.distributed import run_evaluation

        cfg = compose_command("evaluate", overrides)
        save_config(cfg, Path(str(cfg.out_dir)), overrides)
        result = run_evaluation(evaluation_config(cfg))
        if cfg.logger.name == "wandb":
            from spread.distributed.wandb_report import log_evaluation

            log_evaluation(result, mode=str(cfg.logger.mode), project=str(cfg.logger.project),
                           name=cfg.logger.run_name, tags=list(cfg.logger.tags or []), group=str(cfg.experiment_name),
                           config=OmegaConf.to_container(cfg, resolve=True))
        return result.metrics


def strings(node) -> list[str]:
    return [str(x) for x in (OmegaConf.to_container(node, resolve=True) if node is not None else [])]


def ablation_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.AblationSpec` of a composed ``conf/ablate.yaml``."""
    from spread.experiments import AblationSpec

    root = cfg.data.root
    variant_lists = {v: strings(cfg.train.get(v)) for v in ("base", "geometry")}
    return AblationSpec(
        out_dir=Path(str(cfg.out_dir)), data_root=None if root in (None, "") else Path(str(root)),
        split=str(cfg.data.split), variants=tuple(str(v) for v in cfg.variants),
        generate=strings(cfg.data.generate) + strings(cfg.data.get("extra")),
        train=strings(cfg.train.overrides) + strings(cfg.train.get("extra")), train_variant=variant_lists,
        ckpt={k: (None if v in (None, "") else str(v)) for k, v in (cfg.train.get("ckpt") or {}).items()},
        sample=strings(cfg.sample.overrides) + strings(cfg.sample.get("extra")),
        guidance=strings(cfg.sample.guidance),
        evaluate=strings(cfg.evaluate.overrides) + strings(cfg.evaluate.get("extra")),
        title=str(cfg.get("title") or ""), group=f"ablate_{cfg.name}")


def console_table(result, title: str):
    from rich.table import Table

    from spread.experiments.ablation import table_columns

    table = Table(title=title)
    columns = table_columns()
    for c in columns:
        table.add_column(c.label + c.arrow, justify="left" if c.digits is None else "right")
    for r in result.records:
        table.add_row(*[c.format(r.get(c.key)) for c in columns])
    return table


def run(cfg: DictConfig):
    """The ablation of ``cfg`` (a composed ``conf/ablate.yaml``); returns the AblationResult."""
    from spread.cli.train import set_threads
    from spread.experiments import run_ablation

    set_threads(cfg.get("threads"))
    spec = ablation_spec(cfg)
    log_table = None
    if cfg.logger.name == "wandb":
        from spread.experiments.wandb_table import log_ablation

        def log_table(records, png):
            log_ablation(records, png, spec.out_dir, mode=str(cfg.logger.mode), project=str(cfg.logger.project),
                         name=cfg.logger.run_name or f"ablation/{cfg.name}", tags=list(cfg.logger.tags or []),
                         group=spec.group,
                         config=OmegaConf.to_container(cfg, resolve=True))
    elif cfg.logger.name != "none":
        raise SystemExit(f"spread-ablate: unknown logger '{cfg.logger.name}' (wandb or none)")
    return run_ablation(spec, InProcessCommands(), log_table)


def report(result, cfg: DictConfig) -> None:
    from rich.console import Console

    console = Console()
    console.print()
    console.print(console_table(result, f"ablation {cfg.name} ({cfg.out_dir}, {result.seconds / 60:.1f} min)"))
    fid = {r.get("fid_status") for r in result.records if r.get("fid") is None and r.get("fid_status")}
    for status in sorted(fid):
        console.print(f"FID: {status}")
    console.print("stages: " + ", ".join(f"{k} {v}" for k, v in result.stages.items()))
    console.print("table: " + ", ".join(str(p) for p in result.tables.values()))
    for message in result.errors.values():
        console.print(f"[red]✗ {message}[/red]")


@hydra.main(config_path=conf_dir(), config_name="ablate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = run(cfg)
    report(result, cfg)
    if not result.ok:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
