"""Spatial codes (DESIGN §3) and support/contact detection on posed meshes: known answers."""

import numpy as np
import pytest
import torch

from spread.assets.assemble import box_asset, library_from_specs
from spread.relations import (
    VERTICAL_TOLERANCE, physical_codes, scene_spatial_codes, spatial_codes,
)
from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF,
)


def boxes(centres, size=(0.2, 0.2, 0.2)):
    c = np.asarray(centres, float)
    h = np.asarray(size, float) / 2
    return c - h, c + h


@pytest.mark.parametrize(
    "offset, expected",
    [
        ((1, 0, 0), SPATIAL_RIGHT), ((-1, 0, 0), SPATIAL_LEFT),
        ((0, 0, 1), SPATIAL_FRONT), ((0, 0, -1), SPATIAL_BEHIND),
        ((0, 0.2, 0), SPATIAL_ABOVE), ((0, -0.2, 0), SPATIAL_BELOW),
        ((1, 0, 0.9), SPATIAL_RIGHT), ((0.9, 0, 1), SPATIAL_FRONT),
    ],
)
def test_canonical_pairs(offset, expected):
    lo, hi = boxes([offset, (0, 0, 0)])
    codes = spatial_codes(lo, hi)
    assert codes[0, 1] == expected
    assert codes[0, 0] == SPATIAL_SELF and codes[1, 1] == SPATIAL_SELF


def test_reverse_codes_are_consistent():
    rng = np.random.default_rng(0)
    c = rng.uniform(-3, 3, size=(30, 3))
    lo, hi = boxes(c)
    codes = spatial_codes(lo, hi)
    reverse = {SPATIAL_RIGHT: SPATIAL_LEFT, SPATIAL_LEFT: SPATIAL_RIGHT, SPATIAL_FRONT: SPATIAL_BEHIND,
               SPATIAL_BEHIND: SPATIAL_FRONT, SPATIAL_ABOVE: SPATIAL_BELOW, SPATIAL_BELOW: SPATIAL_ABOVE}
    off = ~np.eye(30, dtype=bool)
    # atan2 sector boundaries can break symmetry only exactly on a boundary; random centres avoid it
    assert all(codes[j, i] == reverse[codes[i, j]] for i, j in zip(*np.nonzero(off)))


def test_vertical_tolerance_is_five_millimetres():
    lo, hi = boxes([(0, 0.2 - 0.004, 0), (0, 0, 0)])  # overlaps by 4 mm: still above
    assert spatial_codes(lo, hi)[0, 1] == SPATIAL_ABOVE
    lo, hi = boxes([(0, 0.2 - 0.006, 0.01), (0, 0, 0)])  # overlaps by 6 mm: horizontal
    assert spatial_codes(lo, hi)[0, 1] == SPATIAL_FRONT
    assert VERTICAL_TOLERANCE == 0.005


def test_footprint_rule_uses_either_centre():
    # a small cup above a wide table whose centre is far away: the cup's centre is in the table footprint
    lo = np.array([[1.4, 0.75, 0.0], [-1.5, 0.0, -0.5]])
    hi = np.array([[1.5, 0.85, 0.1], [1.5, 0.75, 0.5]])
    codes = spatial_codes(lo, hi)
    assert codes[0, 1] == SPATIAL_ABOVE and codes[1, 0] == SPATIAL_BELOW


def test_torch_matches_numpy_batched():
    rng = np.random.default_rng(1)
    lo = rng.uniform(-2, 2, size=(4, 12, 3))
    hi = lo + rng.uniform(0.05, 1.0, size=(4, 12, 3))
    np_codes = spatial_codes(lo, hi)
    t_codes = spatial_codes(torch.from_numpy(lo), torch.from_numpy(hi))
    assert t_codes.dtype == torch.int8
    np.testing.assert_array_equal(t_codes.numpy(), np_codes)


@pytest.fixture(scope="module")
def box_library(tmp_path_factory):
    root = tmp_path_factory.mktemp("boxes")
    return library_from_specs(root, [
        box_asset("table", (1.0, 0.1, 0.6), category="table", role="furniture"),
        box_asset("book", (0.2, 0.04, 0.3), category="book"),
        box_asset("cube", (0.1, 0.1, 0.1), category="box"),
    ])


def _codes(lib, ids, centres):
    R = np.tile(np.eye(3), (len(ids), 1, 1))
    return physical_codes(np.asarray(centres, float), R, ids, lib)


def test_book_on_table_is_supported(box_library):
    codes, floor, _, _ = _codes(box_library, ["table", "book"], [(0, 0.05, 0), (0.1, 0.1 + 0.02, 0)])
    assert codes[0, 1] == 1 and codes[1, 0] == 0
    assert floor.tolist() == [True, False]
    assert scene_spatial_codes(np.array([(0, 0.05, 0), (0.1, 0.12, 0)]), np.tile(np.eye(3), (2, 1, 1)),
                               ["table", "book"], box_library)[1, 0] == SPATIAL_ABOVE


def test_floating_book_is_not_supported(box_library):
    codes, floor, _, _ = _codes(box_library, ["table", "book"], [(0, 0.05, 0), (0.1, 0.12 + 0.02, 0)])
    assert codes.sum() == 0 and floor.tolist() == [True, False]


def test_side_by_side_boxes_are_contact_not_support(box_library):
    codes, floor, _, _ = _codes(box_library, ["cube", "cube"], [(0, 0.05, 0), (0.1005, 0.05, 0)])
    assert codes[0, 1] == 2 and codes[1, 0] == 2
    assert floor.all()


def test_stack_gives_a_chain_and_one_supporter_each(box_library):
    ids = ["table", "book", "book", "cube"]
    centres = [(0, 0.05, 0), (0, 0.12, 0), (0, 0.16, 0), (0.02, 0.23, 0)]
    codes, floor, _, _ = _codes(box_library, ids, centres)
    assert (codes == 1).sum(axis=0).tolist() == [0, 1, 1, 1]
    assert codes[0, 1] == 1 and codes[1, 2] == 1 and codes[2, 3] == 1


def test_penetration_depth_is_reported(box_library):
    rel = _codes(box_library, ["cube", "cube"], [(0, 0.05, 0), (0.08, 0.05, 0)])  # overlap 2 cm in x
    assert rel.min_distance[0, 1] == pytest.approx(-0.02, abs=1e-6)
    assert rel.min_distance[1, 0] == pytest.approx(-0.02, abs=1e-6)
