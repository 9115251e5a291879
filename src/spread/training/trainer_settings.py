"""``trainer.*`` settings checked against Lightning's ``Trainer`` arguments before a training launch records its
config, opens a logger run or starts Ray (docs/robustness.md).

Lightning's own refusal comes only when the trainer is built, after the run's config was recorded and its wandb /
MLflow run opened, and it names no setting (``'<' not supported between instances of 'str' and 'int'`` for
``trainer.max_steps=abc``). :func:`trainer_setting_problem` names the key, the value and what the argument takes,
from the ``Trainer.__init__`` annotations of the installed Lightning.
"""

from __future__ import annotations

import functools
import re
import typing


@functools.cache
def _trainer_arguments() -> tuple[dict, bool]:
    """``Trainer.__init__``'s annotations by argument name, and whether it takes ``**kwargs``."""
    import inspect

    from lightning.pytorch import Trainer

    parameters = inspect.signature(Trainer.__init__).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    try:
        hints = typing.get_type_hints(Trainer.__init__)
    except Exception:  # noqa: BLE001 — an annotation this Python cannot evaluate: names are still checked
        hints = {}
    return {name: hints.get(name, typing.Any) for name in parameters if name != "self"}, takes_any


def accepts(annotation, value) -> bool:
    """Whether a plain config value (None, bool, int, float, str, list, dict) fits ``annotation``; a class this
    cannot judge from a config value (an ``Accelerator``, a ``timedelta``) accepts it, and Lightning decides."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is typing.Any:
        return True
    if origin is typing.Union:
        return any(accepts(a, value) for a in args)
    if origin is typing.Literal:
        return any(value == a and type(value) is type(a) for a in args)
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin is list:
        return isinstance(value, list) and all(accepts(args[0], v) for v in value) if args else isinstance(value, list)
    if origin is dict:
        return isinstance(value, dict)
    return True  # a class (Accelerator, timedelta, Path, …): a config value with ``_target_`` or one Lightning converts


def _alternatives(annotation) -> list[str]:
    """``annotation`` as the values or types it allows, flattened (``Optional[int]`` → ``int``, ``None``)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Union:
        return [alt for a in args for alt in _alternatives(a)]
    if origin is typing.Literal:
        return [repr(a) for a in args]
    if annotation is type(None):
        return ["None"]
    if origin is not None:  # list[int]
        return [str(annotation).replace("typing.", "")]
    return [getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")]


def _spelled(annotation) -> str:
    alternatives = _alternatives(annotation)
    return alternatives[0] if len(alternatives) == 1 else "one of " + ", ".join(alternatives)


def trainer_setting_problem(trainer_cfg, overrides: dict | None = None) -> str | None:
    """What is wrong with ``trainer_cfg`` (the composed ``trainer`` node) as Lightning ``Trainer`` arguments, in one
    line, or None: an argument the Trainer does not take, or a value its annotation does not allow. Keys in
    ``overrides`` (a launcher's own arguments, Ray Train's strategy and plugins) are not the user's and are not
    checked; a node whose ``_target_`` is not Lightning's Trainer is not checked."""
    from omegaconf import DictConfig, OmegaConf

    values = OmegaConf.to_container(trainer_cfg, resolve=True) if isinstance(trainer_cfg, DictConfig) \
        else dict(trainer_cfg or {})
    target = str(values.pop("_target_", ""))
    if target not in ("lightning.pytorch.Trainer", "lightning.Trainer", "lightning.pytorch.trainer.trainer.Trainer",
                      "pytorch_lightning.Trainer"):
        return None
    arguments, takes_any = _trainer_arguments()
    problems = []
    for key, value in values.items():
        if key in (overrides or {}) or key.startswith("_"):
            continue
        if key not in arguments:
            if not takes_any:
                problems.append(f"trainer.{key}: Lightning's Trainer takes no such argument")
            continue
        if not accepts(arguments[key], value):
            problems.append(f"trainer.{key}={value!r}: Lightning's Trainer takes {_spelled(arguments[key])} here")
    return "; ".join(problems) or None


def target_setting_problem(node, key: str) -> str | None:
    """What is wrong with a config node that builds a class (``_target_``: the ``checkpoint`` node, a
    ``callbacks.<name>`` node) as that class's constructor arguments, in one line, or None: a value its
    ``__init__`` annotation does not allow (``checkpoint.every_n_train_steps=1.5`` checkpointed at step 3 only).
    A target that cannot be imported is left to the build (:func:`built`), which names it."""
    import inspect

    from hydra.utils import get_class
    from omegaconf import DictConfig, OmegaConf

    values = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node or {})
    target = values.pop("_target_", None)
    if not target:
        return None
    try:
        cls = get_class(str(target))
        parameters = inspect.signature(cls.__init__).parameters
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # noqa: BLE001 - not importable, or annotations this Python cannot evaluate: the build decides
        return None
    problems = [f"{key}.{name}={value!r}: {cls.__name__} takes {_spelled(hints[name])} here"
                for name, value in values.items()
                if not name.startswith("_") and name in parameters and name in hints and not accepts(hints[name], value)]
    return "; ".join(problems) or None


