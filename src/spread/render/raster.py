"""Vectorised numpy rasteriser: which pixels each projected triangle covers, and a label image.

Why numpy and not PIL polygons: drawing one PIL polygon per triangle costs a Python call per
triangle (tens of thousands per scene); a shapely union of the triangles is slower still. Here every
triangle's candidate pixels (its pixel bounding box) are enumerated in one flat array and tested with
edge functions at once, so a scene costs a handful of numpy passes whatever its triangle count.

A pixel is covered when its centre (c + ½, r + ½) lies inside or on a triangle; on top of that the
pixel holding each projected vertex is covered, so objects thinner than a pixel (a pencil seen from
above) still leave a trace. Labels are painted "highest rank wins", the painter's order of the caller.
"""

from __future__ import annotations

import numpy as np

#: Most candidate pixels tested at once; bounds memory to ~0.5 GB of temporaries in the worst case.
MAX_CANDIDATES = 4_000_000


def triangle_pixels(tris: np.ndarray, height: int, width: int,
                    corner_heights: np.ndarray | None = None):
    """Pixels covered by triangles.

    ``tris`` (T, 3, 2) float are (column, row) pixel coordinates of the corners. Returns
    (pixel flat indices ``row * width + col``, triangle index) pairs, int64, one per covered pixel;
    with ``corner_heights`` (T, 3) (world y of the corners) also the height interpolated at each
    covered pixel centre, for a depth test.
    """
    tris = np.asarray(tris, np.float64)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if corner_heights is not None:
        empty = empty + (np.zeros(0),)
    if tris.size == 0:
        return empty
    lo, hi = tris.min(axis=1), tris.max(axis=1)  # (T, 2)
    c0 = np.clip(np.ceil(lo[:, 0] - 0.5), 0, width).astype(np.int64)
    c1 = np.clip(np.floor(hi[:, 0] - 0.5), -1, width - 1).astype(np.int64)
    r0 = np.clip(np.ceil(lo[:, 1] - 0.5), 0, height).astype(np.int64)
    r1 = np.clip(np.floor(hi[:, 1] - 0.5), -1, height - 1).astype(np.int64)
    ncol = np.maximum(c1 - c0 + 1, 0)
    count = ncol * np.maximum(r1 - r0 + 1, 0)
    keep = np.flatnonzero(count)
    out_pix, out_tri, out_h = [], [], []
    # chunk over triangles so the candidate arrays stay bounded
    start = 0
    cum = np.cumsum(count[keep])
    while start < keep.size:
        base = cum[start - 1] if start else 0
        stop = max(int(np.searchsorted(cum, base + MAX_CANDIDATES, side="right")), start + 1)
        sel = keep[start:stop]
        pix, tri, h = _cover(tris[sel], c0[sel], r0[sel], ncol[sel], count[sel], width,
                             None if corner_heights is None else corner_heights[sel])
        out_pix.append(pix)
        out_tri.append(sel[tri])
        out_h.append(h)
        start = stop
    if not out_pix:
        return empty
    if corner_heights is None:
        return np.concatenate(out_pix), np.concatenate(out_tri)
    return np.concatenate(out_pix), np.concatenate(out_tri), np.concatenate(out_h)


def _cover(tris, c0, r0, ncol, count, width, corner_heights=None):
    t = np.repeat(np.arange(len(tris)), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    col = c0[t] + offset % ncol[t]
    row = r0[t] + offset // ncol[t]
    px, py = col + 0.5, row + 0.5
    a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    sign = np.where(area >= 0, 1.0, -1.0)
    eps = -1e-9
    inside = np.ones(len(t), bool)
    edges = []
    for p, q in ((a, b), (b, c), (c, a)):
        e = (q[:, 0] - p[:, 0]) * (py - p[:, 1]) - (q[:, 1] - p[:, 1]) * (px - p[:, 0])
        inside &= e * sign >= eps
        edges.append(e)
    if corner_heights is None:
        return row[inside] * width + col[inside], t[inside], None
    # barycentric weights: the edge opposite a corner weighs that corner
    safe = np.where(np.abs(area) > 1e-12, area, 1.0)
    h = corner_heights[t]
    height = (edges[1] * h[:, 0] + edges[2] * h[:, 1] + edges[0] * h[:, 2]) / safe
    height = np.where(np.abs(area) > 1e-12, height, h.max(axis=1))
    return row[inside] * width + col[inside], t[inside], height[inside]


def point_pixels(points: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the pixels holding (column, row) points (P, 2), and which points were inside."""
    cr = np.floor(np.asarray(points, np.float64)).astype(np.int64)
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < width) & (cr[:, 1] >= 0) & (cr[:, 1] < height)
    idx = np.flatnonzero(ok)
    return cr[idx, 1] * width + cr[idx, 0], idx


def paint_labels(pixels: np.ndarray, ranks: np.ndarray, height: int, width: int,
                 depth: np.ndarray | None = None) -> np.ndarray:
    """(H, W) int64 label image, −1 where nothing is painted.

    Without ``depth``: at each pixel the highest rank painted there (painter's order). With ``depth``
    (world height of each painted sample): the label of the highest sample (a z-buffer), ties broken
    by rank.
    """
    labels = np.full(height * width, -1, np.int64)
    if depth is None:
        np.maximum.at(labels, pixels, ranks)
        return labels.reshape(height, width)
    order = np.lexsort((ranks, depth, pixels))  # per pixel: ascending height, then rank
    pix_sorted = pixels[order]
    last = np.ones(len(order), bool)
    last[:-1] = pix_sorted[1:] != pix_sorted[:-1]
    labels[pix_sorted[last]] = ranks[order][last]
    return labels.reshape(height, width)


def boundary_mask(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool: labelled pixels with a 4-neighbour of a different label (the image edge is not one)."""
    edge = np.zeros(labels.shape, bool)
    diff_v = labels[1:, :] != labels[:-1, :]
    diff_h = labels[:, 1:] != labels[:, :-1]
    edge[1:, :] |= diff_v
    edge[:-1, :] |= diff_v
    edge[:, 1:] |= diff_h
    edge[:, :-1] |= diff_h
    return edge & (labels >= 0)
