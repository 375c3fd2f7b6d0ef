"""Uncertainty maps: the velocity entropy (paper Eq. 8) and the empirical deformation uncertainty.

- ``velocity_entropy``: H(z_j) = sum_c 1/2 log(2 pi e sigma_cj^2), closed form from the posterior's log-variance
  (the paper's Eq. 8 drops the e; we keep the exact Gaussian entropy), resized to the image grid.
- ``displacement_uncertainty``: from K posterior samples of the displacement, the per-voxel variance of each
  component and the entropy of a Gaussian with that diagonal covariance, sum_c 1/2 log(2 pi e var_c).
- ``sampled_displacement_moments``: the same mean and variance streamed over K samples drawn from the posterior
  (``chunk`` at a time; float32 sums of each sample's deviation from the first, whose squares stay small where sums
  of the displacements themselves would cancel), so K full-resolution fields are never held at once.
- ``label_entropy``: from K label maps propagated by K posterior samples, the per-voxel entropy (nats) of the
  empirical label distribution: 0 where every sample agrees, log K at most.
Written here: no library offers these for registration posteriors.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from monai_probreg.blocks.sampling import sample_velocity

__all__ = [
    "velocity_entropy",
    "DisplacementUncertainty",
    "displacement_uncertainty",
    "sampled_displacement_moments",
    "label_entropy",
]

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


def label_entropy(label_samples: Tensor) -> Tensor:
    """Entropy of K propagated label maps per voxel: (K, *S) integer labels -> (*S) float, nats.

    With c_k the number of samples that agree with sample k, H = -sum_l p_l log p_l = -(1/K) sum_k log(c_k / K).
    """
    if label_samples.ndim < 2 or label_samples.shape[0] < 1:
        raise ValueError(f"label_samples must have shape (K, *S) with K >= 1; got {tuple(label_samples.shape)}")
    if label_samples.is_floating_point():
        raise ValueError(f"label_samples must be integer labels; got dtype {label_samples.dtype}")
    num = label_samples.shape[0]
    entropy = torch.zeros(label_samples.shape[1:], dtype=torch.float32, device=label_samples.device)
    for k in range(num):
        agree = (label_samples == label_samples[k]).sum(dim=0, dtype=torch.int32)
        entropy -= torch.log(agree.float() / num)
    return entropy / num


def sampled_displacement_moments(
    mean: Tensor,
    log_var: Tensor,
    to_displacement: Callable[[Tensor], Tensor],
    num_samples: int,
    generator: torch.Generator | None = None,
    chunk: int = 4,
) -> tuple[Tensor, Tensor]:
    """Mean and unbiased variance (each (B, D, *S), float32) of ``to_displacement(z)`` over ``num_samples`` >= 2
    velocities z ~ N(mean, exp(log_var)) (posterior on the velocity grid, (B, D, *V)).

    ``to_displacement`` maps a batch of velocities (n, D, *V) to displacements (n, D, *S), e.g.
    ``lambda z: network.velocity_to_displacement(z, size)``; pass ``-z`` inside it for the inverse. Calibrate
    ``log_var`` first (:func:`monai_probreg.uncertainty.calibration.calibrate_log_var`) for calibrated moments.
    """
    if num_samples < 2:
        raise ValueError(f"num_samples must be >= 2 for a variance; got {num_samples}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1; got {chunk}")
    batch = mean.shape[0]
    shift = total = squares = deviation = None
    for start in range(0, num_samples, chunk):
        z = sample_velocity(mean, log_var, min(chunk, num_samples - start), generator=generator)
        disp = to_displacement(z.flatten(0, 1)).unflatten(0, (z.shape[0], batch)).float()  # (n, B, D, *S)
        if shift is None:  # sums of the deviations from the first sample: small numbers, exact enough in float32
            shift = disp[0].clone()
            total, squares, deviation = torch.zeros_like(shift), torch.zeros_like(shift), torch.empty_like(shift)
        for sample in disp:
            torch.sub(sample, shift, out=deviation)
            total += deviation
            squares.addcmul_(deviation, deviation)
        del disp
    variance = ((squares - total**2 / num_samples) / (num_samples - 1)).clamp(min=0)
    return shift + total / num_samples, variance
