"""The out-of-bounds rate (``oob``, issue 22's metric added through the registry only): known answers on boxes
whose footprints sit inside, on the edge of, across and far outside a 4 m × 3 m floor; rotation counted; rooms
without bounds unmeasured; pooled over scenes; selected by name in the protocol."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spread.assets.assemble import box_asset, library_from_specs
from spread.metrics import OutOfBoundsRate, scene_out_of_bounds

from helpers import scene_of

ROOM = np.array([[0.0, 0.0, 0.0], [4.0, 3.0, 3.0]], np.float32)  # floor x ∈ [0, 4], z ∈ [0, 3] metres


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    return library_from_specs(tmp_path_factory.mktemp("oob_lib"), [box_asset("crate", (1.0, 0.5, 1.0))])


def crates(translations, rotations=None, room=ROOM, scene_id="s"):
    n = len(translations)
    R = np.stack([np.eye(3) if r is None else r for r in (rotations or [None] * n)])
    return scene_of(["crate"] * n, translations, R, categories=["box"] * n, room=room, scene_id=scene_id)


def test_known_answers_inside_edge_across_and_outside(lib):
    scene = crates([[2.0, 0.25, 1.5],      # centre of the floor: inside
                    [0.5, 0.25, 0.5],      # touching the x = 0 and z = 0 walls exactly: inside (0 excess)
                    [3.9, 0.25, 1.5],      # 0.4 m across x = 4: out
                    [0.505, 0.25, 2.5045], # 5 mm inside on x, 4.5 mm across z = 3: under the 1 cm tolerance
                    [9.0, 0.25, 1.5]])     # 4.5 m beyond the wall: out
    result = scene_out_of_bounds(scene, lib)
    assert result.outside == [False, False, True, False, True]
    assert result.excess[2] == pytest.approx(0.4) and result.excess[4] == pytest.approx(5.5)
    assert result.excess[3] == pytest.approx(0.0045, abs=1e-6)
    assert result.to_dict()["oob"] == pytest.approx(2 / 5)


def test_a_turned_box_sticks_out_by_its_diagonal(lib):
    # a 1 m × 1 m footprint turned 45° about y reaches √2/2 ≈ 0.707 m from its centre: at x = 3.4 it crosses x = 4
    turned = Rotation.from_euler("y", 45, degrees=True).as_matrix()
    straight = scene_out_of_bounds(crates([[3.4, 0.25, 1.5]]), lib)
    rotated = scene_out_of_bounds(crates([[3.4, 0.25, 1.5]], [turned]), lib)
    assert straight.outside == [False] and rotated.outside == [True]
    assert rotated.excess[0] == pytest.approx(3.4 + np.sqrt(0.5) - 4.0, abs=1e-6)


def test_scenes_without_room_bounds_are_not_measured_and_the_rate_is_pooled(lib):
    metric = OutOfBoundsRate()
    metric.update([crates([[2.0, 0.25, 1.5], [9.0, 0.25, 1.5]], scene_id="a"),          # 1 of 2 out
                   crates([[2.0, 0.25, 1.5]] * 3, scene_id="b"),                         # 0 of 3
                   crates([[9.0, 0.25, 1.5]], room=None, scene_id="c")], lib)           # no bounds: left out
    assert float(metric.compute()) == pytest.approx(1 / 5)
    assert metric.count_values() == {"n_oob_objects": 1}
    assert metric.pooled_terms({"outside_objects": 1, "objects": 2}) == {"oob": (1.0, 2.0)}
    assert np.isnan(float(OutOfBoundsRate().compute()))


def test_selected_by_name_in_the_protocol_with_its_registered_display():
    from spread.evaluation.protocol import EvalProtocol
    from spread.metrics.registry import METRICS

    protocol = EvalProtocol(metrics=["grecall", "oob"])
    assert list(protocol.build_metrics()) == ["grecall", "oob"]
    spec = METRICS.get("oob")
    assert (spec.higher_is_better, spec.column, spec.default) == (False, "OOB", False)
    with pytest.raises(ValueError, match="unknown metric 'ooob'"):
        EvalProtocol(metrics=["ooob"])
