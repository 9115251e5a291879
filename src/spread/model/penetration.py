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
``relu(depth(x̂_0) − max(depth(x_0), 0))`` metres — only the overlap beyond what the real room has.

That one-sided cost misleads a pair in a support relation: a laptop on a bed lies inside the bed's box (the
headboard makes it tall), so lifting the laptop off the mattress lowers the overlap and costs nothing, sinking it
costs; under uncertainty the model learns to lift supported objects (measured: ASD 144 → 241 mm at 2,000 steps).
So with ``support_weight`` μ > 0 the support pairs (i supports j, physical code 1) also pay the support term
(:func:`support_error`), in the quantities that say "j rests on i" (the gradient reaches j only: a supporter is
not moved by what it supports). They stay in the box-overlap sum, which still charges a supported object pushed
into its supporter's sides, back or headboard (taken out of it, unguided Col_mesh doubled: RESULTS, issue 33):

* the height of j's lowest box point above i's centre, ``(t_j,y − r_j,y) − t_i,y`` with ``r_j,y = Σ_k h_jk |R_j[y, k]|``
  (metres), against the same height in the training room (it names the shelf board or mattress j rests on
  without meshes): a pinball loss, 2q × a sinking, 2(1 − q) × a floating, q = ``support_quantile`` (0.5: both
  alike; Col_mesh counts every sinking > 1 cm, floating costs only ASD, which gravity guidance closes);
* how far j's centre lies outside i's footprint, in i's frame (local x and z beyond i's half extents, metres),
  beyond the training room's own overhang.

A scene's term is the sum over its pairs divided by its object count, weighted by ᾱ_t of its timestep (x̂_0 of a
nearly pure noise state is the data mean, whose boxes overlap by construction; at low noise it is the model's
actual placement); the batch's term is the mean over scenes. Measured (benchmarks/RESULTS.md, issue 33): at
2,000 steps λ 0.3 gave Col_mesh 0.277 → 0.143 with ASD 144 → 241 mm (supported objects lifted).
"""

from __future__ import annotations

import torch

#: Cross-product axes shorter than this (parallel box axes) are not separating candidates.
AXIS_EPS = 1e-6


def pair_depths(ti: torch.Tensor, ri: torch.Tensor, hi: torch.Tensor, tj: torch.Tensor, rj: torch.Tensor,
                hj: torch.Tensor) -> torch.Tensor:
    """(...,) separating-axis overlap depth (metres) of box pairs given side by side: centres t (..., 3) metres,
    rotations r (..., 3, 3) world-from-local, full extents h (..., 3) metres (module docstring)."""
    ai, aj = ri.transpose(-1, -2), rj.transpose(-1, -2)  # (..., 3 axes, 3 xyz): row k is R e_k
    cross = torch.linalg.cross(ai[..., :, None, :], aj[..., None, :, :], dim=-1).flatten(-3, -2)  # (..., 9, 3)
    length = cross.norm(dim=-1, keepdim=True)
    valid = length[..., 0] > AXIS_EPS
    candidates = torch.cat([ai, aj, cross / length.clamp_min(AXIS_EPS)], dim=-2)  # (..., 15, 3)
    # radius of a box on each axis: Σ_k h_k/2 |u · R e_k|
    r_i = ((candidates @ ai.transpose(-1, -2)).abs() * hi[..., None, :] / 2).sum(-1)
    r_j = ((candidates @ aj.transpose(-1, -2)).abs() * hj[..., None, :] / 2).sum(-1)
    distance = (candidates @ (tj - ti)[..., :, None])[..., 0].abs()
    overlap = r_i + r_j - distance
    keep = torch.cat([valid.new_ones(valid.shape[:-1] + (6,)), valid], dim=-1)
    return torch.where(keep, overlap, torch.full_like(overlap, torch.inf)).amin(-1)


def box_depths(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """(B, N, N) separating-axis overlap depth (metres) of every pair of oriented boxes: translation (B, N, 3)
    metres, rotation (B, N, 3, 3) world-from-local, extents (B, N, 3) full canonical sizes (metres). The
    diagonal (a box with itself) is its own smallest full size; callers mask it."""
    N = translation.shape[1]
    return pair_depths(translation[:, :, None].expand(-1, -1, N, -1), rotation[:, :, None].expand(-1, -1, N, -1, -1),
                       extents[:, :, None].expand(-1, -1, N, -1), translation[:, None].expand(-1, N, -1, -1),
                       rotation[:, None].expand(-1, N, -1, -1, -1), extents[:, None].expand(-1, N, -1, -1))


def upper_depths(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """(B, P) the depths of the pairs i < j only (P = N(N − 1)/2, in ``torch.triu_indices(N, N, 1)`` order):
    :func:`box_depths` without the other half of the matrix."""
    i, j = torch.triu_indices(translation.shape[1], translation.shape[1], 1, device=translation.device)
    return pair_depths(translation[:, i], rotation[:, i], extents[:, i], translation[:, j], rotation[:, j],
                       extents[:, j])


def penetration_excess(translation: torch.Tensor, rotation: torch.Tensor, reference_translation: torch.Tensor,
                       reference_rotation: torch.Tensor, extents: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) per scene: Σ over pairs i < j of real objects of relu(depth − max(reference depth, 0)) (metres), divided
    by the scene's object count. The poses (B, N, 3) / (B, N, 3, 3) are the prediction, the reference poses the
    training scene's (no gradient reaches them)."""
    N = mask.shape[1]
    i, j = torch.triu_indices(N, N, 1, device=mask.device)
    depth = upper_depths(translation, rotation, extents)  # (B, P)
    with torch.no_grad():
        reference = upper_depths(reference_translation, reference_rotation, extents)
    pairs = mask[:, i] & mask[:, j]
    cost = (depth - reference.clamp_min(0)).clamp_min(0)
    excess = torch.where(pairs, cost, torch.zeros_like(depth))
    return excess.sum(1) / mask.sum(1).clamp_min(1).to(excess.dtype)


