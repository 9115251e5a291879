"""PhyScene's collision guidance as the registered term ``box_iou`` (Yang et al., CVPR 2024).

Facts from PhyScene/PhyScene ``configs/optimizer/collision.yaml`` and ``models/optimizer/collision.py`` (written
anew here): the loss of a scene is the sum over ordered pairs of distinct objects of the **oriented 3D IoU** of
their boxes, divided by the object count (:func:`box_iou_loss`); its gradient moves the centre in x and z and the
heading only (the edit :func:`horizontal_only` zeroes the normalised-y channel), each value of the step clipped
to ±0.1, at the last 10 denoising steps on the sampled state. ``guidance=physcene`` sets exactly that (mode
``sample``, ``last_steps`` 10, ``grad_clip`` 0.1, ``terms.box_iou`` 0.15 = PhyScene's 0.075 × 2, the built-in
terms off); ``+guidance.terms.box_iou=λ`` adds the term to any method's guidance.

A box is the object's posed canonical box: centre = the translation (assets are centred at their bounding-box
centre, DESIGN §3), heading θ and rest orientation T split from the rotation (R = R_y(θ)·T,
:func:`spread.box_geometry.split_rotation`), size = ``|T| · extents`` with the asset mesh's extents (metres) —
the box DiffuScene's state holds.
"""

from __future__ import annotations

import torch

from spread.box_geometry import box_size, oriented_iou, pairwise, split_rotation
from spread.guidance.terms import GuidanceTerm, TermContext, register_term

#: Normalised-y channel of a state (translation x, y, z come first in every method's state).
Y_CHANNEL = 1


def mesh_extents(ctx: TermContext) -> torch.Tensor:
    """(B, N, 3) extents (metres) of each object's canonical mesh (0 at padding)."""
    t = ctx.meshes.tensors(ctx.translation.device, ctx.translation.dtype)
    v, m = t["vertices"], t["vmask"][..., None]
    hi = torch.where(m, v, torch.full_like(v, -torch.inf)).amax(2)
    lo = torch.where(m, v, torch.full_like(v, torch.inf)).amin(2)
    return torch.where(ctx.mask[..., None], hi - lo, torch.zeros_like(hi))


def object_boxes(ctx: TermContext) -> torch.Tensor:
    """(B, N, 7) posed boxes [centre (metres), size (metres), θ] of the context's objects (module docstring)."""
    yaw, tilt = split_rotation(ctx.rotation)
    size = box_size(mesh_extents(ctx), tilt.detach())
    return torch.cat([ctx.translation, size, yaw[..., None]], dim=-1)


def box_iou_loss(ctx: TermContext) -> torch.Tensor:
    """Per-scene (B,) Σ_{i≠j} oriented IoU(box_i, box_j) / N (PhyScene's collision term)."""
    iou = pairwise(oriented_iou, object_boxes(ctx), ctx.mask)
    return iou.sum((1, 2)) / ctx.mask.sum(1).clamp(min=1).to(iou.dtype)


def horizontal_only(grad: torch.Tensor, config) -> torch.Tensor:
    """PhyScene moves centres in x and z only: the normalised-y channel's gradient is dropped."""
    grad = grad.clone()
    grad[..., Y_CHANNEL] = 0.0
    return grad


BOX_IOU = register_term(GuidanceTerm(
    "box_iou", box_iou_loss, edit=horizontal_only,
    description="PhyScene: Σ oriented box IoU / N, x/z and heading only (guidance.terms.box_iou; guidance=physcene)"))
