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

What does not depend on the poses — the masked canonical points and normals, which objects have a neighbour,
optionally a Morton order of each object's points — is a :class:`PointCloud`, made once per sample
(:func:`prepare_points`; the network keeps it in its :class:`~spread.model.network.Condition` for all the
denoising steps); :func:`signed_distances` is the per-step work: pose, search, sign.

The search is exact, in float32 whatever autocast says: ``search`` ``tree`` (a k-d tree per object on the host,
:func:`spread.model.nearest.nearest_other_point_tree`: best on CPU), ``pruned`` (:mod:`spread.model.nearest`: object
pruning batched over scenes on the inputs' device) or ``dense`` (:mod:`spread.model.nearest_dense`: one operator, a
Triton kernel on CUDA). It runs without autograd; the final gather is differentiable, so
gradients reach translation and rotation through the chosen pairs (as for any nearest-neighbour loss).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from spread.model.nearest import CHUNK_ELEMENTS, morton_order, nearest_other_point, nearest_other_point_tree
from spread.model.parts_distance import PARTS_RANGE, PartPlanes, parts_distances
from spread.data.rotation import rot6d_to_matrix
from spread.model.poses import pose_points

#: Signed distance (metres) given to points of an object that has no other real object in its scene.
NO_NEIGHBOUR_DISTANCE = 10.0
#: ``ModelConfig.nearest``: how the nearest other-object point is searched.
SEARCHES = ("auto", "tree", "pruned", "dense")
#: The searches that cannot run inside ``torch.compile`` (host work or data-dependent sizes).
UNCOMPILABLE = ("tree", "pruned")


def resolve_search(search: str, device: torch.device) -> str:
    """``auto`` → the fastest exact search for ``device``: ``dense`` on CUDA (one kernel), ``tree`` on CPU (7–10× the
    pruned search there) — but ``dense`` inside ``torch.compile`` anywhere (the tree search runs on the host, the pruned
    search's blocks have data-dependent sizes: neither makes one graph)."""
    if search not in SEARCHES:
        raise ValueError(f"model.config.nearest: unknown search '{search}' (choose from {SEARCHES})")
    if search == "auto":
        cuda = torch.device(device).type == "cuda"
        return "dense" if cuda or torch.compiler.is_compiling() else "tree"
    return search


@dataclass
class PointCloud:
    """The pose-independent part of a batch's geometry (module docstring). points, normals: (B, N, M, 3) float32
    canonical frame, zero at padding objects; valid (B, N) bool; has_other (B, N, 1) bool (another real object in
    the scene); fill (B, N, 1) float32, the distance of an object without a neighbour (``no_neighbour_distance``
    for a lone real object, 0 for padding); count (B, 1) real objects."""

    points: torch.Tensor
    normals: torch.Tensor
    valid: torch.Tensor
    has_other: torch.Tensor
    fill: torch.Tensor
    count: torch.Tensor
    no_neighbour: float = NO_NEIGHBOUR_DISTANCE
    parts: PartPlanes | None = None  # geometry_distance=parts: the objects' convex part planes (then d is theirs)


def prepare_points(points_local: torch.Tensor, normals_local: torch.Tensor, mask: torch.Tensor,
                   morton: bool = False, no_neighbour_distance: float = NO_NEIGHBOUR_DISTANCE) -> PointCloud:
    """The :class:`PointCloud` of canonical points and normals (B, N, M, 3) of objects ``mask`` (B, N). ``morton``
    puts each object's points in Morton order of their canonical coordinates (the same points, reordered: the
    dense search then skips most of its tiles; the features are the same set)."""
    valid = mask.bool()
    keep = valid[..., None, None]
    # padding objects: everything zeroed first, so junk (even NaN) there cannot leak anywhere
    p_local = torch.where(keep, points_local.float(), 0.0)
    n_local = torch.where(keep, normals_local.float(), 0.0)
    if morton:
        order = morton_order(p_local)[..., None].expand(-1, -1, -1, 3)
        p_local, n_local = p_local.gather(2, order), n_local.gather(2, order)
    count = valid.sum(1, keepdim=True)
    has_other = (valid & ((count - valid.long()) > 0))[..., None]
    fill = (valid[..., None] & ~has_other).float() * no_neighbour_distance
    return PointCloud(p_local, n_local, valid, has_other, fill, count.clamp(min=1), float(no_neighbour_distance))


