"""``spread-compare +table1=quick``: the paper's Table 1 — every method trained, sampled, evaluated, tabulated.

The stages and their resume rules are :mod:`spread.experiments.compare` (the ablation's machinery); this file
maps ``conf/compare.yaml`` to a :class:`~spread.experiments.compare.CompareSpec`, runs each stage's command in
this process (:class:`spread.cli.ablate.InProcessCommands`), logs the table to wandb (offline by default) and
prints it. Exit status 1 when a stage failed (the table is still written, with the failed rows empty).
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir
from spread.cli.ablate import InProcessCommands, strings


def compare_spec(cfg: DictConfig):
    """The :class:`~spread.experiments.compare.CompareSpec` of a composed ``conf/compare.yaml``."""
    from spread.experiments.compare import METHODS, TRAINED, CompareSpec

    root = cfg.data.root
    return CompareSpec(
        out_dir=Path(str(cfg.out_dir)), data_root=None if root in (None, "") else Path(str(root)),
        split=str(cfg.data.split), methods=tuple(str(m) for m in cfg.methods),
        generate=strings(cfg.data.generate) + strings(cfg.data.get("extra")),
        train=strings(cfg.train.overrides) + strings(cfg.train.get("extra")),
        train_method={m: strings(cfg.train.get(m)) for m in TRAINED},
        ckpt={k: (None if v in (None, "") else str(v)) for k, v in (cfg.train.get("ckpt") or {}).items()},
        box_guidance=OmegaConf.to_container(cfg.physcene.box_guidance, resolve=True),
        sample=strings(cfg.sample.overrides) + strings(cfg.sample.get("extra")),
        sample_method={m: strings(cfg.sample.get(m)) for m in METHODS},
        evaluate=strings(cfg.evaluate.overrides) + strings(cfg.evaluate.get("extra")),
        layout=str(cfg.layout), title=str(cfg.get("title") or ""), group=f"compare_{cfg.name}")


def run(cfg: DictConfig):
    """The comparison of ``cfg`` (a composed ``conf/compare.yaml``); returns the CompareResult."""
    from spread.cli.train import set_threads
    from spread.experiments.compare import log_table1, run_comparison

    set_threads(cfg.get("threads"))
    spec = compare_spec(cfg)
    log_table = None
    if cfg.logger.name == "wandb":
        def log_table(records, columns):
            log_table1(records, columns, spec.out_dir, mode=str(cfg.logger.mode), project=str(cfg.logger.project),
                       name=cfg.logger.run_name or f"table1/{cfg.name}", tags=list(cfg.logger.tags or []),
                       group=spec.group, config=OmegaConf.to_container(cfg, resolve=True))
    elif cfg.logger.name != "none":
        raise SystemExit(f"spread-compare: unknown logger '{cfg.logger.name}' (wandb or none)")
    return run_comparison(spec, InProcessCommands(), log_table)


def report(result, cfg: DictConfig) -> None:
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


@hydra.main(config_path=conf_dir(), config_name="compare", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = run(cfg)
    report(result, cfg)
    if not result.ok:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
