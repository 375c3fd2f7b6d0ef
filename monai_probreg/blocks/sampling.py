"""Reparameterised sampling of the velocity posterior ``q(z | moving, fixed) = N(mean, diag(exp(log_var)))``.

``log_var`` is a log-variance (log sigma^2), per voxel and per component, on the velocity grid.
This is the variational head's sampling layer (written here: MONAI has no equivalent).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from monai_probreg.utils.tensors import shape_str

__all__ = ["sample_velocity", "VelocitySampler"]


def sample_velocity(
    mean: Tensor,
    log_var: Tensor,
    num_samples: int = 1,
    generator: torch.Generator | None = None,
    scales: Tensor | None = None,
) -> Tensor:
    """Draw ``z = mean + exp(log_var / 2) * eps``, ``eps ~ N(0, I)``; differentiable in mean and log_var.
    ``scales`` (num_samples,): sample k's deviation from the mean multiplied by ``scales[k]`` (a Gaussian scale
    mixture's draws, :func:`monai_probreg.uncertainty.samples.sample_scales`); None: 1.

    Shapes: mean, log_var (B, D, *S) -> (num_samples, B, D, *S).
    """
    if mean.shape != log_var.shape:
        raise ValueError(
            "mean and log_var must have the same shape; got "
            + shape_str(mean.shape)
            + " and "
            + shape_str(log_var.shape)
        )
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1; got {num_samples}")
    if scales is not None and (scales.dim() != 1 or scales.shape[0] != num_samples):
        raise ValueError(f"expected one scale per sample, shape ({num_samples},); got {shape_str(scales.shape)}")
    eps = torch.randn([num_samples] + list(mean.shape), dtype=mean.dtype, device=mean.device, generator=generator)
    std = torch.exp(0.5 * log_var).unsqueeze(0)
    if scales is not None:
        shape = [num_samples] + [1] * mean.dim()
        std = std * scales.to(device=mean.device, dtype=mean.dtype).view(shape)
    return mean.unsqueeze(0) + std * eps


class VelocitySampler(nn.Module):
    """Training: one reparameterised sample. Eval: the posterior mean (deterministic, the MAP of the paper's Eq. 7)."""

    def forward(self, mean: Tensor, log_var: Tensor) -> Tensor:
        if not self.training:
            return mean
        return sample_velocity(mean, log_var, num_samples=1)[0]
