"""The pair's residual: where the registered images still differ, the answer is least pinned down.

The network's posterior variance is amortised: it hardly depends on how well this pair ended up aligned, and after
the refinement has moved the mean it ranks the errors of the answer only weakly (``benchmarks/uncertainty_calibration.py``).
What a registration leaves unexplained is visible in the pair itself: after warping, the images still differ where
anatomy could not be matched (a structure the prior would not let the field reach, a fold of cortex the other brain
does not have, a boundary the deformation stopped short of). The Gaussian image likelihood of the paper reads that
difference as noise of one variance sigma^2 everywhere; estimated locally instead (a heteroscedastic likelihood),
the places of large residual are the places the data hold the field least, and the posterior widens there.

:func:`residual_variance` is that local estimate: the mean squared intensity difference of the warped moving image
and the fixed image (the network's inputs, intensities in [0, 1]) over a ``RESIDUAL_WINDOW``-voxel box, averaged onto
the velocity grid. :mod:`monai_probreg.uncertainty.calibration` adds it, times the fitted ``residual_weight``, to the
network's velocity variance before the scale; the weight is chosen by how well the sampled std ranks the errors of
the calibration's cases (``monai_probreg.fitting.calibration_probes``). Written by hand: no library offers a local
residual variance on another grid.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch.nn.functional as F
from torch import Tensor

from monai_probreg.losses.lncc import box_sum

__all__ = ["RESIDUAL_WINDOW", "residual_variance"]

RESIDUAL_WINDOW = 9  # side of the box the squared difference is averaged over, voxels of the images' grid (odd)


def residual_variance(
    warped: Tensor, fixed: Tensor, velocity_shape: Sequence[int], window: int = RESIDUAL_WINDOW
) -> Tensor:
    """(B, 1, *V): the local mean of ``(warped - fixed)^2`` (channels averaged) over a ``window``-voxel box, averaged
    onto the velocity grid ``velocity_shape`` (``V``; area averaging). ``warped``, ``fixed``: (B, C, *S), the warped
    moving image and the fixed image on one grid, intensities of the network's inputs; squared intensity units."""
    if warped.shape != fixed.shape or warped.ndim not in (4, 5):
        raise ValueError(
            f"expected the warped and fixed images (B, C, *S) of one shape, 2D or 3D; got {tuple(warped.shape)} and "
            f"{tuple(fixed.shape)}"
        )
    shape = tuple(int(n) for n in velocity_shape)
    if len(shape) != warped.ndim - 2 or min(shape) < 1:
        raise ValueError(f"expected {warped.ndim - 2} velocity grid sizes >= 1; got {tuple(velocity_shape)}")
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of voxels >= 1; got {window}")
    squared = (warped.float() - fixed.float()).square().mean(1, keepdim=True)
    local = box_sum(squared, window) / window ** (squared.ndim - 2) if window > 1 else squared  # zeros outside
    return F.interpolate(local, size=shape, mode="area")
