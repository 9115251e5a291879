"""Shared fixtures. wandb is disabled in tests; nothing here touches the network."""

import os

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")

import pytest


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """torch on one intra-op thread per test module: on a small shared CPU two threads are many times slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
