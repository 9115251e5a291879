"""Augmentation keeps the graphs true: after each of the 8 floor symmetries, the remapped spatial codes are
the codes recomputed from the transformed poses (of the mirrored assets when mirrored), and the encoded item
is that transformed room."""

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from spread.data import SceneDataset, compute_stats, rot6d_to_matrix, save_stats
from spread.data.augment import (
    NUM_TRANSFORMS, bounds_centre, mirror_local, remap_spatial, square_bounds, transform_poses, transform_scene,
)
from spread.relations import posed_aabbs, spatial_codes
from spread.scene import SPATIAL_BEHIND, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, Scene, write_scene


def asymmetric_hulls(rng, count):
    """Point sets with no mirror symmetry (an L-shaped corner of random boxes), bbox-centred like assets."""
    hulls = []
    for _ in range(count):
        a, b = rng.uniform(0.05, 0.8, 3), rng.uniform(0.05, 0.5, 3)
        box = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
        v = np.concatenate([box * a, box * b + [a[0], 0, 0]])
        hulls.append(v - (v.min(0) + v.max(0)) / 2)
    return hulls


def random_room(rng, n=14):
    """Objects on the floor and stacked, random yaw, some tilted; centred off the origin."""
    hulls = asymmetric_hulls(rng, n)
    t = np.column_stack([rng.uniform(-2.3, 2.9, n), rng.uniform(0.1, 1.5, n), rng.uniform(-1.7, 2.2, n)])
    t[n // 2:, [0, 2]] = t[: n - n // 2, [0, 2]] + rng.normal(0, 0.05, (n - n // 2, 2))  # stacks: shared footprints
    yaw = Rotation.from_rotvec(np.column_stack([np.zeros(n), rng.uniform(0, 2 * np.pi, n), np.zeros(n)]))
    tilt = Rotation.from_rotvec(rng.normal(0, 0.3, (n, 3)) * (rng.random((n, 1)) < 0.3))
    return t, (yaw * tilt).as_matrix(), hulls


def codes_of(t, R, hulls):
    return spatial_codes(*posed_aabbs(t, R, hulls))


@pytest.mark.parametrize("k", range(NUM_TRANSFORMS))
def test_remapped_codes_equal_codes_recomputed_from_transformed_poses(k):
    rng = np.random.default_rng(k)
    centre = (0.3, -0.2)
    checked = 0
    for _ in range(20):
        t, R, hulls = random_room(rng)
        truth = codes_of(t, R, hulls)
        t2, R2 = transform_poses(t, R, k, centre)
        assert np.allclose(np.linalg.det(R2), 1.0) and np.allclose(np.einsum("nji,njk->nik", R2, R2), np.eye(3))
        recomputed = codes_of(t2, R2, [mirror_local(h, k) for h in hulls])
        assert np.array_equal(remap_spatial(truth, k), recomputed)
        checked += truth.size
    assert checked > 3000


def test_quarter_turn_and_mirror_codes_by_hand():
    # i is right of j (dx > 0): a quarter turn about y, (x, z) -> (z, -x), puts i behind j; the mirror, left of j
    t = np.array([[1.0, 0.5, 0.0], [0.0, 0.5, 0.0]])
    R = np.stack([np.eye(3)] * 2)
    box = [np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1)])] * 2
    assert codes_of(t, R, box)[0, 1] == SPATIAL_RIGHT
    for k, expected in ((1, SPATIAL_BEHIND), (2, SPATIAL_LEFT), (3, SPATIAL_FRONT), (4, SPATIAL_LEFT),
                        (5, SPATIAL_FRONT)):
        assert remap_spatial(codes_of(t, R, box), k)[0, 1] == expected
        assert codes_of(*transform_poses(t, R, k), box)[0, 1] == expected
    with pytest.raises(ValueError, match="0..7"):
        transform_poses(t, R, 8)


def test_transforms_keep_world_geometry_and_room_inside_square_bounds():
    rng = np.random.default_rng(3)
    t, R, hulls = random_room(rng)
    bounds = [float(v) for v in np.concatenate([t.min(0), t.max(0)])]
    square = square_bounds(bounds)
    centre = bounds_centre(bounds)
    for k in range(NUM_TRANSFORMS):
        t2, R2 = transform_poses(t, R, k, centre)
        assert (t2 >= np.array(square[:3]) - 1e-9).all() and (t2 <= np.array(square[3:]) + 1e-9).all()
        # pairwise distances between posed (mirrored-asset) vertices are those of the original room
        w1 = np.concatenate([h @ r.T + x for h, r, x in zip(hulls, R, t)])
        w2 = np.concatenate([mirror_local(h, k) @ r.T + x for h, r, x in zip(hulls, R2, t2)])
        d1 = np.linalg.norm(w1[:, None] - w1[None], axis=-1)
        d2 = np.linalg.norm(w2[:, None] - w2[None], axis=-1)
        assert np.allclose(d1, d2, atol=1e-9)
        assert np.allclose(w2[:, 1], w1[:, 1])  # heights unchanged: support stays support


def test_augmented_item_encodes_the_transformed_room(tmp_path):
    from spread.assets.assemble import box_asset, library_from_specs

    lib = library_from_specs(tmp_path / "assets", [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("mug", (0.08, 0.1, 0.08), category="mug")])
    ids = ["table", "mug", "mug"]
    t = np.array([[0.5, 0.375, -0.4], [0.7, 0.8, -0.3], [2.0, 0.05, 1.0]])
    R = Rotation.from_rotvec([[0, 0.3, 0], [0, 1.0, 0], [0, -2.0, 0]]).as_matrix()
    spatial = spatial_codes(*posed_aabbs(t, R, [lib.mesh(a).vertices for a in ids]))
    physical = np.zeros((3, 3), np.int8)
    physical[0, 1] = 1
    scene = Scene("s0", ids, ["dining_table", "mug", "mug"], t, R, spatial, physical,
                  room=np.array([[-1, 0, -2], [3, 3, 2]]))
    write_scene(scene, tmp_path / "train" / "s0.npz")
    stats = compute_stats([scene])
    save_stats(tmp_path / "stats.json", stats)
    (tmp_path / "manifest.json").write_text(json.dumps({"categories": ["dining_table", "mug"]}))
    bounds = square_bounds(stats["bounds_translations"])
    data = SceneDataset(tmp_path, "train", num_points=32, bounds=bounds)
    plain = data.item(0, 0)
    for k in range(NUM_TRANSFORMS):
        item = data.item(0, k)
        moved = transform_scene(scene, k, bounds_centre(bounds))
        lo, hi = np.array(bounds[:3]), np.array(bounds[3:])
        decoded = (item["x"][:, :3].double().numpy() + 1) / 2 * (hi - lo) + lo
        assert np.allclose(decoded, moved.translation, atol=1e-5)
        assert np.allclose(rot6d_to_matrix(item["x"][:, 3:]).numpy(), moved.rotation, atol=1e-5)
        assert torch.equal(item["spatial"], torch.from_numpy(remap_spatial(spatial, k).astype(np.int64)))
        assert torch.equal(item["physical"], plain["physical"])
        sign = torch.tensor([-1.0 if k >= 4 else 1.0, 1.0, 1.0])
        assert torch.equal(item["points"], plain["points"] * sign)
        assert torch.equal(item["normals"], plain["normals"] * sign)
        moved.validate(assets=lib)
