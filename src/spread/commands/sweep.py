"""``spread-sweep``'s body: the sweep of a command line (:func:`spread.experiments.sweep.parse_arguments`), its
trials running this package's commands in Ray Tune's trial processes
(:class:`~spread.commands.in_process.InProcessCommands`)."""

from __future__ import annotations


def sweep(args: list[str]):
    """Parse the command line's arguments into a plan and run it; returns the
    :class:`~spread.experiments.sweep.SweepResult` (``ValueError``: a bad setting, before any trial)."""
    from spread.commands.in_process import InProcessCommands
    from spread.experiments.sweep import parse_arguments, run_sweep

    return run_sweep(parse_arguments(args), InProcessCommands())
