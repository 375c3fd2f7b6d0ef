"""The displacement's spread under the calibrated velocity posterior, to first order: no sampling.

The posterior is a diagonal Gaussian over the stationary velocity, N(mean, sigma^2), on the velocity grid. A
perturbation ``dv`` of the velocity moves the displacement of ``exp(mean + dv)`` by about ``dv`` resized onto the image
grid, to first order at the identity (a constant ``dv`` integrates to exactly that translation). With the posterior's
perturbation taken smooth at the velocity grid's scale, each component's displacement std on the image grid is the
velocity std resized like the velocity itself (linear, ``align_corners=True``, in voxels of the image grid):

    std_c(x) = resize(sigma_c)(x)        (voxels of the image grid; times the spacing along axis c for mm)

What is left out, on purpose: samples of the diagonal posterior are independent from one velocity voxel to the next,
and linear interpolation of independent noise has the variance sum_k w_k^2 sigma_k^2, lower between the velocity
grid's voxels than on them (a pattern of the grid, not of the pair); the integration averages them further along the
mean's flow; and K samples estimate a std with a relative error of about 1 / sqrt(2 (K - 1)) (18% for K = 16).
The calibration (``std_scale``, fitted on this map by ``python -m monai_probreg.fitting``) absorbs the average
damping; its ``sample_gain`` widens the samples that the label entropy reads so that their displacement spread
matches this map on average (:mod:`monai_probreg.uncertainty.calibration`). Held out, this map ranks the errors better
than the std of 16 samples (docs/uncertainty.md).

Written by hand: no library gives a registration posterior's displacement spread.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from monai_probreg.blocks.box_resize import resize_displacement_box

__all__ = ["displacement_variance"]


def displacement_variance(
    log_var: Tensor, spatial_size: Sequence[int], spacing: Sequence[float] | None = None
) -> Tensor:
    """(B, D, *spatial_size) first-order variance of each displacement component (module docstring) of the calibrated
    velocity posterior ``log_var`` (B, D, *V) (:func:`~monai_probreg.uncertainty.calibration.calibrate_log_var`'s),
    along the image grid's axis of that channel: squared voxels of ``spatial_size``, or mm^2 with ``spacing`` (the
    voxel size per axis of the image grid)."""
    if log_var.ndim not in (4, 5) or log_var.shape[1] != log_var.ndim - 2:
        raise ValueError(f"expected log_var (B, spatial_dims, *V), 2-d or 3-d; got shape {tuple(log_var.shape)}")
    dims = log_var.ndim - 2
    size = [int(s) for s in spatial_size]
    if len(size) != dims:
        raise ValueError(f"expected {dims} sizes of the image grid; got {tuple(spatial_size)}")
    std = resize_displacement_box((0.5 * log_var.float()).exp(), size, ([0] * dims, size))
    variance = std.square()
    if spacing is not None:
        if len(spacing) != dims:
            raise ValueError(f"expected one spacing per axis ({dims}); got {tuple(spacing)}")
        if not all(float(v) > 0 for v in spacing):
            raise ValueError(f"spacing must be positive; got {tuple(spacing)}")
        weights = torch.as_tensor([float(v) ** 2 for v in spacing], dtype=variance.dtype, device=variance.device)
        variance = variance * weights.view(1, dims, *([1] * dims))
    return variance
