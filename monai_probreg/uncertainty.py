"""Uncertainty maps: the velocity entropy (paper Eq. 8) and the empirical deformation uncertainty.

- ``velocity_entropy``: H(z_j) = sum_c 1/2 log(2 pi e sigma_cj^2), closed form from the posterior's log-variance
  (the paper's Eq. 8 drops the e; we keep the exact Gaussian entropy), resized to the image grid.
- ``displacement_uncertainty``: from K posterior samples of the displacement, the per-voxel variance of each
  component and the entropy of a Gaussian with that diagonal covariance, sum_c 1/2 log(2 pi e var_c).
Written here: no library offers these for registration posteriors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch.nn.functional as F
from torch import Tensor

__all__ = ["velocity_entropy", "DisplacementUncertainty", "displacement_uncertainty"]

_LOG_2PI_E = math.log(2.0 * math.pi * math.e)


def velocity_entropy(log_var: Tensor, spatial_size: Sequence[int] | None = None) -> Tensor:
    """Per-voxel entropy of q(z_j): ``log_var`` (B, D, *V) -> (B, 1, *V), or (B, 1, *spatial_size) if given
    (linear resampling, align-corners, onto the image grid)."""
    if log_var.ndim not in (4, 5) or log_var.shape[1] != log_var.ndim - 2:
        raise ValueError(f"log_var must have shape (B, spatial_dims, *V); got {tuple(log_var.shape)}")
    entropy = 0.5 * (_LOG_2PI_E + log_var).sum(dim=1, keepdim=True)
    if spatial_size is not None and tuple(spatial_size) != tuple(entropy.shape[2:]):
        mode = "trilinear" if entropy.ndim == 5 else "bilinear"
        entropy = F.interpolate(entropy, size=tuple(spatial_size), mode=mode, align_corners=True)
    return entropy


class DisplacementUncertainty(NamedTuple):
    """mean, variance: (B, D, *S) over samples (variance unbiased, K - 1); entropy: (B, 1, *S)."""

    mean: Tensor
    variance: Tensor
    entropy: Tensor


def displacement_uncertainty(samples: Tensor, eps: float = 1e-12) -> DisplacementUncertainty:
    """Summarise K displacement samples (K, B, D, *S), K >= 2. ``eps`` floors the variance inside the log."""
    if samples.ndim not in (5, 6) or samples.shape[2] != samples.ndim - 3:
        raise ValueError(f"samples must have shape (K, B, spatial_dims, *S); got {tuple(samples.shape)}")
    if samples.shape[0] < 2:
        raise ValueError(f"need at least 2 samples for a variance; got {samples.shape[0]}")
    mean = samples.mean(dim=0)
    variance = samples.var(dim=0, unbiased=True)
    entropy = 0.5 * (_LOG_2PI_E + variance.clamp(min=eps).log()).sum(dim=1, keepdim=True)
    return DisplacementUncertainty(mean, variance, entropy)
