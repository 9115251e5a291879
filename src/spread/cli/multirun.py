"""A multirun's jobs, composed before the first one runs (``spread-sample -m ... sampler.kind=ddim,nope``).

Hydra's basic sweeper composes every job before it launches any, but with Hydra's composition only: a value the
platform's settings refuse when they are built (an unknown sampler kind, ``sampler.eta`` on a sampler that does not
read it, a required setting left unset) was found only when its job started — after the jobs before it had run,
which for a sweep of training or sampling runs is hours. :func:`multirun_problem` expands the command line into its
jobs the way Hydra's basic sweeper does (the config's ``hydra.sweeper.params``, then the command line's sweeps; the
last value given for a key wins) and checks each job as a single run is checked (:func:`spread.cli.errors.
compose_problem`) and builds its settings (:func:`built_problem`), so a bad job is refused, by its number and its
overrides, before the first job starts."""

from __future__ import annotations

#: Hydra's flags that run the command line as a multirun; any other flag (``--cfg``, ``--help``, …) is Hydra's.
MULTIRUN_FLAGS = ("-m", "--multirun")
#: The sweeper whose expansion this module repeats; another (Optuna, Ax, …) chooses its jobs as it runs.
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
#: Up to this many jobs every job is composed (~0.15 s each); above, each swept value is composed once, with the
#: other keys at their first value (:func:`covering_jobs`), so the check stays a few seconds for any grid.
ALL_JOBS_LIMIT = 64


def is_multirun(args: list[str]) -> bool:
    """Whether ``args`` run as a multirun this module expands: ``-m``/``--multirun`` and no other Hydra flag."""
    flags = [a for a in args if a.startswith("-")]
    return bool(flags) and all(f in MULTIRUN_FLAGS for f in flags)


