"""``spread-compare +table1=quick``: the paper's Table 1 — every method trained, sampled, evaluated, tabulated.

The work is :func:`spread.commands.compare.compare`. Exit status 1 when a stage failed (the table
is still written, with the failed rows empty).
"""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main
from spread.configs import register

register()


@console_main("spread-compare", config="compare")
def main(cfg: DictConfig) -> None:
    from spread.commands.compare import compare, print_comparison

    result = compare(cfg)
    print_comparison(result)
    if not result.ok:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
