"""Thin Hydra entry points. Configs live in the repository's ``conf/`` (or ``$SPREAD_CONF_DIR``)."""

from __future__ import annotations

import os
from pathlib import Path


def conf_dir() -> str:
    """Absolute path of the Hydra config folder."""
    env = os.environ.get("SPREAD_CONF_DIR")
    if env:
        return str(Path(env).resolve())
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "conf" / "generate.yaml").exists():
            return str(parent / "conf")
    raise FileNotFoundError("cannot find the conf/ folder; set SPREAD_CONF_DIR to the repository's conf/")
