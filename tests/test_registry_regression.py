"""Behaviour unchanged by the registries (issue 22): the fixed run of ``tests/regression.py`` — a small generated
dataset's jittered test scenes through ``spread-evaluate``, and four guidance ``refine`` iterations — gives every
per-scene value, every ``metrics.json`` number and every guided state recorded in ``tests/data/regression.json``
before evaluation and guidance were rebuilt on the registries."""

import json
import math

from regression import FIXTURE, compute


def assert_same(new, old, where: str) -> None:
    if isinstance(old, dict):
        assert isinstance(new, dict) and set(new) >= set(old), f"{where}: keys {sorted(old)} vs {new!r}"
        for k in old:
            assert_same(new[k], old[k], f"{where}.{k}")
    elif isinstance(old, list):
        assert isinstance(new, list) and len(new) == len(old), f"{where}: {new!r} != {old!r}"
        for i, (a, b) in enumerate(zip(new, old)):
            assert_same(a, b, f"{where}[{i}]")
    elif isinstance(old, float):
        assert isinstance(new, (int, float)) and math.isclose(new, old, rel_tol=1e-12, abs_tol=1e-15), \
            f"{where}: {new!r} != recorded {old!r}"
    else:
        assert new == old, f"{where}: {new!r} != recorded {old!r}"


def test_every_recorded_number_is_unchanged(tmp_path):
    recorded = json.loads(FIXTURE.read_text())
    now = json.loads(json.dumps(compute(tmp_path)))
    assert_same(now, recorded, "regression")
