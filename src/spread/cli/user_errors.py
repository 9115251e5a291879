"""Which exceptions report a bad setting or input (a user error, told in one line) and which are bugs
(:mod:`spread.cli.errors`, which names these too)."""

from __future__ import annotations

import os


def verbose() -> bool:
    return any(os.environ.get(v, "") not in ("", "0") for v in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG"))


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exceptions that report a bad setting or input (not a bug): their message is the whole story."""
    from hydra.errors import ConfigCompositionException, OverrideParseException

    from omegaconf.errors import MissingMandatoryValue

    from spread.io import RunFolderBusy, UnsafeOutputError

    # Hydra's: an override that names no key of the config or does not parse (a command that composes configs
    # itself, as spread-sweep and spread-ablate do for their points and stages); OmegaConf's: a required setting
    # (``???``) read while unset (a multirun, which is not composed before Hydra runs). A ``???`` read through an
    # interpolation is a ValueError already (InterpolationToMissingValueError).
    return (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError,
            RunFolderBusy, UnsafeOutputError, ConfigCompositionException, OverrideParseException,
            MissingMandatoryValue)


def user_error(exc: BaseException) -> BaseException | None:
    """The user error ``exc`` reports (:func:`user_error_types`), or None: ``exc`` itself, or the error a setting's
    constructor raised inside Hydra's ``instantiate`` (which wraps it, naming the target, in an
    ``InstantiationException`` whose cause it is)."""
    if isinstance(exc, user_error_types()):
        return exc
    try:
        from hydra.errors import InstantiationException
    except ImportError:  # pragma: no cover — Hydra is a dependency of every console script
        return None
    while isinstance(exc, InstantiationException) and exc.__cause__ is not None:  # nested instantiates too
        exc = exc.__cause__
        if isinstance(exc, user_error_types()):
            return exc
    return None
