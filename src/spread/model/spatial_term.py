"""A relation-aware training term on the decoded poses: the model is told, in metres, how far its predicted clean
scene puts a pair of objects from the spatial relation its graph asks for (issue 33, unguided GRecall).

Why: GRecall counts a pair as right or wrong by the sector of the direction between the two objects' centres
(``spread.relations``); a pair near a sector's edge flips its code by a few centimetres, which the denoising MSE
in normalised units (one unit: half the room's extent, several metres) hardly charges. This term measures that
error on the network's own x̂_0, as :mod:`spread.model.penetration` does for overlaps.

Per ordered pair (i, j) of real objects with graph code c = ``spatial[i, j]`` ("i is c of j"), with the objects'
oriented boxes (centres t metres, rotations R world-from-local, full canonical extents h metres; assets are centred
at their bounding-box centre, DESIGN §3) standing in for their meshes, d = t_i − t_j:

* right of: i must lie in the sector d_x ≥ |d_z|; its violation is relu(|d_z| − d_x)/√2 (metres), the distance of
  d (x, z) to the nearer of the sector's edge lines z = ±x (extended through the apex, so a pair in the opposite
  sector pays its distance to those lines, not to the apex); in front of: relu(|d_x| − d_z)/√2; behind:
  relu(|d_x| + d_z)/√2; left of: relu(|d_z| + d_x)/√2 — the codes' sectors (θ = atan2(d_z, d_x) at ±π/4, ±3π/4).
  Known blind spot: a sector does not ask a stacked pair (one centre over the other's footprint, apart in
  height) to unstack, which ``spread.relations`` would need for the directional code;
* above: the pair must be stacked (the xz-centre of one inside the other's world-AABB footprint; the violation is
  the smaller of the two centres' xz distances outside the other's footprint) and i's AABB bottom no lower than
  j's top − 5 mm (violation relu(top_j − 5 mm − bottom_i)); the two added; below: the same with i and j swapped in
  the height test. The world AABB of a posed box: t ± |R| h / 2 (:func:`spread.box_geometry.box_size`).

Boxes are not meshes, so the boxes of the training room itself may violate a little (the world AABB of a turned
mesh is smaller than its turned box's and need not share its centre; they agree at multiples of a right angle); a
pair costs relu(violation(x̂_0) − violation(x_0)), only what the prediction adds. A scene's term is the mean over its ordered real pairs (metres per
pair), weighted by ᾱ_t of its timestep in :meth:`spread.model.module.SceneDiffusion.training_terms`, as the
penetration term is. Codes other than the six (self, padding) cost nothing.
"""

from __future__ import annotations

import math

import torch

from spread.box_geometry import box_size
from spread.relations import VERTICAL_TOLERANCE
from spread.scene import SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT


def spatial_violation(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor,
                      spatial: torch.Tensor) -> torch.Tensor:
    """(B, N, N) metres: [b, i, j] how far the boxes (translation (B, N, 3) m, rotation (B, N, 3, 3), extents
    (B, N, 3) m) are from "i is ``spatial[b, i, j]`` of j" (module docstring; 0 when it holds, and for codes outside
    the six)."""
    d = translation[:, :, None, :] - translation[:, None, :, :]  # t_i − t_j, (B, N, N, 3)
    dx, dz = d[..., 0], d[..., 2]
    root2 = math.sqrt(2.0)
    sectors = {SPATIAL_RIGHT: dz.abs() - dx, SPATIAL_FRONT: dx.abs() - dz, SPATIAL_BEHIND: dx.abs() + dz,
               SPATIAL_LEFT: dz.abs() + dx}
    half = box_size(extents, rotation) / 2  # (B, N, 3) the world AABB's half-size
    # i's xz-centre outside j's footprint, and j's outside i's: (B, N, N)
    outside_ij = (d.abs()[..., (0, 2)] - half[:, None, :, (0, 2)]).clamp_min(0).norm(dim=-1)
    outside_ji = (d.abs()[..., (0, 2)] - half[:, :, None, (0, 2)]).clamp_min(0).norm(dim=-1)
    stacked = torch.minimum(outside_ij, outside_ji)
    bottom, top = translation[..., 1] - half[..., 1], translation[..., 1] + half[..., 1]  # (B, N)
    above = (top[:, None, :] - VERTICAL_TOLERANCE - bottom[:, :, None]).clamp_min(0)  # top_j − tol − bottom_i
    below = (top[:, :, None] - VERTICAL_TOLERANCE - bottom[:, None, :]).clamp_min(0)  # top_i − tol − bottom_j
    code = spatial.long()
    violation = torch.zeros_like(dx)
    for value, cone in sectors.items():
        violation = torch.where(code == value, cone.clamp_min(0) / root2, violation)
    violation = torch.where(code == SPATIAL_ABOVE, stacked + above, violation)
    return torch.where(code == SPATIAL_BELOW, stacked + below, violation)


def spatial_excess(translation: torch.Tensor, rotation: torch.Tensor, reference_translation: torch.Tensor,
                   reference_rotation: torch.Tensor, extents: torch.Tensor, mask: torch.Tensor,
                   spatial: torch.Tensor) -> torch.Tensor:
    """(B,) per scene: the mean over ordered pairs of real objects of relu(violation − the training room's
    violation) (metres; module docstring). Poses (B, N, 3) / (B, N, 3, 3) are the prediction, the reference poses
    the training scene's (no gradient reaches them); ``spatial`` (B, N, N) the graph's codes; mask (B, N)."""
    violation = spatial_violation(translation, rotation, extents, spatial)
    with torch.no_grad():
        reference = spatial_violation(reference_translation, reference_rotation, extents, spatial)
    mask = mask.bool()
    N = mask.shape[1]
    pairs = mask[:, :, None] & mask[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=mask.device)
    cost = torch.where(pairs, (violation - reference).clamp_min(0), torch.zeros_like(violation))
    return cost.sum((1, 2)) / pairs.sum((1, 2)).clamp_min(1).to(cost.dtype)
