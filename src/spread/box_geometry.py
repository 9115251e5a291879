"""Box geometry: headings split from rotations, box sizes, and box overlaps — axis-aligned 3D IoU (DiffuScene's
training term) and oriented 3D IoU (PhyScene's guidance term, :mod:`spread.guidance.box_iou`).

A full rotation R (world-from-local, y-up) splits as R = R_y(θ)·T (:func:`split_rotation`; θ the y-rotation nearest
to R, T the rest orientation; :mod:`spread.methods.boxes` explains the convention); the box of an object is the
axis-aligned box of its canonical extents after T (:func:`box_size`), turned by θ.

Boxes are (..., 7) tensors ``[centre x, y, z, size x, y, z, θ]`` in metres (full sizes, not half), y up,
θ the heading about y (:mod:`spread.methods.boxes`: the box is ``R_y(θ)`` applied to the axis-aligned box
of that size). Both IoUs are differentiable in centres, sizes and θ.

Oriented IoU: the boxes' footprints are rotated rectangles in the xz plane; their intersection is a convex
polygon whose vertices are among the 4 + 4 corners lying inside the other rectangle and the 16 edge–edge
crossings. The valid candidates are ordered by angle about their mean (the order is a constant of the
forward pass, so gradients flow through the vertex coordinates only), and the shoelace formula gives the
area; the vertical overlap multiplies it. Everything is batched over pairs; no Python loop over objects.
"""

from __future__ import annotations

import torch

#: Denominators below this (edge crossings of parallel edges) are replaced, so no NaN reaches a gradient.
EPS = 1e-9
#: Slack (metres) of the inside / on-segment tests, so touching boxes count their shared boundary points.
SLACK = 1e-7


def axis_aligned_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of axis-aligned boxes ``[centre (3), size (3), ...]`` (θ ignored), broadcast over leading dims."""
    lo = torch.maximum(a[..., :3] - a[..., 3:6] / 2, b[..., :3] - b[..., 3:6] / 2)
    hi = torch.minimum(a[..., :3] + a[..., 3:6] / 2, b[..., :3] + b[..., 3:6] / 2)
    inter = (hi - lo).clamp(min=0).prod(-1)
    union = a[..., 3:6].prod(-1) + b[..., 3:6].prod(-1) - inter
    return inter / union.clamp(min=EPS)


def footprint(box: torch.Tensor) -> torch.Tensor:
    """(..., 4, 2) xz corners of the boxes' footprints, counter-clockwise in (x, z)."""
    sx, sz = box[..., 3] / 2, box[..., 5] / 2
    c, s = torch.cos(box[..., 6]), torch.sin(box[..., 6])
    local_x = torch.stack([-sx, sx, sx, -sx], -1)
    local_z = torch.stack([-sz, -sz, sz, sz], -1)
    # R_y(θ) applied to (x, 0, z): x' = c·x + s·z, z' = −s·x + c·z (a proper rotation of the xz plane)
    x = box[..., 0, None] + c[..., None] * local_x + s[..., None] * local_z
    z = box[..., 2, None] - s[..., None] * local_x + c[..., None] * local_z
    return torch.stack([x, z], -1)


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _inside(points: torch.Tensor, polygon: torch.Tensor) -> torch.Tensor:
    """(..., P) bool: points (..., P, 2) inside or on the convex CCW quad (..., 4, 2)."""
    a = polygon[..., None, :, :]  # (..., 1, 4, 2)
    edge = torch.roll(polygon, -1, dims=-2)[..., None, :, :] - a
    return (_cross(edge, points[..., :, None, :] - a) >= -SLACK).all(-1)


