"""``spread-sample ckpt=PATH data.root=DIR out_dir=OUT``: a checkpoint + test graphs → scene files (DESIGN §5).

``guidance=paper|refine`` samples with physics guidance; ``evaluate=true`` then evaluates ``out_dir/scenes``
into ``out_dir/metrics.json`` — one run folder per point of a guidance sweep. The work is
:func:`spread.commands.sample.sample`.
"""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-sample", config="sample")
def main(cfg: DictConfig) -> None:
    from spread.commands.evaluate import print_evaluation_summary
    from spread.commands.sample import print_sampling_summary, sample

    result, evaluation = sample(cfg)
    if evaluation is not None:
        print_evaluation_summary(evaluation.metrics, evaluation.out_dir)
    if result is not None:
        print_sampling_summary(result)
    if evaluation is not None and evaluation.metrics["n_evaluated"] == 0:
        raise SystemExit(f"spread-sample: none of the {evaluation.metrics['n_scenes']} sampled scenes could be evaluated")


if __name__ == "__main__":
    main()
