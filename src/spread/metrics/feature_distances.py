"""Distances between two sets of image features: Fréchet (FID) and kernel (KID) distance, in float64 numpy.

**Fréchet distance** of the Gaussians fitted to features X (n₁ × D) and Y (n₂ × D):

    d² = |μ_X − μ_Y|² + tr Σ_X + tr Σ_Y − 2 tr (Σ_X^½ Σ_Y Σ_X^½)^½

with the unbiased covariances of ``np.cov`` (what clean-fid's ``fid_from_feats`` uses). Computed without
``sqrtm`` and without subtracting two large traces:

* moments in two passes: μ first, then the centred rows A = (X − μ_X)/√(n₁−1), B likewise, so Σ_X = AᵀA
  exactly as written and no Σffᵀ − nμμᵀ cancellation happens;
* the trace term is the nuclear norm of B Aᵀ: Σ_X^½ Σ_Y Σ_X^½ = (B Σ_X^½)ᵀ(B Σ_X^½) and
  (B Σ_X^½)(B Σ_X^½)ᵀ = (B Aᵀ)(B Aᵀ)ᵀ, so both have the singular values of B Aᵀ. Thin QR factors
  (A = Q_A R_A) shrink it to k × k, k = min(n, D), whatever the number of scenes;
* the covariance part is then a sum of squares, tr Σ_X + tr Σ_Y − 2‖R_B R_Aᵀ‖_* = min over rotations U of
  ‖R_Aᵀ − R_Bᵀ U‖²_F (orthogonal Procrustes; U from the SVD of R_B R_Aᵀ), evaluated as that residual:
  d² ≥ 0 by construction, never a negative FID from rounding.

Two identical feature sets (the same rows in any order) have distance 0 exactly: the Procrustes rotation
of a set onto itself is the identity, which the SVD returns only to ~1e-16, so that case is decided by
comparing the rows instead of left to rounding.

**Kernel distance** (KID, Bińkowski et al. 2018) as clean-fid computes it: the unbiased MMD² with the
cubic polynomial kernel k(x, y) = (xᵀy / D + 1)³, averaged over ``subsets`` random subsets of
m = min(n₁, n₂, ``max_subset_size``) rows of each set drawn without replacement. The draws come from
``numpy.random.RandomState(seed)`` in clean-fid's order (Y's rows, then X's, per subset), so the value is
reproducible and equals clean-fid's ``kernel_distance`` after ``np.random.seed(seed)``. KID is unbiased
and can be slightly negative when the sets match; it is meaningful at the few hundred scenes where FID
(which needs n ≫ D to estimate Σ) is biased upward.
"""

from __future__ import annotations

import numpy as np

#: clean-fid's KID defaults.
KID_SUBSETS = 100
KID_MAX_SUBSET_SIZE = 1000


def _as_features(x, name: str) -> np.ndarray:
    x = np.asarray(x, np.float64)
    if x.ndim != 2:
        raise ValueError(f"{name}: features must be (n, D), got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{name}: features contain NaN or inf")
    return x


def same_rows(x: np.ndarray, y: np.ndarray) -> bool:
    """Whether ``x`` and ``y`` hold the same rows, in any order."""
    if x.shape != y.shape or not np.array_equal(np.sort(x[:, 0]), np.sort(y[:, 0])):
        return False
    return bool(np.array_equal(x[np.lexsort(x.T[::-1])], y[np.lexsort(y.T[::-1])]))


def _centred_factor(x: np.ndarray) -> np.ndarray:
    """R (k × D, k = min(n, D)) with RᵀR = the unbiased covariance of the rows of ``x``."""
    a = (x - x.mean(axis=0)) / np.sqrt(len(x) - 1)
    return np.linalg.qr(a, mode="r")


def frechet_distance(x, y) -> float:
    """The Fréchet distance between the Gaussians of feature sets ``x`` (n₁, D) and ``y`` (n₂, D), n ≥ 2."""
    x, y = _as_features(x, "x"), _as_features(y, "y")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"feature sizes differ: {x.shape[1]} and {y.shape[1]}")
    if min(len(x), len(y)) < 2:
        raise ValueError(f"the Fréchet distance needs ≥ 2 features per set, got {len(x)} and {len(y)}")
    if same_rows(x, y):
        return 0.0
    ra, rb = _centred_factor(x), _centred_factor(y)
    k = max(len(ra), len(rb))  # pad to one size: the Procrustes rotation is then square (orthogonal)
    ra = np.vstack([ra, np.zeros((k - len(ra), ra.shape[1]))])
    rb = np.vstack([rb, np.zeros((k - len(rb), rb.shape[1]))])
    u, _, vt = np.linalg.svd(rb @ ra.T)
    residual = ra.T - rb.T @ (u @ vt)
    diff = x.mean(axis=0) - y.mean(axis=0)
    return float(diff @ diff + np.sum(residual * residual))


def kernel_distance(x, y, subsets: int = KID_SUBSETS, max_subset_size: int = KID_MAX_SUBSET_SIZE,
                    seed: int = 0) -> float:
    """KID between feature sets ``x`` (generated) and ``y`` (reference), clean-fid's estimator (module
    docstring); needs ≥ 2 features per set."""
    x, y = _as_features(x, "x"), _as_features(y, "y")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"feature sizes differ: {x.shape[1]} and {y.shape[1]}")
    d = x.shape[1]
    m = min(len(x), len(y), int(max_subset_size))
    if m < 2:
        raise ValueError(f"KID needs ≥ 2 features per set, got {len(x)} and {len(y)}")
    rng = np.random.RandomState(int(seed))
    total = 0.0
    for _ in range(int(subsets)):
        a = y[rng.choice(len(y), m, replace=False)]
        b = x[rng.choice(len(x), m, replace=False)]
        kaa = (a @ a.T / d + 1) ** 3
        kbb = (b @ b.T / d + 1) ** 3
        kab = (a @ b.T / d + 1) ** 3
        same = kaa.sum() - np.trace(kaa) + kbb.sum() - np.trace(kbb)
        total += same / (m - 1) - kab.sum() * 2 / m
    return float(total / int(subsets) / m)
