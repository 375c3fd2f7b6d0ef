"""MONAI's local normalised cross-correlation with a rectangular window, its window sums taken by pooling on large grids.

``BoxLNCCLoss`` is :class:`monai.losses.LocalNormalizedCrossCorrelationLoss` (``kernel_type="rectangular"``): the same
formula, the same zero padding at the borders, the same ``smooth_nr`` / ``smooth_dr`` and reductions, so the same
values (tested against MONAI's to float rounding, 1-d to 3-d, values and gradients). Only the five window sums differ
in how they are computed, and only on grids of at least ``POOLED_FROM_VOXELS``: there MONAI's
``separable_filtering`` (a 1-d convolution per axis of each one-channel tensor) slows down much more than linearly on a
CPU, and ``avg_pool`` along one axis at a time over the stacked tensors (a fixed target's two sums outside autograd)
is faster, forward and backward (``benchmarks/lncc_speed.py``, 1 thread: 3.1x at 160 x 192 x 160, 1.6x at
120 x 144 x 120, 1.2x at 96 x 112 x 96; MONAI's is faster at the network's 80 x 96 x 80, 0.22 s against 0.28 s).
Below it, MONAI's own ``forward`` runs. The test-time refinement (:mod:`monai_probreg.engines.refinement`) evaluates
this loss and its gradient at every step, on a grid twice finer than the network's with ``image_grid_factor`` 2.
Written by hand for that reason only: neither MONAI nor torch offers the pooled form. (A box filter by cumulative
sums was tried in a scratch check: faster on small grids, but float32 cancellation put its gradient far from MONAI's
on a real brain pair.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from monai.losses import LocalNormalizedCrossCorrelationLoss
from torch import Tensor

__all__ = ["POOLED_FROM_VOXELS", "BoxLNCCLoss", "box_mean"]

# spatial voxels from which the window sums are pooled (MONAI's separable convolution below): the crossover measured
# by benchmarks/lncc_speed.py on a CPU lies between 80 x 96 x 80 (0.61M voxels, 0.8x) and 96 x 112 x 96 (1.03M, 1.2x)
POOLED_FROM_VOXELS = 800_000

_AVG_POOL = {1: F.avg_pool1d, 2: F.avg_pool2d, 3: F.avg_pool3d}


def box_mean(x: Tensor, kernel_size: int) -> Tensor:
    """(B, C, *S) -> the mean of each ``kernel_size``-wide window centred on each voxel (odd size), the voxels
    outside the image counted as zeros: one axis at a time (a box filter is separable)."""
    spatial_dims = x.ndim - 2
    pool = _AVG_POOL[spatial_dims]
    radius = kernel_size // 2
    for axis in range(spatial_dims):
        window = [1] * spatial_dims
        window[axis] = kernel_size
        padding = [0] * spatial_dims
        padding[axis] = radius
        x = pool(x, tuple(window), stride=1, padding=tuple(padding), count_include_pad=True)
    return x


class BoxLNCCLoss(LocalNormalizedCrossCorrelationLoss):
    """:class:`monai.losses.LocalNormalizedCrossCorrelationLoss` with a rectangular window, window sums by pooling on
    grids of ``pooled_from_voxels`` spatial voxels or more (module docstring; 0: always). Arguments as MONAI's, less
    ``kernel_type``; ``forward(pred, target)`` (B, C, *S), in [-1, 0]."""

    def __init__(
        self,
        spatial_dims: int = 3,
        kernel_size: int = 3,
        reduction: str = "mean",
        smooth_nr: float = 0.0,
        smooth_dr: float = 1e-5,
        pooled_from_voxels: int = POOLED_FROM_VOXELS,
    ) -> None:
        super().__init__(spatial_dims, kernel_size, "rectangular", reduction, smooth_nr, smooth_dr)
        if isinstance(pooled_from_voxels, bool) or not isinstance(pooled_from_voxels, int) or pooled_from_voxels < 0:
            raise ValueError(f"pooled_from_voxels must be an integer >= 0; got {pooled_from_voxels!r}")
        self.pooled_from_voxels = pooled_from_voxels

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.ndim - 2 != self.ndim:
            raise ValueError(f"expected pred with {self.ndim} spatial dimensions; got shape {tuple(pred.shape)}")
        if target.shape != pred.shape:
            raise ValueError(f"target must have pred's shape {tuple(pred.shape)}; got {tuple(target.shape)}")
        if pred.shape[2:].numel() < self.pooled_from_voxels:
            return super().forward(pred, target)
        channels = pred.shape[1]
        volume = float(self.kernel_size**self.ndim)
        # a fixed target (no gradient, the refinement's fixed image) is pooled outside autograd: its two window sums
        # need no backward pass, about a fifth of the loss's time on a 160 x 192 x 160 grid (same values)
        with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
            target_sums = box_mean(torch.cat([target, target * target], dim=1), self.kernel_size) * volume
        pred_sums = box_mean(torch.cat([pred, pred * pred, target * pred], dim=1), self.kernel_size) * volume
        t_sum, t2_sum = target_sums.split(channels, dim=1)
        p_sum, p2_sum, tp_sum = pred_sums.split(channels, dim=1)
        t_avg, p_avg = t_sum / volume, p_sum / volume
        # MONAI's formula: squared NCC = cross^2 / (var_t var_p), the variances floored at smooth_dr
        floor = torch.as_tensor(self.smooth_dr, dtype=pred_sums.dtype, device=pred_sums.device)
        cross = tp_sum - p_avg * t_sum
        t_var = torch.max(t2_sum - t_avg * t_sum, floor)
        p_var = torch.max(p2_sum - p_avg * p_sum, floor)
        ncc = (cross * cross + self.smooth_nr) / (t_var * p_var)
        if self.reduction == "sum":
            return ncc.sum().neg()
        if self.reduction == "none":
            return ncc.neg()
        if self.reduction == "mean":
            return ncc.mean().neg()
        raise ValueError(f"reduction must be 'mean', 'sum' or 'none'; got {self.reduction!r}")
