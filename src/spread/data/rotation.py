"""6D rotation representation (Zhou et al. 2019), as in the reference release (DESIGN §3).

``rot6d`` = the first two COLUMNS of R (world-from-local) concatenated:
``[R00, R10, R20, R01, R11, R21]``. Back to R by Gram–Schmidt: b1 = a1/|a1|,
b2 = normalise(a2 − (b1·a2) b1), b3 = b1 × b2, R = [b1 b2 b3] as columns. Always a proper rotation
(det +1) for any input whose two halves are not parallel. Both functions take numpy arrays or torch
tensors and are batched over any leading dimensions.
"""

from __future__ import annotations

import numpy as np
from einops import rearrange

#: Added to norms before dividing, so a zero vector gives zeros instead of NaN.
EPS = 1e-8


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def matrix_to_rot6d(R):
    """(..., 3, 3) rotation matrices → (..., 6) first two columns, column-major."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_rot6d expects (..., 3, 3), got {tuple(R.shape)}")
    return rearrange(R[..., :, :2], "... row col -> ... (col row)")


def rot6d_to_matrix(x):
    """(..., 6) → (..., 3, 3) rotation matrices by Gram–Schmidt (columns b1, b2, b3)."""
    if x.shape[-1] != 6:
        raise ValueError(f"rot6d_to_matrix expects (..., 6), got {tuple(x.shape)}")
    if _is_torch(x):
        import torch

        a1, a2 = x[..., 0:3], x[..., 3:6]
        b1 = a1 / (torch.linalg.vector_norm(a1, dim=-1, keepdim=True) + EPS)
        b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
        b2 = b2 / (torch.linalg.vector_norm(b2, dim=-1, keepdim=True) + EPS)
        b3 = torch.linalg.cross(b1, b2, dim=-1)
        return torch.stack([b1, b2, b3], dim=-1)
    x = np.asarray(x)
    a1, a2 = x[..., 0:3], x[..., 3:6]
    b1 = a1 / (np.linalg.norm(a1, axis=-1, keepdims=True) + EPS)
    b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 = b2 / (np.linalg.norm(b2, axis=-1, keepdims=True) + EPS)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)
