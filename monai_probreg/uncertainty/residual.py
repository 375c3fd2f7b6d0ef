"""The pair's residual: where the registered images still differ, the answer is least pinned down.

The network's posterior variance is amortised: it hardly depends on how well this pair ended up aligned, and after
the refinement has moved the mean it ranks the errors of the answer only weakly (``benchmarks/uncertainty_calibration.py``).
What a registration leaves unexplained is visible in the pair itself: after warping, the images still differ where
anatomy could not be matched (a structure the prior would not let the field reach, a fold of cortex the other brain
does not have, a boundary the deformation stopped short of). The Gaussian image likelihood of the paper reads that
difference as noise of one variance sigma^2 everywhere; estimated locally instead (a heteroscedastic likelihood),
the places of large residual are the places the data hold the field least, and the posterior widens there.

:func:`residual_variance` is that local estimate, of what the registration can have left: both images smoothed over a
``RESIDUAL_SMOOTHING``-voxel box (the noise of a voxel is no misalignment), the warped moving image multiplied by the
local gain that matches its ``RESIDUAL_GAIN_WINDOW``-voxel mean to the fixed image's (a bias field, a scanner's
shading: a smooth intensity ratio is no misalignment either), then the mean squared difference over a
``RESIDUAL_WINDOW``-voxel box, averaged onto the velocity grid (intensities of the network's inputs, in [0, 1]).
:mod:`monai_probreg.uncertainty.calibration` adds it, times the fitted ``residual_weight``, to the network's velocity
variance before the scale; the weight is chosen by how well the std map ranks the errors of the calibration's
cases (``monai_probreg.fitting.calibration_probes``). The smoothing and the gain were chosen by how the std ranks the
errors of both calibration probes (docs/uncertainty.md, "The pair's residual"). Written by hand: no library offers
a local residual variance on another grid.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch.nn.functional as F
from torch import Tensor

from monai_probreg.losses.lncc import box_sum

__all__ = [
    "PLAIN_RESIDUAL_FORM",
    "RESIDUAL_GAIN_WINDOW",
    "RESIDUAL_SMOOTHING",
    "RESIDUAL_WINDOW",
    "residual_form",
    "residual_variance",
    "squared_difference",
]

RESIDUAL_WINDOW = 9  # side of the box the squared difference is averaged over, voxels of the images' grid (odd)
RESIDUAL_SMOOTHING = 3  # side of the box both images are averaged over first (odd; 1: no smoothing)
RESIDUAL_GAIN_WINDOW = 25  # side of the box whose mean intensities give the local gain (odd; 1: no gain)
# the residual of bundles 0.24.0-0.28.0 (the squared difference itself over a 9-voxel box, as they fixed it): what a
# calibration sidecar without a "residual" record was fitted with, whatever the defaults above become
PLAIN_RESIDUAL_FORM = {"window": 9, "smoothing": 1, "gain_window": 1}
_GAIN_FLOOR = 1e-3  # added to both local means: the gain of an empty neighbourhood (the background) is 1


def residual_form() -> dict[str, int]:
    """The boxes :func:`residual_variance` uses by default, as a calibration sidecar records them (its
    ``residual_weight`` is per unit of this residual)."""
    return {"window": RESIDUAL_WINDOW, "smoothing": RESIDUAL_SMOOTHING, "gain_window": RESIDUAL_GAIN_WINDOW}


def _box_average(x: Tensor, window: int) -> Tensor:
    """The mean over a ``window``-voxel box centred on each voxel, the voxels outside counted as zeros (``box_sum``,
    the CPU's faster box, rather than ``losses.lncc.box_mean``'s pooling, which the loss keeps for its backward)."""
    return box_sum(x, window) / window ** (x.ndim - 2) if window > 1 else x


def residual_variance(
    warped: Tensor,
    fixed: Tensor,
    velocity_shape: Sequence[int],
    window: int = RESIDUAL_WINDOW,
    smoothing: int = RESIDUAL_SMOOTHING,
    gain_window: int = RESIDUAL_GAIN_WINDOW,
) -> Tensor:
    """(B, 1, *V): the local mean over a ``window``-voxel box of ``(g s(warped) - s(fixed))^2`` (channels averaged),
    averaged onto the velocity grid ``velocity_shape`` (``V``; area averaging); ``s``: the mean over a
    ``smoothing``-voxel box, ``g``: the ratio of the fixed to the warped image's mean over a ``gain_window``-voxel box
    (each plus a floor of 1e-3: 1 where both are empty). ``warped``, ``fixed``: (B, C, *S), the warped moving image
    and the fixed image on one grid, intensities of the network's inputs; squared intensity units."""
    shape = tuple(int(n) for n in velocity_shape)
    if len(shape) != warped.ndim - 2 or min(shape) < 1:
        raise ValueError(f"expected {warped.ndim - 2} velocity grid sizes >= 1; got {tuple(velocity_shape)}")
    _check_box("window", window)
    squared = squared_difference(warped, fixed, smoothing, gain_window)
    return F.interpolate(_box_average(squared, window), size=shape, mode="area")


def squared_difference(
    warped: Tensor, fixed: Tensor, smoothing: int = RESIDUAL_SMOOTHING, gain_window: int = RESIDUAL_GAIN_WINDOW
) -> Tensor:
    """(B, 1, *S): ``(g s(warped) - s(fixed))^2`` per voxel (channels averaged), before :func:`residual_variance`'s
    box and averaging (its docstring); the error model boxes it over several windows (uncertainty.error_model)."""
    if warped.shape != fixed.shape or warped.ndim not in (4, 5):
        raise ValueError(
            f"expected the warped and fixed images (B, C, *S) of one shape, 2D or 3D; got {tuple(warped.shape)} and "
            f"{tuple(fixed.shape)}"
        )
    _check_box("smoothing", smoothing)
    _check_box("gain_window", gain_window)
    moving, target = warped.float(), fixed.float()
    if gain_window > 1:
        gain = (_box_average(target, gain_window) + _GAIN_FLOOR) / (_box_average(moving, gain_window) + _GAIN_FLOOR)
        moving = moving * gain
    return (_box_average(moving, smoothing) - _box_average(target, smoothing)).square().mean(1, keepdim=True)


def _check_box(name: str, size: int) -> None:
    if isinstance(size, bool) or not isinstance(size, int) or size < 1 or size % 2 == 0:
        raise ValueError(f"{name} must be an odd number of voxels >= 1; got {size!r}")
