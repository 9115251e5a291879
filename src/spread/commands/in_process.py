"""The commands as one object, run in this process: what a study's stages call
(:class:`~spread.experiments.stages.Commands`) and what a sweep's trials call."""

from __future__ import annotations

from pathlib import Path

from spread.commands.evaluate import evaluate
from spread.commands.generate import generate
from spread.commands.sample import sample
from spread.commands.train import train


class InProcessCommands:
    """:class:`~spread.experiments.stages.Commands` backed by the functions above: each stage composes its
    command's config from the stage's overrides and runs it (which records the config in its folder)."""

    def generate(self, overrides: list[str]) -> None:
        from spread.configs import compose

        generate(compose("generate", overrides))

    def train(self, overrides: list[str], run_dir: Path) -> None:
        from spread.configs import compose

        train(compose("train", overrides), run_dir=run_dir, overrides=overrides)

    def sample(self, overrides: list[str]) -> None:
        from spread.configs import compose

        sample(compose("sample", overrides), log=False, overrides=overrides)

    def evaluate(self, overrides: list[str]) -> dict:
        from spread.configs import compose

        return evaluate(compose("evaluate", overrides), overrides=overrides).metrics

    def sample_config(self, cfg, overrides: list[str]):
        """``spread-sample`` on an already composed config (a sweep point): (result, evaluation), as
        :func:`spread.commands.sample.sample` returns them."""
        return sample(cfg, overrides=overrides)

    def record_config(self, cfg, folder, overrides: list[str]) -> None:
        """Write ``cfg`` and ``overrides`` into ``folder/.hydra`` (a sweep's training point)."""
        from spread.commands.common import record_config

        record_config(cfg, folder, overrides)()
