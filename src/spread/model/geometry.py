"""Signed chamfer point features of a posed scene (paper §3.3, eq. for d_scd; reference §2.2).

For every object i and every one of its M canonical surface points p (placed at i's current, possibly
noisy, pose), find the nearest point q among the posed points of all OTHER real objects of the same
scene and sign the distance by q's posed normal::

    d(p) = ‖p − q‖ · (−1 if (p − q)·n_q < 0 else +1)        (metres)

so d < 0 when p lies behind the neighbour's surface (inside it: penetration). It is a point-to-point
nearest-neighbour proxy of a signed distance field, exactly as the paper and the reference define it.
One change from the reference: ``(p − q)·n_q == 0`` counts as outside (+1) rather than giving 0.

Output (B, N, M, 4) = [p in the object's canonical frame (x, y, z, metres), d]. Padding objects
(``mask`` False) have all-zero features and are never anyone's neighbour. A real object with no other
real object in its scene gets ``d = no_neighbour_distance``.

The search (:mod:`spread.model.nearest`) is exact, batched over scenes on the inputs' device, in
float32 whatever autocast says, with memory bounded by chunking. It runs without autograd; the final
gather is differentiable, so gradients reach translation and rotation through the chosen pairs (as
for any nearest-neighbour loss).
"""

from __future__ import annotations

import torch
from einops import rearrange, repeat

from spread.model.nearest import CHUNK_ELEMENTS, nearest_other_point
from spread.model.poses import pose_points

#: Signed distance (metres) given to points of an object that has no other real object in its scene.
NO_NEIGHBOUR_DISTANCE = 10.0


def signed_chamfer_features(points_local: torch.Tensor, normals_local: torch.Tensor, translation: torch.Tensor,
                            rotation: torch.Tensor, mask: torch.Tensor, chunk: int | None = None,
                            max_elements: int = CHUNK_ELEMENTS, prune: bool = True,
                            no_neighbour_distance: float = NO_NEIGHBOUR_DISTANCE) -> torch.Tensor:
    """(B, N, M, 4) = [canonical xyz, signed NN distance to other objects] (see module docstring).

    points_local, normals_local: (B, N, M, 3) canonical frame (metres; unit normals).
    translation (B, N, 3) metres, rotation (B, N, 3, 3) world-from-local; mask (B, N) bool.
    chunk / max_elements / prune: see :func:`spread.model.nearest.nearest_other_point` (they change
    speed and memory, never the result).
    """
    B, N, M, _ = points_local.shape
    valid = mask.bool()
    with torch.autocast(device_type=points_local.device.type, enabled=False):
        # padding objects: everything zeroed first, so junk (even NaN) there cannot leak anywhere
        keep = valid[..., None, None]
        p_local = torch.where(keep, points_local.float(), 0.0)
        n_local = torch.where(keep, normals_local.float(), 0.0)
        R = torch.where(keep, rotation.float(), 0.0)
        t = torch.where(valid[..., None], translation.float(), 0.0)
        # scene-centred world frame: distances are unchanged and the float32 matmul keeps more digits
        count = valid.sum(1, keepdim=True).clamp(min=1)
        t = torch.where(valid[..., None], t - (t.sum(1) / count)[:, None, :], 0.0)
        world = pose_points(p_local, t, R)  # (B, N, M, 3)
        with torch.no_grad():
            nearest = nearest_other_point(world.detach(), p_local, t.detach(), R.detach(), valid,
                                          chunk=chunk, max_elements=max_elements, prune=prune)
        world_flat = rearrange(world, "b n m c -> b (n m) c")
        normals_flat = rearrange(torch.einsum("bnij,bnmj->bnmi", R, n_local), "b n m c -> b (n m) c")
        index = repeat(nearest, "b k -> b k c", c=3)
        diff = world_flat - world_flat.gather(1, index)
        dist = torch.linalg.vector_norm(diff, dim=-1)
        outside = (diff * normals_flat.gather(1, index)).sum(-1) >= 0
        signed = rearrange(torch.where(outside, dist, -dist), "b (n m) -> b n m", n=N)
        has_other = (valid.sum(1, keepdim=True) - valid.long()) > 0  # (B, N)
        signed = torch.where(has_other[..., None], signed, torch.full_like(signed, no_neighbour_distance))
        features = torch.cat([p_local, signed[..., None]], dim=-1)
        return features * valid[..., None, None]
