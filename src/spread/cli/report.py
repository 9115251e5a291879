"""``spread-report runs=DIR_OR_GLOB [out_dir=DIR] [compare=[A,B]]``: runs → comparison table and plots (DESIGN §5);
a sweep folder also gets its analysis section (:mod:`spread.results.analysis`; ``compare``: two of its points).

The work is :func:`spread.reporting.report.run_report`. A missing path, a glob that matches nothing or a run
without ``metrics.json`` stops the command with a message naming it.
"""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-report", config="report")
def main(cfg: DictConfig) -> None:
    from spread.reporting.report import print_report, run_report, runs_argument
    from spread.reporting.runs import RunError
    from spread.commands.common import record_config

    from spread.io import check_folder_kind, run_lock
    from spread.results.analysis import report_analysis

    try:
        check_folder_kind(cfg.out_dir, "spread-report", {"report"})  # a run's folder: its record and files kept
        weights = None if cfg.get("weights") is None else [str(w) for w in cfg.weights]
        compare = None if cfg.get("compare") is None else [str(p) for p in cfg.compare]
        analysis = report_analysis(runs_argument(cfg.runs), compare)  # a sweep folder's section (spread.results)
        with run_lock(cfg.out_dir, "spread-report"):
            result = run_report(runs_argument(cfg.runs), cfg.out_dir, weights=weights,
                                metrics=None if cfg.metrics is None else [str(m) for m in cfg.metrics],
                                title=str(cfg.title or ""), analysis=analysis)
            record_config(cfg, cfg.out_dir)()
    except (RunError, ValueError) as exc:
        raise SystemExit(f"spread-report: {exc}") from exc
    print_report(result)


if __name__ == "__main__":
    main()
