"""InstructScene's spatial predicates (chenguolin/InstructScene ``compute_loc_rel``; reference notes §4.3), batched.

Ten predicates, in InstructScene's index order, plus two codes of ours:

===== ==================== ===== ====================
0     above                6     right of
1     left of              7     behind
2     in front of          8     closely right of
3     closely left of      9     closely behind
4     closely in front of  10    none (:data:`NONE`: farther than 3 m, and the diagonal)
5     below                11    :data:`PAD` (padding objects, and the dropped graph of classifier-free guidance)
===== ==================== ===== ====================

For the ordered pair (subject i, object j) of oriented boxes (centre c, full size s, heading θ about y;
:mod:`spread.methods.boxes`):

1. d = c_i − c_j, φ = atan2(d_z, d_x); horizontal predicate by the sectors of DESIGN §3 (the same as
   :func:`spread.relations.spatial_codes`): right of −π/4 ≤ φ < π/4, in front of π/4 ≤ φ < 3π/4, behind
   −3π/4 ≤ φ < −π/4, left of otherwise.
2. Vertical override when i's xz centre lies strictly inside j's footprint (the rotated bottom rectangle)
   or j's inside i's: δ₁ = c_i,y − c_j,y, δ₂ = (H_i + H_j)/2 (H the box heights); δ₁ − δ₂ ≥ 0 or i is a
   lamp → above; else −δ₁ − δ₂ ≥ 0 or j is a lamp → below; vertically overlapping boxes fall through.
3. Otherwise: ground distance |d_xz| > 3 m → none; < 1 m → the "closely" form.

As in InstructScene, the predicate is computed for i < j and the pair (j, i) gets its reverse (above ↔
below, left ↔ right, front ↔ behind, "closely" kept), so the graph is consistent even where the lamp rule
is not symmetric. Our DESIGN §3 codes differ (world AABB footprints, a 5 mm tolerance, no distance
classes), so this is a second function rather than a call of ``spatial_codes``; the sector rule is shared.
"""

from __future__ import annotations

import math

import torch

from spread.box_geometry import footprint

PREDICATES = ("above", "left of", "in front of", "closely left of", "closely in front of", "below", "right of",
              "behind", "closely right of", "closely behind")
ABOVE, LEFT, FRONT, CLOSE_LEFT, CLOSE_FRONT, BELOW, RIGHT, BEHIND, CLOSE_RIGHT, CLOSE_BEHIND = range(10)
NONE = 10
PAD = 11
VOCAB = 12
#: Beyond this ground distance (metres) a pair has no relation; below CLOSE it is "closely".
FAR = 3.0
CLOSE = 1.0
#: predicate → its reverse (the relation of the pair read the other way round)
REVERSE = (BELOW, RIGHT, BEHIND, CLOSE_RIGHT, CLOSE_BEHIND, ABOVE, LEFT, FRONT, CLOSE_LEFT, CLOSE_FRONT, NONE, PAD)


def _strictly_inside(points: torch.Tensor, quads: torch.Tensor) -> torch.Tensor:
    """(B, N, N) bool: point i (B, N, 2) strictly inside quad j (B, N, 4, 2) (counter-clockwise)."""
    a = quads[:, None, :, :, :]  # (B, 1, N, 4, 2)
    edge = torch.roll(quads, -1, dims=-2)[:, None] - a
    rel = points[:, :, None, None, :] - a  # (B, N, N, 4, 2)
    cross = edge[..., 0] * rel[..., 1] - edge[..., 1] * rel[..., 0]
    return (cross > 0).all(-1)


def instruct_predicates(centre: torch.Tensor, size: torch.Tensor, yaw: torch.Tensor, is_lamp: torch.Tensor,
                        mask: torch.Tensor) -> torch.Tensor:
    """(B, N, N) long predicate codes (module docstring) of boxes: centre (B, N, 3) and size (B, N, 3) in
    metres, yaw (B, N), is_lamp (B, N) bool, mask (B, N) bool. Diagonal NONE, pairs with padding PAD."""
    centre, size, yaw = centre.double(), size.double(), yaw.double()
    mask, is_lamp = mask.bool(), is_lamp.bool() & mask.bool()
    B, N, _ = centre.shape
    d = centre[:, :, None, :] - centre[:, None, :, :]  # c_i − c_j
    phi = torch.atan2(d[..., 2], d[..., 0])
    q = math.pi / 4
    horizontal = torch.full(phi.shape, LEFT, dtype=torch.long, device=centre.device)
    horizontal[(phi >= -q) & (phi < q)] = RIGHT
    horizontal[(phi >= q) & (phi < 3 * q)] = FRONT
    horizontal[(phi >= -3 * q) & (phi < -q)] = BEHIND
    distance = torch.linalg.vector_norm(d[..., [0, 2]], dim=-1)
    close = {LEFT: CLOSE_LEFT, RIGHT: CLOSE_RIGHT, FRONT: CLOSE_FRONT, BEHIND: CLOSE_BEHIND}
    codes = horizontal.clone()
    for far_code, close_code in close.items():
        codes[(horizontal == far_code) & (distance < CLOSE)] = close_code
    codes[distance > FAR] = NONE
    boxes = torch.cat([centre, size, yaw[..., None]], dim=-1)
    quads = footprint(boxes)  # (B, N, 4, 2)
    inside = _strictly_inside(centre[..., [0, 2]], quads)
    stacked = inside | inside.transpose(1, 2)
    delta1 = d[..., 1]
    delta2 = (size[:, :, None, 1] + size[:, None, :, 1]) / 2
    above = stacked & ((delta1 - delta2 >= 0) | is_lamp[:, :, None])
    below = stacked & ~above & ((-delta1 - delta2 >= 0) | is_lamp[:, None, :])
    codes[above] = ABOVE
    codes[below] = BELOW
    # i < j as computed, (j, i) its reverse
    upper = torch.triu(torch.ones(N, N, dtype=torch.bool, device=centre.device), diagonal=1)
    reverse = torch.as_tensor(REVERSE, device=centre.device)[codes].transpose(1, 2)
    codes = torch.where(upper, codes, reverse)
    eye = torch.eye(N, dtype=torch.bool, device=centre.device)
    codes = torch.where(eye, torch.full_like(codes, NONE), codes)
    pair = mask[:, :, None] & mask[:, None, :]
    return torch.where(pair, codes, torch.full_like(codes, PAD))


def drop_edges(edges: torch.Tensor, drop: torch.Tensor) -> torch.Tensor:
    """The graphs of the scenes in ``drop`` (B,) bool replaced by :data:`PAD` everywhere (the null graph of
    classifier-free guidance, InstructScene's 20% edge dropout); the others unchanged."""
    return torch.where(drop[:, None, None].to(edges.device), torch.full_like(edges, PAD), edges)