def batch_cloud(batch: dict, mask: torch.Tensor, parts: bool = False, morton: bool = False) -> PointCloud:
    """The :class:`PointCloud` of a batch's ``points`` and ``normals`` (:func:`prepare_points`); with ``parts``
    (``geometry_distance=parts``) it carries the objects' convex part planes too (the batch's ``part_planes``,
    ``part_boxes``, ``part_valid``), so its distances are to the other objects' parts."""
    cloud = prepare_points(batch["points"], batch["normals"], mask, morton=morton)
    if parts:
        cloud.parts = PartPlanes.from_batch(batch, mask)
    return cloud


def signed_distances(cloud: PointCloud, translation: torch.Tensor, rotation: torch.Tensor, search: str = "pruned",
                     chunk: int | None = None, max_elements: int = CHUNK_ELEMENTS, prune: bool = True) -> torch.Tensor:
    """(B, N, M) signed nearest-other-object distance d of every point of ``cloud`` posed by translation (B, N, 3)
    metres and rotation (B, N, 3, 3) world-from-local (finite everywhere, padding objects too); the cloud's
    ``no_neighbour`` for an object alone in its scene, 0 at padding. ``search``: ``tree`` | ``pruned`` | ``dense``
    (``auto`` resolved by the caller: :func:`resolve_search`); chunk / max_elements / prune: see
    :func:`spread.model.nearest.nearest_other_point` (speed and memory, never the result). Differentiable in
    translation and rotation through the chosen pairs.

    The pruned search compares distances in the ``‖q‖² − 2p·q`` form, so its scenes are centred first (fewer
    float32 digits lost); the dense one measures differences, which need no centring. Without a gradient to keep,
    the dense search signs the distances itself (one operator: :mod:`spread.model.nearest_dense`)."""
    B, N, M, _ = cloud.points.shape
    valid = cloud.valid
    with torch.autocast(device_type=cloud.points.device.type, enabled=False):
        R, t = rotation.float(), translation.float()
        keep_graph = torch.is_grad_enabled() and (R.requires_grad or t.requires_grad)
        if search != "dense":  # scene-centred world frame: distances are unchanged
            t = t - (t * valid[..., None]).sum(1, keepdim=True) / cloud.count[..., None]
        world = pose_points(cloud.points, t, R)  # (B, N, M, 3)
        normals = torch.einsum("bnij,bnmj->bnmi", R, cloud.normals)
        if search == "dense" and not keep_graph:
            from spread.model.nearest_dense import tile_boxes

            _, d = torch.ops.spread.signed_nearest(world, normals, tile_boxes(world), valid, cloud.no_neighbour)
            return d.view(B, N, M)
        with torch.no_grad():
            if search == "dense":
                from spread.model.nearest_dense import nearest_dense_search

                nearest = nearest_dense_search(world.detach(), valid)
            elif search == "tree":
                nearest = nearest_other_point_tree(world.detach(), valid)
            else:
                nearest = nearest_other_point(world.detach(), cloud.points, t.detach(), R.detach(), valid,
                                              chunk=chunk, max_elements=max_elements, prune=prune)
        world_flat = world.view(B, N * M, 3)
        normals_flat = normals.reshape(B, N * M, 3)
        index = nearest[..., None].expand(B, N * M, 3)
        diff = world_flat - world_flat.gather(1, index)
        dist = torch.linalg.vector_norm(diff, dim=-1)
        # the sign of (p − q)·n_q, +0 for a zero product (adding +0.0 turns −0.0 into +0.0): outside, as documented
        signed = torch.copysign(dist, (diff * normals_flat.gather(1, index)).sum(-1) + 0.0)
        return torch.where(cloud.has_other, signed.view(B, N, M), cloud.fill)


