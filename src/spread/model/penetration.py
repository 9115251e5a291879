"""A penetration-aware training term on the decoded poses: the model is told, in metres, when its predicted
clean scene pushes two objects further into each other than the training scene does (issue 33, item 2).

Why: the denoising MSE lives in normalised state units, where one unit of translation is half the room's
extent (metres: ``(max − min)/2`` per axis, several metres), so a 3 cm penetration costs almost nothing in it;
Col_mesh counts every object that penetrates another by more than 1 cm. This term measures exactly that kind of
error, on the network's own prediction of the clean scene x̂_0.

The measure is the separating-axis overlap of two oriented boxes: for boxes with centres c (metres), axes the
columns of R (world-from-local) and half extents h (metres, the asset's canonical extents / 2; assets are
centred at their bounding-box centre, DESIGN §3), the overlap along a unit axis u is
``r_i(u) + r_j(u) − |u·(c_j − c_i)|`` with ``r(u) = Σ_k h_k |u·R e_k|``, and the depth of the pair is its minimum
over the 15 candidate axes (each box's 3 axes and their 9 cross products; a cross product of parallel axes is
no candidate). depth > 0: the boxes overlap by that much along the easiest way out; depth ≤ 0: they are apart.

Boxes are coarse for non-convex objects (a chair under a table, a book inside a bookcase overlap as boxes in a
correct room), so the term compares with the training scene itself: a pair costs
``relu(depth(x̂_0) − max(depth(x_0), 0))`` metres — only the overlap beyond what the real room has. A pair in a
support relation (physical code 1 either way) may also pay α × its gap: ``relu(depth(x_0) − depth(x̂_0))`` (for a
book on a table the depth is minus its gap), α = ``support_gap_weight``. Penetration alone (α = 0) teaches the
model to lift objects off their supporters when unsure, which gravity guidance then closes; α = 1 (sinking and
floating alike) keeps them on their supporters but then half of them sink > 1 cm. Measured (benchmarks/RESULTS.md,
issue 33): at 2,000 steps, α = 0 and λ 0.3 gave Col_mesh 0.277 → 0.143 with ASD 144 → 241 mm; at 1,000 steps α = 1
gave Col_mesh 0.244 → 0.358 with ASD 215 → 154 mm. A scene's term is
the sum over its pairs divided by its object count, weighted by ᾱ_t of its timestep (x̂_0 of a nearly pure noise
state is the data mean, whose boxes overlap by construction; at low noise it is the model's actual placement);
the batch's term is the mean over scenes.
"""

from __future__ import annotations

import torch

#: Cross-product axes shorter than this (parallel box axes) are not separating candidates.
AXIS_EPS = 1e-6


def box_depths(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """(B, N, N) separating-axis overlap depth (metres) of every pair of oriented boxes: translation (B, N, 3)
    metres, rotation (B, N, 3, 3) world-from-local, extents (B, N, 3) full canonical sizes (metres). The
    diagonal (a box with itself) is its own smallest full size; callers mask it."""
    axes = rotation.transpose(-1, -2)  # (B, N, 3 axes, 3 xyz): row k is R e_k
    half = extents / 2
    B, N = translation.shape[:2]
    ai = axes[:, :, None, :, None, :].expand(B, N, N, 3, 3, 3)
    aj = axes[:, None, :, None, :, :].expand(B, N, N, 3, 3, 3)
    cross = torch.linalg.cross(ai, aj, dim=-1).reshape(B, N, N, 9, 3)
    length = cross.norm(dim=-1, keepdim=True)
    valid = length[..., 0] > AXIS_EPS
    cross = cross / length.clamp_min(AXIS_EPS)
    candidates = torch.cat([axes[:, :, None].expand(B, N, N, 3, 3), axes[:, None, :].expand(B, N, N, 3, 3), cross],
                           dim=3)  # (B, N, N, 15, 3)
    # radius of box i on each axis: Σ_k h_ik |u · R_i e_k|
    r_i = (torch.einsum("bijad,bikd->bijak", candidates, axes).abs() * half[:, :, None, None, :]).sum(-1)
    r_j = (torch.einsum("bijad,bjkd->bijak", candidates, axes).abs() * half[:, None, :, None, :]).sum(-1)
    offset = translation[:, None, :, :] - translation[:, :, None, :]  # c_j − c_i, (B, N, N, 3)
    distance = torch.einsum("bijad,bijd->bija", candidates, offset).abs()
    overlap = r_i + r_j - distance
    keep = torch.cat([valid.new_ones(B, N, N, 6), valid], dim=3)
    overlap = torch.where(keep, overlap, torch.full_like(overlap, torch.inf))
    return overlap.amin(-1)


def penetration_excess(translation: torch.Tensor, rotation: torch.Tensor, reference_translation: torch.Tensor,
                       reference_rotation: torch.Tensor, extents: torch.Tensor, mask: torch.Tensor,
                       supports: torch.Tensor | None = None, gap_weight: float = 0.0) -> torch.Tensor:
    """(B,) per scene: Σ over pairs i < j of real objects of relu(depth − max(reference depth, 0)) (metres), plus
    ``gap_weight`` × relu(reference depth − depth) where ``supports`` (B, N, N) bool, [b, i, j] = i supports j,
    relates the pair either way; divided by the scene's object count. The poses (B, N, 3) / (B, N, 3, 3) are the
    prediction, the reference poses the training scene's (no gradient reaches them)."""
    depth = box_depths(translation, rotation, extents)
    with torch.no_grad():
        reference = box_depths(reference_translation, reference_rotation, extents)
    pairs = mask[:, :, None] & mask[:, None, :]
    pairs = pairs & torch.ones(pairs.shape[1:], dtype=torch.bool, device=mask.device).triu(1)
    cost = (depth - reference.clamp_min(0)).clamp_min(0)
    if supports is not None and gap_weight > 0:
        held = supports | supports.transpose(1, 2)
        cost = cost + torch.where(held, gap_weight * (reference - depth).clamp_min(0), torch.zeros_like(cost))
    excess = torch.where(pairs, cost, torch.zeros_like(depth))
    return excess.sum((1, 2)) / mask.sum(1).clamp_min(1).to(excess.dtype)
