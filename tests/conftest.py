"""Shared fixtures. wandb is disabled in tests; nothing here touches the network."""

import os

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")

import shutil
import tempfile

import pytest

_OWN_CACHE: list[str] = []


def pytest_configure(config):
    """One cache folder per test session (helpers.SESSION_CACHE), made by the first process (xdist's controller,
    before its workers start, so they inherit it) and removed by it at the end."""
    if "SPREAD_TEST_CACHE" not in os.environ:
        _OWN_CACHE.append(tempfile.mkdtemp(prefix="spread-test-cache-"))
        os.environ["SPREAD_TEST_CACHE"] = _OWN_CACHE[0]


def pytest_unconfigure(config):
    for folder in _OWN_CACHE:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop("SPREAD_TEST_CACHE", None)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """torch on one intra-op thread per test module: on a small shared CPU two threads are many times slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


#: test modules by their share of a ``make test`` run, heaviest first (measured on 2 cores, 2026-11-29: 222 s down
#: to 16 s of ~2,000 s). With ``--dist loadfile`` each module goes whole to one worker in collection order (the
#: Makefile passes ``--no-loadscope-reorder``: xdist would otherwise order modules by their number of tests);
#: handing out the long ones first keeps both workers busy to the end instead of leaving one long module alone at
#: the tail.
HEAVY_MODULES = ("test_hostile_round4", "test_evaluate", "test_ablate_report", "test_scaleout", "test_compare",
                 "test_command_lines",
                 "test_dashboard", "test_gpu_paths", "test_train_sample", "test_ablate_seeds", "test_robustness",
                 "test_plugins", "test_procgen", "test_cli_defaults", "test_hostile_inputs", "test_hostile_round5",
                 "test_hostile_round6", "test_hostile_round6_view",
                 "test_registry_regression",
                 "test_readonce", "test_documented_commands", "test_clean_stops", "test_assets", "test_notebooks")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: each module's own order kept
