"""``spread-evaluate scenes=DIR reference=DATASET_DIR out_dir=OUT``: scene files → metrics (DESIGN §5, §6).

Writes ``OUT/metrics.json``, ``OUT/per_scene.jsonl``, ``OUT/renders/`` and, with ``logger=wandb`` (the
default, offline), ``OUT/wandb/``. The work is :func:`spread.commands.evaluate.evaluate`.
"""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-evaluate", config="evaluate")
def main(cfg: DictConfig) -> None:
    from spread.commands.evaluate import evaluate, print_evaluation_summary

    result = evaluate(cfg)
    print_evaluation_summary(result.metrics, result.out_dir)
    if result.metrics["n_evaluated"] == 0:  # metrics.json lists why; a run that measured nothing did not succeed
        raise SystemExit(f"spread-evaluate: none of the {result.metrics['n_scenes']} scenes could be evaluated")


if __name__ == "__main__":
    main()