def check_renders(renders) -> None:
    """The ``renders`` node (:class:`~spread.training.renders.SampleRenders`): ``every_n_epochs`` (0: off), ``scenes``
    and ``seed`` whole numbers, ``sampler`` one the platform knows, refused by key (``renders.scenes=1.5`` rendered
    one scene; ``renders.sampler=bogus-7`` failed at the first render epoch, after that training)."""
    from spread.checks import whole_number

    for name, least, note in (("every_n_epochs", 0, "(0: off)"), ("scenes", 1, ""), ("seed", 0, "")):
        if renders is not None and name in renders:
            whole_number(renders[name], f"renders.{name}", least, note=note)
    if renders is not None and renders.get("sampler") is not None:  # an unknown one failed at the first render
        from omegaconf import DictConfig, OmegaConf

        from spread.model.sampler import Sampler

        sampler = renders["sampler"]
        try:
            Sampler.from_config(OmegaConf.to_container(sampler) if isinstance(sampler, DictConfig) else sampler)
        except Exception as exc:  # noqa: BLE001 - the registry's or the sampler's own refusal, named by key
            raise ValueError(f"renders.sampler={sampler!r}: {exc}") from None


#: ``trainer.max_time`` as Lightning's ``Timer`` reads a text: days, then hours, minutes and seconds of two digits.
MAX_TIME = re.compile(r"(\d+):(\d\d):(\d\d):(\d\d)")


def max_time_seconds(value, key: str = "trainer.max_time") -> float | None:
    """``trainer.max_time`` in seconds (None: no limit): a ``DD:HH:MM:SS`` text or an object of ``timedelta``'s
    arguments (``{minutes: 4}``), as Lightning's ``Timer`` takes them; else ``ValueError`` by key."""
    import datetime
    import math

    if value is None:
        return None
    if isinstance(value, str):
        match = MAX_TIME.fullmatch(value.strip())
        if match:
            days, hours, minutes, seconds = map(int, match.groups())
            return float(((days * 24 + hours) * 60 + minutes) * 60 + seconds)
    elif isinstance(value, dict) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                   and math.isfinite(v) and v >= 0 for v in value.values()):
        try:
            return datetime.timedelta(**value).total_seconds()
        except (TypeError, OverflowError):
            pass
    raise ValueError(f"{key}={value!r}: expected DD:HH:MM:SS (days, then hours, minutes and seconds of two digits: "
                     f"00:00:04:00), an object such as {{minutes: 4}}, or null for no limit")


def _whole(least: int) -> typing.Callable:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= least


def _fraction_or_count(v) -> bool:  # a float is a share of the batches, an int a count
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0 or isinstance(v, float) and 0.0 <= v <= 1.0


def _finite_at_least_0(v) -> bool:
    import math

    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


#: The range each ``Trainer`` argument's value must fall in, beyond its type (:func:`trainer_setting_problem`): a
#: value outside failed only when Lightning built the trainer — after the run's config was recorded — or mid-fit
#: (``accumulate_grad_batches=0``: ZeroDivisionError) or at the first step (``gradient_clip_val=nan``). None is
#: checked by the type (where the argument takes it).
TRAINER_RANGES = {
    "max_steps": (_whole(-1), "a whole number ≥ -1 (-1: no limit)"),
    "max_epochs": (_whole(-1), "a whole number ≥ -1 (-1: no limit), or null"),
    "min_steps": (_whole(0), "a whole number ≥ 0, or null"),
    "min_epochs": (_whole(0), "a whole number ≥ 0, or null"),
    "accumulate_grad_batches": (_whole(1), "a whole number ≥ 1"),
    "check_val_every_n_epoch": (_whole(1), "a whole number ≥ 1, or null"),
    "log_every_n_steps": (_whole(1), "a whole number ≥ 1"),
    "num_sanity_val_steps": (_whole(-1), "a whole number ≥ -1 (-1: every batch)"),
    "devices": (lambda v: not isinstance(v, int) or isinstance(v, bool) or v >= 1 or v == -1,
                "a whole number ≥ 1 or -1 (every device), a list of device indices, or 'auto'"),
    "num_nodes": (_whole(1), "a whole number ≥ 1"),
    "gradient_clip_val": (_finite_at_least_0, "a finite number ≥ 0 (0 or null: no clipping)"),
    **{f"limit_{stage}_batches": (_fraction_or_count, "a share of the batches in [0.0, 1.0] or a whole count ≥ 0")
       for stage in ("train", "val", "test", "predict")},
    "val_check_interval": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1
                           or isinstance(v, float) and 0.0 < v <= 1.0,
                           "a share of an epoch in (0.0, 1.0] or a whole number of batches ≥ 1, or null"),
}