def rectangle_intersection_area(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Area (...,) of the intersection of convex CCW quads p, q (..., 4, 2)."""
    # edge crossings: p_i + u (p_{i+1} − p_i) = q_j + v (q_{j+1} − q_j)
    a, r = p[..., :, None, :], (torch.roll(p, -1, -2) - p)[..., :, None, :]  # (..., 4, 1, 2)
    c, d = q[..., None, :, :], (torch.roll(q, -1, -2) - q)[..., None, :, :]  # (..., 1, 4, 2)
    denom = _cross(r, d)
    safe = torch.where(denom.abs() < EPS, torch.full_like(denom, EPS), denom)
    u = _cross(c - a, d) / safe
    v = _cross(c - a, r) / safe
    crossing = (a + u[..., None] * r).flatten(-3, -2)  # (..., 16, 2)
    crossing_ok = ((denom.abs() >= EPS) & (u >= -SLACK) & (u <= 1 + SLACK) & (v >= -SLACK) & (v <= 1 + SLACK))
    points = torch.cat([p, q, crossing], dim=-2)  # (..., 24, 2)
    valid = torch.cat([_inside(p, q), _inside(q, p), crossing_ok.flatten(-2)], dim=-1)
    weight = valid.to(points.dtype)
    count = weight.sum(-1, keepdim=True)
    centre = (points * weight[..., None]).sum(-2) / count.clamp(min=1)
    with torch.no_grad():  # the order is constant: gradients flow through the vertices, not the sort
        rel = points - centre[..., None, :]
        angle = torch.atan2(rel[..., 1], rel[..., 0])
        angle = torch.where(valid, angle, torch.full_like(angle, 10.0))  # invalid last
        order = angle.argsort(dim=-1)
    ordered = torch.gather(points, -2, order[..., None].expand_as(points))
    ordered_valid = torch.gather(valid, -1, order)
    first = ordered[..., :1, :].expand_as(ordered)
    ordered = torch.where(ordered_valid[..., None], ordered, first)  # invalid points collapse onto the first
    nxt = torch.roll(ordered, -1, dims=-2)
    area = 0.5 * _cross(ordered, nxt).sum(-1).abs()
    return torch.where(count[..., 0] >= 3, area, torch.zeros_like(area))


def oriented_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """3D IoU (...,) of boxes a, b (..., 7) rotated about y (module docstring), broadcast over leading dims."""
    a, b = torch.broadcast_tensors(a, b)
    area = rectangle_intersection_area(footprint(a), footprint(b))
    bottom = torch.maximum(a[..., 1] - a[..., 4] / 2, b[..., 1] - b[..., 4] / 2)
    top = torch.minimum(a[..., 1] + a[..., 4] / 2, b[..., 1] + b[..., 4] / 2)
    inter = area * (top - bottom).clamp(min=0)
    union = a[..., 3:6].prod(-1) + b[..., 3:6].prod(-1) - inter
    return inter / union.clamp(min=EPS)


def pairwise(iou_fn, boxes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, N, N) IoU of every ordered pair of real, distinct objects (0 elsewhere); boxes (B, N, 7)."""
    N = boxes.shape[-2]
    iou = iou_fn(boxes[..., :, None, :], boxes[..., None, :, :])
    mask = mask.bool()
    pair = mask[..., :, None] & mask[..., None, :] & ~torch.eye(N, dtype=torch.bool, device=boxes.device)
    return torch.where(pair, iou, torch.zeros_like(iou))


def rot_y(theta: torch.Tensor) -> torch.Tensor:
    """(...,) angles → (..., 3, 3) rotations about +y: [[c, 0, s], [0, 1, 0], [−s, 0, c]]."""
    c, s = torch.cos(theta), torch.sin(theta)
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    return torch.stack([torch.stack([c, zero, s], -1), torch.stack([zero, one, zero], -1),
                        torch.stack([-s, zero, c], -1)], -2)


def yaw_of(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations → (...,) θ of the nearest rotation about y (module docstring)."""
    return torch.atan2(rotation[..., 0, 2] - rotation[..., 2, 0], rotation[..., 0, 0] + rotation[..., 2, 2])


def split_rotation(rotation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3, 3) → θ (...,) and T = R_y(−θ)·R (..., 3, 3)."""
    theta = yaw_of(rotation)
    return theta, rot_y(-theta) @ rotation


def box_size(extents: torch.Tensor, tilt: torch.Tensor) -> torch.Tensor:
    """Axis-aligned size (..., 3) of a canonical box of ``extents`` (..., 3) rotated by ``tilt`` (..., 3, 3)."""
    return (tilt.abs() @ extents[..., None])[..., 0]