def sweep_jobs(config: str, args: list[str]) -> list[list[str]] | None:
    """The task overrides of each job of the multirun ``args`` of ``conf/<config>.yaml``, in Hydra's order (job
    ``#0`` first), or None where Hydra's basic sweeper does not choose the jobs (another ``hydra/sweeper``). Raises
    Hydra's error for a command line that does not parse or a master config that does not compose."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from spread.configs import COMMANDS, conf_dir, register

    register(config) if config in COMMANDS else register()
    words = [a for a in args if a not in MULTIRUN_FLAGS]
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):  # the loader lists a group (glob)
        parser = OverridesParser.create(config_loader=GlobalHydra.instance().config_loader())
        parsed = parser.parse_overrides(words)
        master = [o.input_line for o in parsed if not o.is_sweep_override()]
        hydra = compose(config_name=config, overrides=master, return_hydra_config=True).hydra
        if str(hydra.sweeper.get("_target_", "")) != BASIC_SWEEPER:
            return None
        task = [o.input_line for o in parsed if not o.is_hydra_override()]
        params = [f"{k}={v}" for k, v in (hydra.sweeper.get("params") or {}).items()]
        return BasicSweeper.split_arguments(parser.parse_overrides(params + task), None)[0]


def covering_jobs(jobs: list[list[str]]) -> list[list[str]]:
    """Fewer jobs that hold every override of ``jobs`` (a full grid, each job one override per key in one order):
    the first job, then each other value of each key with the other keys as in the first job."""
    if not jobs:
        return []
    first, out, seen = jobs[0], [jobs[0]], set(jobs[0])
    for job in jobs[1:]:
        for i, override in enumerate(job):
            if override not in seen:
                seen.add(override)
                out.append(first[:i] + [override] + first[i + 1:])
    return out


def multirun_problem(config: str, args: list[str], name: str, single) -> str | None:
    """Why a job of the multirun ``args`` cannot run, in one line naming the job (Hydra's number and the overrides
    that make it other than the rest), or None (also where another sweeper chooses the jobs). ``single(config,
    job, name)``: a single run's check, (problem or None, the composed config) (:func:`spread.cli.errors.
    composed_ahead`)."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from spread.configs import error_message

    try:
        jobs = sweep_jobs(config, args)
    except (HydraException, OmegaConfBaseException) as exc:
        return error_message(exc)
    except Exception:  # noqa: BLE001 — a command line this expansion cannot follow is left to Hydra, which says
        return None
    if not jobs:
        return None
    numbered = list(enumerate(jobs))
    if len(jobs) > ALL_JOBS_LIMIT:
        index = {tuple(job): n for n, job in numbered}
        numbered = [(index[tuple(job)], job) for job in covering_jobs(jobs)]  # each is a job of the grid
    swept = [i for i in range(len(jobs[0])) if len({job[i] for job in jobs}) > 1]
    folders: dict[str, list[int]] = {}
    for number, job in numbered:
        problem, composed = single(config, job, name)
        problem = problem or built_problem(composed) or trainer_problem(composed, job)
        if problem:
            which = " ".join(job[i] for i in swept) or " ".join(job)
            return f"job #{number} of the multirun ({which}): {problem}"
        folders.setdefault(job_folder(composed), []).append(number)
    shared = {folder: numbers for folder, numbers in folders.items() if folder is not None and len(numbers) > 1}
    if not shared:
        return None
    folder, (a, b) = next((f, n[:2]) for f, n in shared.items())  # the later would redo, refuse or delete the earlier
    keys = [o.lstrip("+~").split("=", 1)[0] for o, p in zip(jobs[a], jobs[b]) if o != p]
    if not keys:
        return f"job #{b} of the multirun repeats job #{a} (both write to out_dir={folder}): give each setting once"
    return (f"jobs #{a} and #{b} of the multirun write to one out_dir={folder}: the later job would redo, refuse or "
            f"delete what the earlier one wrote; give each job its own out_dir, one that names the swept keys "
            f"(e.g. 'out_dir={folder}/{'_'.join('${' + k + '}' for k in keys)}')")


def job_folder(composed) -> str | None:
    """A composed job's ``out_dir`` as an absolute path, or None: no ``out_dir``, one only the running app resolves
    (``${hydra:...}``), or one that holds the time (``${now:...}``: each job resolves it when it starts)."""
    import os

    from omegaconf import OmegaConf

    if composed is None or "out_dir" not in composed:
        return None
    try:
        raw = OmegaConf.to_container(composed, resolve=False).get("out_dir")
        value = composed.get("out_dir")
    except Exception:  # noqa: BLE001 - an interpolation only the running app resolves
        return None
    if not isinstance(value, str) or not value or "now:" in str(raw):
        return None
    return os.path.abspath(os.path.expanduser(value))


def built_problem(composed) -> str | None:
    """What a composed job's settings refuse when they are built as the command builds them (its schema's
    dataclasses and their checks: ``sampler.eta`` on a sampler that does not read it, an unknown sampler kind), in
    one line, or None — also for a command without a schema (its settings are built by its code) and for a value
    only the running app can resolve (``${hydra:...}``)."""
    import dataclasses

    from omegaconf import OmegaConf
    from omegaconf.errors import InterpolationResolutionError

    from spread.cli.user_errors import user_error
    from spread.configs import error_message

    if composed is None or not dataclasses.is_dataclass(OmegaConf.get_type(composed)):
        return None
    try:
        OmegaConf.to_object(composed)
    except InterpolationResolutionError:
        return None
    except Exception as exc:  # noqa: BLE001 — a user error is the job's problem; anything else is the app's to say
        cause = user_error(exc)
        return error_message(cause) if cause is not None else None
    return None


def trainer_problem(composed, job: list[str]) -> str | None:
    """What Lightning's ``Trainer`` refuses of a job's ``trainer.*`` values (:func:`spread.training.trainer_settings.
    trainer_setting_problem`: ``trainer.max_steps=abc``), in one line, or None; asked only of a job whose overrides
    set the trainer, since the check loads Lightning (a single run asks it in the app, as each job always did)."""
    if composed is None or "trainer" not in composed:
        return None
    if not any(o.lstrip("+~").split("=", 1)[0].split(".", 1)[0] in ("trainer", "experiment") for o in job):
        return None
    from spread.training.trainer_settings import trainer_setting_problem

    try:
        return trainer_setting_problem(composed.trainer)
    except Exception:  # noqa: BLE001 — a value only the running app resolves: the job's own check says it
        return None


__all__ = ["ALL_JOBS_LIMIT", "built_problem", "covering_jobs", "is_multirun", "job_folder", "multirun_problem",
           "sweep_jobs", "trainer_problem"]
