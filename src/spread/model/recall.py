"""Graph recall of sampled poses, for validation (DESIGN §6 GRecall, computed on a model batch).

Spatial codes are recomputed from the sampled poses with :func:`spread.relations.spatial_codes` —
each object's world AABB being that of its M posed canonical surface samples (a close inner
approximation of the mesh's AABB) — and compared with the input graph over the ordered off-diagonal
pairs of real objects. The evaluation command computes the exact metric on meshes; this is the
cheap in-training proxy.
"""

from __future__ import annotations

import torch

from spread.model.poses import points_aabb, pose_points
from spread.relations import spatial_codes


def graph_recall(translation: torch.Tensor, rotation: torch.Tensor, points: torch.Tensor, spatial: torch.Tensor,
                 mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(correct (B,), pairs (B,)) counts of ordered off-diagonal real pairs whose recomputed code
    equals ``spatial`` (B, N, N). translation (B, N, 3) m, rotation (B, N, 3, 3), points (B, N, M, 3)."""
    lo, hi = points_aabb(pose_points(points.float(), translation.float(), rotation.float()))
    codes = spatial_codes(lo, hi).long()
    mask = mask.bool()
    N = mask.shape[1]
    pairs = mask[:, :, None] & mask[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=mask.device)
    correct = (codes == spatial.long()) & pairs
    return correct.sum((1, 2)), pairs.sum((1, 2))
