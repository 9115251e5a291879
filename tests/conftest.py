"""Shared fixtures. wandb is disabled in tests; nothing here touches the network."""

import os

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")
