"""Known third-party noise a user cannot act on, silenced at its source (docs/robustness.md).

Each entry names the library, the message and why it is noise here; nothing else is filtered, and the
filters match the message's start, so a new or changed message still shows.

* Ray: "Token authentication is enabled for this Ray cluster ..." (a warning at every ``ray.init`` of a
  private local cluster, which this platform starts on 127.0.0.1 for one command): the logger of Ray's
  token setup is raised to ERROR while :func:`spread.runtime.ray_session` starts Ray.
* Lightning: "💡 Tip: ... litlogger / litmodels" advertisements (INFO on every fit).
* Lightning: "`isinstance(treespec, LeafSpec)` is deprecated" (Lightning's own use of a torch API; the
  platform cannot change it).
* wandb: "The anonymous setting has no effect" (Lightning's WandbLogger passes ``anonymous=None``): the key
  is removed from the logger's init arguments in :func:`spread.tracking.loggers.lightning_loggers`.
"""

from __future__ import annotations

import contextlib
import logging
import warnings

#: Message starts dropped from Lightning's rank-zero logger.
LIGHTNING_NOISE = ("💡 Tip:",)
#: Python warnings (regular expressions of the message) silenced everywhere.
WARNING_NOISE = (r"`isinstance\(treespec, LeafSpec\)` is deprecated",)
#: Ray's logger of the token-authentication notice.
RAY_TOKEN_LOGGER = "ray._private.authentication.authentication_token_setup"


class _DropStarts(logging.Filter):
    def __init__(self, starts: tuple[str, ...]):
        super().__init__()
        self.starts = starts

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).startswith(self.starts)


_INSTALLED = False


def silence_known_noise() -> None:
    """Install the filters of the module docstring (idempotent)."""
    global _INSTALLED
    if _INSTALLED:
        return
    _INSTALLED = True
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).addFilter(_DropStarts(LIGHTNING_NOISE))
    for pattern in WARNING_NOISE:
        warnings.filterwarnings("ignore", message=pattern)


@contextlib.contextmanager
def quiet_ray_start():
    """Ray's token-authentication notice silenced while Ray starts (errors still show)."""
    logger = logging.getLogger(RAY_TOKEN_LOGGER)
    before = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(before)
