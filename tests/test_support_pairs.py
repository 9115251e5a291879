"""benchmarks/support_pairs.py: a sampled room's support pairs by supporter category (signed distance, metres) and
its colliding pairs by kind, on a hand-made room whose answers are known."""

from __future__ import annotations


import numpy as np
import pytest

from spread.assets.assemble import box_asset, library_from_specs
from spread.scene import PHYSICAL_SUPPORT

from helpers import load_script, scene_of


@pytest.fixture(scope="module")
def sp():
    return load_script("support_pairs")


def test_a_sunk_support_pair_a_pair_overlapping_in_the_room_and_another_pair_are_told_apart(sp, tmp_path):
    lib = library_from_specs(tmp_path / "assets", [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("mug", (0.08, 0.1, 0.08), category="mug"),
        box_asset("chair", (0.45, 0.9, 0.45), category="chair", role="furniture"),
        box_asset("crate", (0.3, 0.3, 0.3), category="box"),
    ])
    ids = ["table", "mug", "chair", "crate"]
    physical = np.zeros((4, 4), np.int8)
    physical[0, 1] = PHYSICAL_SUPPORT  # the table holds the mug
    # the test room: the mug on the table, the chair pushed 17.5 cm under the table's edge, the crate far away
    room = scene_of(ids, [[0, 0.375, 0], [0, 0.80, 0], [0.55, 0.45, 0], [2.0, 0.15, 0]], library=lib,
                    physical=physical)
    # the sample: the mug sunk 5 cm into the table, the chair as in the room, the crate 7.5 cm into the chair only
    sample = room.with_poses(np.array([[0, 0.375, 0], [0, 0.75, 0], [0.55, 0.45, 0], [0.75, 0.15, 0.3]]),
                             room.rotation)
    signed, kinds, col, asd = sp.tally([(sample, room)], lib)
    assert kinds == {"support": 1, "room-overlap": 1, "other": 1}
    assert set(signed) == {"dining_table"} and signed["dining_table"] == pytest.approx([-0.05], abs=2e-3)
    assert col == 1.0 and asd == pytest.approx(0.05, abs=2e-3)
    # the room itself: only the chair under the table collides, its mug rests on it
    signed, kinds, col, asd = sp.tally([(room, room)], lib)
    assert kinds == {"support": 0, "room-overlap": 1, "other": 0}
    assert col == pytest.approx(0.5) and asd == pytest.approx(0.0, abs=2e-3)
    text = sp.table("unguided", signed, kinds, col, asd)
    assert "| dining_table | 1 |" in text and "room-overlap 1" in text
