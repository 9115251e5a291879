"""``spread-report runs=DIR_OR_GLOB [out_dir=DIR]``: runs → comparison table and plots (DESIGN §5).

The work is :func:`spread.experiments.run_report`; this file turns the Hydra config into its arguments
and prints the table. A missing path, a glob that matches nothing or a run without ``metrics.json``
stops the command with a message naming it.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, ListConfig

from spread.cli import conf_dir


def runs_argument(value) -> list[str]:
    """``runs`` as a list of strings (a single path or glob, or a list)."""
    if isinstance(value, (ListConfig, list, tuple)):
        return [str(v) for v in value]
    return [str(value)]


@hydra.main(config_path=conf_dir(), config_name="report", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from rich.console import Console

    from spread.experiments import RunError, run_report

    try:
        result = run_report(runs_argument(cfg.runs), cfg.out_dir, weights=[str(w) for w in cfg.weights],
                            metrics=[str(m) for m in cfg.metrics], title=str(cfg.title or ""))
    except (RunError, ValueError) as exc:
        raise SystemExit(f"spread-report: {exc}") from exc
    console = Console()
    console.print(result.tables["md"].read_text())
    for path in result.unfinished:
        console.print(f"[yellow]skipped (no metrics.json yet): {path}[/yellow]")
    console.print(f"{len(result.records)} runs; table {result.tables['md']}, {result.tables['csv']}; "
                  f"{len(result.plots)} plots in {result.tables['md'].parent / 'plots'}")


if __name__ == "__main__":
    main()
