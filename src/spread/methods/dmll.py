"""Discretised mixture of logistics (Salimans et al. 2017, PixelCNN++), ATISS's output distribution.

A value x ∈ [−1, 1] is modelled on ``bins`` equal bins (ATISS: 256) by K logistics with mixture logits π,
means μ and log-scales log s (clamped below at :data:`LOG_SCALE_MIN`). The probability of x is the mass of
its bin, ``σ((x + δ − μ)/s) − σ((x − δ − μ)/s)`` with δ = 1/(bins − 1); the two end bins extend to ∓∞.
Parameters come packed as (..., 3K) = [π, μ, log s].
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

LOG_SCALE_MIN = -7.0


def unpack(params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    logits, mean, log_scale = params.chunk(3, dim=-1)
    return logits, mean, log_scale.clamp(min=LOG_SCALE_MIN)


def log_prob(params: torch.Tensor, x: torch.Tensor, bins: int = 256) -> torch.Tensor:
    """log p(x) (...,) for values x (...,) in [−1, 1] and parameters (..., 3K)."""
    logits, mean, log_scale = unpack(params)
    x = x.clamp(-1.0, 1.0)[..., None]
    centred = x - mean
    inv_s = torch.exp(-log_scale)
    half = 1.0 / (bins - 1)
    plus_in = inv_s * (centred + half)
    min_in = inv_s * (centred - half)
    log_cdf_plus = plus_in - F.softplus(plus_in)  # log σ(plus_in): the lowest bin
    log_one_minus_cdf_min = -F.softplus(min_in)  # log(1 − σ(min_in)): the highest bin
    cdf_delta = torch.sigmoid(plus_in) - torch.sigmoid(min_in)
    mid_in = inv_s * centred
    log_pdf_mid = mid_in - log_scale - 2.0 * F.softplus(mid_in)  # density at the bin centre
    inner = torch.where(cdf_delta > 1e-5, torch.log(cdf_delta.clamp(min=1e-12)),
                        log_pdf_mid - math.log((bins - 1) / 2))
    per_component = torch.where(x < -0.999, log_cdf_plus, torch.where(x > 0.999, log_one_minus_cdf_min, inner))
    return torch.logsumexp(per_component + F.log_softmax(logits, dim=-1), dim=-1)


def sample(params: torch.Tensor, uniforms: torch.Tensor) -> torch.Tensor:
    """Samples (...,) in [−1, 1]: ``uniforms`` (..., 2) in (0, 1) pick the component (inverse CDF of the
    mixture weights) and the logistic draw μ + s·logit(u)."""
    logits, mean, log_scale = unpack(params)
    cdf = torch.softmax(logits, dim=-1).cumsum(-1)
    k = torch.searchsorted(cdf.contiguous(), uniforms[..., :1].contiguous().to(cdf.dtype)).clamp(max=cdf.shape[-1] - 1)
    mu = torch.gather(mean, -1, k)[..., 0]
    s = torch.gather(log_scale, -1, k)[..., 0].exp()
    u = uniforms[..., 1].clamp(1e-5, 1 - 1e-5)
    return (mu + s * (torch.log(u) - torch.log1p(-u))).clamp(-1.0, 1.0)