def state_distances(cloud: PointCloud, states: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor,
                    search: str = "pruned", pairs: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """:func:`signed_distances` of the poses of node states (B, N, 9) — normalised translation, denormalised as
    ``offset + x·scale`` (metres), and rot6d — as the network computes them at every denoising step (no gradient):
    with the dense search, two operators (pose, signed search: :mod:`spread.model.nearest_dense`). A cloud with
    ``parts`` reads the distance to the other objects' convex parts instead (:mod:`spread.model.parts_distance`);
    with ``pairs`` (``parts`` only) it also returns each ordered pair's distance (B, N, N)."""
    B, N, M, _ = cloud.points.shape
    x = states.float()
    if pairs and cloud.parts is None:
        raise ValueError("pair distances (model.config.geometry_pairs) need geometry_distance=parts")
    if cloud.parts is not None:
        t, R = torch.addcmul(offset, x[..., :3], scale), rot6d_to_matrix(x[..., 3:9])
        return parts_distances(cloud.parts, pose_points(cloud.points, t, R), t, R, cloud.valid, pairs=pairs)
    if search == "dense":
        from spread.model.nearest_dense import BLOCK_K

        world, normals, boxes = torch.ops.spread.pose_states(x, offset, scale, cloud.points, cloud.normals, BLOCK_K)
        _, d = torch.ops.spread.signed_nearest(world, normals, boxes, cloud.valid, cloud.no_neighbour)
        return d.view(B, N, M)
    return signed_distances(cloud, torch.addcmul(offset, x[..., :3], scale), rot6d_to_matrix(x[..., 3:9]), search)


def blind_distances(cloud: PointCloud, pairs: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """What :func:`state_distances` reads when no other object is near anywhere — the geometry features of a scene
    whose objects are all far apart, whatever the poses: every real object's points at ``PARTS_RANGE`` (a cloud
    with ``parts``) or at the cloud's ``no_neighbour`` distance (chamfer), 0 at padding (B, N, M); with ``pairs``
    also every ordered pair at ``PARTS_RANGE`` (B, N, N). No search runs. Classifier-free guidance on the geometry
    (``SamplingConfig.geometry_scale``) contrasts the network's output with these against its output with the real
    ones."""
    B, N, M, _ = cloud.points.shape
    if pairs and cloud.parts is None:
        raise ValueError("pair distances (model.config.geometry_pairs) need geometry_distance=parts")
    far = PARTS_RANGE if cloud.parts is not None else cloud.no_neighbour
    out = torch.where(cloud.valid[..., None], far, 0.0).to(cloud.points.dtype).expand(B, N, M)
    if not pairs:
        return out
    return out, torch.full((B, N, N), PARTS_RANGE, device=out.device, dtype=out.dtype)


def signed_chamfer_features(points_local: torch.Tensor, normals_local: torch.Tensor, translation: torch.Tensor,
                            rotation: torch.Tensor, mask: torch.Tensor, chunk: int | None = None,
                            max_elements: int = CHUNK_ELEMENTS, prune: bool = True, search: str = "pruned",
                            no_neighbour_distance: float = NO_NEIGHBOUR_DISTANCE) -> torch.Tensor:
    """(B, N, M, 4) = [canonical xyz, signed NN distance to other objects] (see module docstring).

    points_local, normals_local: (B, N, M, 3) canonical frame (metres; unit normals).
    translation (B, N, 3) metres, rotation (B, N, 3, 3) world-from-local; mask (B, N) bool.
    search / chunk / max_elements / prune: see :func:`signed_distances` (speed and memory, never the result).
    """
    cloud = prepare_points(points_local, normals_local, mask, no_neighbour_distance=no_neighbour_distance)
    valid = cloud.valid
    # padding objects' poses may be anything (even NaN): identity at the origin instead
    t = torch.where(valid[..., None], translation.float(), 0.0)
    R = torch.where(valid[..., None, None], rotation.float(), torch.eye(3, device=rotation.device))
    d = signed_distances(cloud, t, R, resolve_search(search, points_local.device), chunk, max_elements, prune)
    return torch.cat([cloud.points, d[..., None]], dim=-1)
