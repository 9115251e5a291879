"""A mesh-exact penetration term on the decoded poses, from the objects' convex parts (issue 33, item 3).

Why: the box term (:mod:`spread.model.penetration`) cannot see most of the collisions a trained model makes. Of
the pairs Col_mesh counts in the quick ablation's unguided samples, 87 % are a supported object sunk into its
supporter (a laptop into the mattress, a toy into a shelf board; benchmarks/RESULTS.md, issue 33), and such a pair
already overlaps as boxes in the training room (the laptop lies inside the bed's box): the box overlap's easiest
way out is sideways, so sinking costs the box term nothing. The objects' convex parts (:mod:`spread.data.parts`,
the shapes the ``parts`` geometry distance reads) tell the mattress from the air above it.

For a pair (i, j) of real objects, with i's canonical surface points p_m (metres) posed by (t_i, R_i) and j's parts
k given by face planes [n, d] in j's canonical frame,

    s_ijkm = max over k's planes (n·q − d),   q = R_jᵀ (R_i p_m + t_i − t_j)

is < 0 exactly when the point lies inside part k (minus its depth there), and the pair's depth is
D_ij = max(0, −min over k, m of s_ijkm) metres: i's deepest sampled point inside j (the union of j's parts; a point
inside two overlapping parts reads the deeper one). Col_mesh counts an object when one of its pairs is deeper than
1 cm, measured on the meshes; the generated assets' meshes are exactly their parts' union, so D_ij is that depth
at the sampled points. The training rooms read ≤ 5.2 mm (RESULTS, "the parts distance").

A pair costs relu(D_ij(x̂_0) − D_ij(x_0)) metres, only what the prediction adds to the training room's; a scene's
term is the sum over its ordered pairs divided by its object count, weighted by ᾱ_t of its timestep in
:meth:`spread.model.module.SceneDiffusion.training_terms`, as the box term is.

Cost: the (scene, i, j, part) candidates are the pairs whose posed part box meets i's posed points' box (one
``nonzero``: a host synchronisation); for each, the deepest point is found without autograd in chunks of at most
``max_elements`` numbers, and only those points — one per candidate that is inside — are evaluated again with
autograd (the gradient of a max of planes flows through the plane that gives it).
"""

from __future__ import annotations

import torch

from spread.model.parts_distance import CHUNK_ELEMENTS, PartPlanes, part_candidates, part_values
from spread.model.poses import pose_points


@torch.no_grad()
def _inside_candidates(parts: PartPlanes, world: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                       valid: torch.Tensor, max_elements: int) -> tuple[torch.Tensor, ...]:
    """(b, i, j, k, m): for every part k of object j that object i's posed points ``world`` (B, N, M, 3) enter,
    i's deepest point m inside it."""
    candidates = part_candidates(parts, world, translation, rotation, valid, reach=0.0)
    inside, deepest = [], []
    for _, s in part_values(parts, world, translation, rotation, candidates, max_elements):
        value, m = s.min(-1)
        inside.append(value < 0)
        deepest.append(m)
    if not inside:
        return tuple(candidates[0][:0] for _ in range(5))
    keep = torch.cat(inside)
    return (*(v[keep] for v in candidates), torch.cat(deepest)[keep])


def pair_part_depths(parts: PartPlanes, points: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                     valid: torch.Tensor, max_elements: int = CHUNK_ELEMENTS) -> torch.Tensor:
    """(B, N, N) D_ij (metres, ≥ 0): how deep object i's deepest canonical point ``points`` (B, N, M, 3), posed by
    translation (B, N, 3) and rotation (B, N, 3, 3) world-from-local, lies inside one of object j's parts; 0 on the
    diagonal, at padding and for pairs apart. Differentiable in translation and rotation (module docstring)."""
    B, N, M, _ = points.shape
    t, R, p = translation.float(), rotation.float(), points.float()
    world = pose_points(p, t, R)
    b, i, j, k, m = _inside_candidates(parts, world.detach(), t.detach(), R.detach(), valid.bool(), max_elements)
    out = torch.zeros(B * N * N, device=points.device, dtype=world.dtype)
    if len(b) == 0:
        return out.view(B, N, N) + 0 * world.sum()  # keeps the graph (a zero gradient) when nothing is inside
    q = torch.einsum("ci,cij->cj", world[b, i, m] - t[b, j], R[b, j])  # (C, 3) in j's canonical frame
    planes = parts.planes[b, j, k]  # (C, F, 4)
    s = ((planes[..., :3] * q[:, None]).sum(-1) - planes[..., 3]).amax(-1)
    depth = torch.relu(-s)
    out = out.scatter_reduce(0, (b * N + i) * N + j, depth, "amax", include_self=True)
    return out.view(B, N, N)


def parts_excess(parts: PartPlanes, points: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                 true_translation: torch.Tensor, true_rotation: torch.Tensor, mask: torch.Tensor,
                 max_elements: int = CHUNK_ELEMENTS) -> torch.Tensor:
    """(B,) per scene: Σ over ordered pairs of relu(D_ij(predicted poses) − D_ij(training poses)) / object count
    (metres; :func:`pair_part_depths`). Poses: translation (B, N, 3) metres, rotation (B, N, 3, 3); mask (B, N)."""
    valid = mask.bool()
    predicted = pair_part_depths(parts, points, translation, rotation, valid, max_elements)
    with torch.no_grad():
        truth = pair_part_depths(parts, points, true_translation, true_rotation, valid, max_elements)
    excess = torch.relu(predicted - truth).sum((1, 2))
    return excess / valid.sum(1).clamp(min=1)
