"""``spread-evaluate scenes=DIR reference=DATASET_DIR out_dir=OUT``: scene files → metrics (DESIGN §5, §6).

Writes ``OUT/metrics.json``, ``OUT/per_scene.jsonl``, ``OUT/renders/`` and, with ``logger=wandb`` (the
default, offline), ``OUT/wandb/``. The work is :func:`spread.distributed.run_evaluation`; this file only
turns the Hydra config into its arguments and prints a summary.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir


def eval_protocol(protocol: DictConfig, fid: DictConfig, seed: int):
    """The :class:`~spread.distributed.EvalProtocol` of a ``protocol`` and a ``fid`` config node
    (``conf/protocol``, ``conf/fid``; shared by spread-evaluate and ``spread-sample evaluate=true``)."""
    from spread.distributed import EvalProtocol

    return EvalProtocol(**OmegaConf.to_container(protocol, resolve=True), seed=int(seed),
                        fid_enabled=bool(fid.enabled), fid_feature_model=str(fid.feature_model),
                        fid_weights_path=fid.weights_path, fid_extractor=fid.extractor, fid_device=str(fid.device))


def evaluation_config(cfg: DictConfig):
    """The :class:`~spread.distributed.EvaluationConfig` of a composed ``conf/evaluate.yaml``."""
    from spread.distributed import EvaluationConfig, RaySettings

    try:
        return EvaluationConfig(
            scenes=str(cfg.scenes), reference=str(cfg.reference), out_dir=str(cfg.out_dir),
            reference_split=str(cfg.reference_split), chunk_size=int(cfg.chunk_size), resume=bool(cfg.resume),
            retry_failed=bool(cfg.retry_failed), renders=int(cfg.renders), progress=bool(cfg.progress),
            protocol=eval_protocol(cfg.protocol, cfg.fid, cfg.seed),
            ray=RaySettings(**OmegaConf.to_container(cfg.ray, resolve=True)),
        )
    except TypeError as exc:  # an unknown key under protocol/ray
        raise SystemExit(f"spread-evaluate: bad config: {exc}") from exc


def print_summary(metrics: dict, out_dir) -> None:
    from rich.console import Console
    from rich.table import Table

    def fmt(v, digits=4):
        return "null" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    table = Table(title=f"evaluation {out_dir}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row("Col_mesh (share of objects, ↓)", fmt(metrics["col_mesh"]))
    table.add_row("GRecall (share of pairs, ↑)", fmt(metrics["grecall"]))
    table.add_row("ASD (mm, ↓)", fmt(None if metrics["asd"] is None else 1000 * metrics["asd"], 2))
    table.add_row("Stability (share of pairs, ↑)", fmt(metrics["stability"]))
    table.add_row("still objects (share)", fmt(metrics["still_fraction"]))
    table.add_row("FID", fmt(metrics["fid"], 2))
    table.add_row("scenes / evaluated / failed",
                  f"{metrics['n_scenes']} / {metrics['n_evaluated']} / {metrics['n_failed']}")
    table.add_row("objects", str(metrics["n_objects"]))
    table.add_row("seconds", fmt(metrics["run"]["seconds"], 1))
    console = Console()
    console.print(table)
    if metrics.get("per_room_type"):
        by_type = Table(title="per room type")
        for col in ("room type", "scenes", "Col_mesh", "GRecall", "ASD (mm)", "Stability"):
            by_type.add_column(col, justify="left" if col == "room type" else "right")
        for name, m in metrics["per_room_type"].items():
            by_type.add_row(name, str(m["n_evaluated"]), fmt(m["col_mesh"]), fmt(m["grecall"]),
                            fmt(None if m["asd"] is None else 1000 * m["asd"], 2), fmt(m["stability"]))
        console.print(by_type)
    console.print(f"fid_status: {metrics['fid_status']}")
    for f in metrics["failed"][:10]:
        console.print(f"failed {f['scene_id']}: {f['error']}")


@hydra.main(config_path=conf_dir(), config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.distributed import run_evaluation

    result = run_evaluation(evaluation_config(cfg))
    if cfg.logger.name == "wandb":
        from spread.distributed.wandb_report import log_evaluation

        log_evaluation(result, mode=str(cfg.logger.mode), project=str(cfg.logger.project),
                       name=cfg.logger.run_name, tags=list(cfg.logger.tags or []), group=str(cfg.experiment_name),
                       config=OmegaConf.to_container(cfg, resolve=True))
    elif cfg.logger.name != "none":
        raise SystemExit(f"spread-evaluate: unknown logger '{cfg.logger.name}' (wandb or none)")
    print_summary(result.metrics, result.out_dir)


if __name__ == "__main__":
    main()