def trainer_range_problem(trainer_cfg, overrides: dict | None = None) -> str | None:
    """What of ``trainer_cfg`` falls outside its argument's range (:data:`TRAINER_RANGES`, ``max_time``:
    :func:`max_time_seconds`), in one line, or None; keys in ``overrides`` (a launcher's own) are not checked."""
    from omegaconf import DictConfig, OmegaConf

    values = OmegaConf.to_container(trainer_cfg, resolve=True) if isinstance(trainer_cfg, DictConfig) \
        else dict(trainer_cfg or {})
    problems = []
    for key, value in values.items():
        if key in (overrides or {}) or value is None:
            continue
        if key == "max_time":
            try:
                max_time_seconds(value)
            except ValueError as exc:
                problems.append(str(exc))
        elif key in TRAINER_RANGES and not TRAINER_RANGES[key][0](value):
            problems.append(f"trainer.{key}={value!r}: expected {TRAINER_RANGES[key][1]}")
    return "; ".join(problems) or None


def check_checkpoint_filename(node) -> None:
    """``checkpoint.filename`` names a file in the run's ``checkpoints/`` folder: a path that leaves it (``..``, or
    absolute: ``"../../esc/s{step}"`` wrote checkpoints outside the run) is refused by key (``ValueError``)."""
    from pathlib import PurePosixPath, PureWindowsPath

    name = None if node is None else node.get("filename")
    if name is None:
        return
    text = str(name)
    parts = PurePosixPath(text.replace("\\", "/")).parts
    if not text.strip() or PurePosixPath(text).is_absolute() or PureWindowsPath(text).is_absolute() or ".." in parts:
        raise ValueError(f"checkpoint.filename={text!r}: a checkpoint's name within the run's checkpoints/ folder "
                         f"(no '..', not absolute), such as step{{step:07d}}")


def check_trainer_settings(trainer_cfg, overrides: dict | None = None) -> None:
    """Raise ``ValueError`` (one line, the command's refusal) for :func:`trainer_setting_problem`, then for
    :func:`trainer_range_problem`."""
    problem = trainer_setting_problem(trainer_cfg, overrides) or trainer_range_problem(trainer_cfg, overrides)
    if problem:
        raise ValueError(problem)


def check_training_settings(cfg, overrides: dict | None = None) -> None:
    """Before a training launch records its config or opens a logger run: the ``trainer.*`` values
    (:func:`check_trainer_settings`), ``seed`` (Lightning's, a whole number in [0, 2³²)), ``threads`` (≥ 1, or null
    for torch's default), ``renders.*`` and the ``checkpoint`` / ``callbacks.*`` constructor arguments, each refused
    by key (``ValueError``)."""
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 32:
        raise ValueError(f"seed={seed!r}: expected a whole number in [0, 2**32)")
    from spread.checks import true_or_false

    true_or_false(cfg.get("fresh", False), "fresh")  # fresh=no moved the run aside: a non-empty text is true
    check_checkpoint_filename(cfg.get("checkpoint"))
    from spread.runtime.threads import check_threads

    check_threads(cfg.get("threads"))
    check_trainer_settings(cfg.trainer, overrides)
    check_renders(cfg.get("renders"))
    callbacks = cfg.get("callbacks") or {}
    nodes = [("checkpoint", cfg.get("checkpoint"))] + [(f"callbacks.{k}", v) for k, v in callbacks.items()]
    for key, node in nodes:
        problem = target_setting_problem(node, key)
        if problem:
            raise ValueError(problem)


def built(make, key: str):
    """``make()`` (a Hydra ``instantiate`` of the config node ``key``), its constructor's refusal as ``ValueError``
    naming the key (Lightning's ``MisconfigurationException`` is no ValueError, and Hydra wraps it in a traceback)."""
    from hydra.errors import InstantiationException

    try:
        return make()
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        text = " ".join(str(cause).split())
        if isinstance(cause, ValueError) and text.startswith(f"{key}."):  # it names the key already, as is
            raise ValueError(text) from exc
        raise ValueError(f"{key}: {type(cause).__name__}: {text}") from exc