def _rest_height(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """(B, N, N): [b, i, j] the height (metres) of j's lowest box point above i's centre; no gradient reaches i
    (a supporter is not moved by what it supports) nor j's rotation (tilting a flat object lowers its lowest
    point: the term would teach books to tip over rather than to come down)."""
    bottom = translation[..., 1] - (rotation.detach()[..., 1, :].abs() * extents / 2).sum(-1)  # (B, N)
    return bottom[:, None, :] - translation.detach()[:, :, None, 1]


def _overhang(translation: torch.Tensor, rotation: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """(B, N, N): [b, i, j] how far j's centre lies outside i's footprint (local x and z beyond its half
    extents, summed; metres); no gradient reaches i. Assets are y-up in their own frame (DESIGN §3)."""
    held = translation.detach()
    offset = translation[:, None, :, :] - held[:, :, None, :]  # c_j − c_i, (B, N, N, 3)
    local = torch.einsum("bikd,bijk->bijd", rotation.detach(), offset)  # R_iᵀ (c_j − c_i)
    beyond = (local.abs() - extents[:, :, None, :] / 2).clamp_min(0)
    return beyond[..., 0] + beyond[..., 2]


def support_error(translation: torch.Tensor, rotation: torch.Tensor, reference_translation: torch.Tensor,
                  reference_rotation: torch.Tensor, extents: torch.Tensor, mask: torch.Tensor,
                  supports: torch.Tensor, quantile: float = 0.5) -> torch.Tensor:
    """(B,) per scene: Σ over support pairs (``supports`` (B, N, N) bool, [b, i, j] = i supports j; real objects
    only) of the rest-height error, 2q × a sinking and 2(1 − q) × a floating (metres; q = ``quantile``, 0.5:
    |error|; the loss is then least when a share q of the supported objects rest at or above their height in
    the room), plus relu(overhang − the training room's overhang) (module docstring), divided by the scene's
    object count. The gradient reaches the supported object only. Poses as in :func:`penetration_excess`."""
    if not 0 < quantile < 1:
        raise ValueError(f"the support quantile must be in (0, 1), got {quantile}")
    height = _rest_height(translation, rotation, extents)
    overhang = _overhang(translation, rotation, extents)
    with torch.no_grad():
        ref_height = _rest_height(reference_translation, reference_rotation, extents)
        ref_overhang = _overhang(reference_translation, reference_rotation, extents)
    pairs = supports & mask[:, :, None] & mask[:, None, :]
    pairs = pairs & ~torch.eye(pairs.shape[1], dtype=torch.bool, device=mask.device)
    lift = height - ref_height
    cost = 2 * quantile * (-lift).clamp_min(0) + 2 * (1 - quantile) * lift.clamp_min(0)
    cost = cost + (overhang - ref_overhang).clamp_min(0)
    error = torch.where(pairs, cost, torch.zeros_like(cost))
    return error.sum((1, 2)) / mask.sum(1).clamp_min(1).to(error.dtype)
