"""What a registration can say about its own quality without labels: the features of the quality estimate.

All are computed on the grid the network worked on (the model grid of the command line, the dataset grid of the
bundle), inside the fixed image's foreground, from what every registration has: the two network inputs (intensities
in [0, 1], the moving one already affinely aligned on the command line), the warped moving image, the displacement
(voxels, channel k = tensor axis k) and the calibrated velocity entropy map:

- ``ncc_before`` / ``ncc_after``: Pearson correlation of moving / warped with fixed (global);
- ``lncc_before`` / ``lncc_after``: mean local NCC (MONAI's ``LocalNormalizedCrossCorrelationLoss``, negated) in a
  ``LNCC_KERNEL``-voxel window on the grid halved by 2x2x2 averaging (a 10-voxel window of the model grid; at full
  resolution the same statistic costs 40x more); local NCC sees misaligned folds that the global one averages out;
- ``entropy``: mean calibrated velocity entropy (nats, paper Eq. 8): the posterior's own doubt;
- ``displacement_mm``: mean length of the displacement in mm: a model that must move tissue far is either meeting
  an unusual anatomy or compensating for a failed affine;
- ``std_log_jacobian``, ``folding_percent``: how irregular the warp is (|J| <= 0 counts as folded).

An inverted or foreign contrast gives a low or negative NCC; a wrong orientation that the affine did not undo, a
cropped field of view or a missing block give low (L)NCC before and after; the entropy and the displacement grow
where the network has to guess. :mod:`monai_probreg.uncertainty.quality` turns these into a predicted Dice and a
probability of failure.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from monai.losses import LocalNormalizedCrossCorrelationLoss
from torch import Tensor

from monai_probreg.metrics.jacobian import jacobian_determinant

__all__ = ["FOREGROUND_LEVEL", "LNCC_KERNEL", "QualityFeatures", "local_ncc", "quality_features"]

FOREGROUND_LEVEL = 0.05  # fixed-input intensity (of [0, 1]) above which a voxel is foreground (brain or head)
LNCC_KERNEL = 5  # local NCC window, voxels of the half-resolution grid (about VoxelMorph's 9 at full)
_MIN_FOREGROUND = 64  # fewer foreground voxels than this: no meaningful statistic (an almost empty fixed image)


class QualityFeatures(NamedTuple):
    """One registration's label-free quality features (see the module docstring); plain floats."""

    ncc_before: float
    ncc_after: float
    lncc_before: float
    lncc_after: float
    entropy: float
    displacement_mm: float
    std_log_jacobian: float
    folding_percent: float


def _ncc(image: Tensor, fixed: Tensor, mask: Tensor) -> float:
    """Pearson correlation of ``image`` and ``fixed`` over ``mask``'s voxels (their copies centred in place)."""
    a, b = image[mask], fixed[mask]
    a, b = a.sub_(a.mean()), b.sub_(b.mean())
    denominator = float((a.square().sum() * b.square().sum()).sqrt())
    return float((a * b).sum()) / denominator if denominator > 0 else 0.0


def _length_mm(displacement: Tensor, spacing: Tensor) -> Tensor:
    """The displacement's length in mm per voxel: the components' squares added in axis order (as a sum over the
    first axis adds them: the same values) into one map, one component's temporary at a time."""
    length = (displacement[0] * spacing[0]).square_()
    for axis in range(1, len(displacement)):
        length += (displacement[axis] * spacing[axis]).square_()
    return length.sqrt_()


def _check(name: str, value: Tensor, shape: tuple[int, ...], channels: int | None = None) -> None:
    expected = shape if channels is None else (channels, *shape)
    if tuple(value.shape) != expected:
        raise ValueError(
            f"{name} must have shape {expected} (the fixed grid{', one channel per axis' if channels else ''}"
            f"); got {tuple(value.shape)}"
        )


def local_ncc(images: Tensor, fixed: Tensor, mask: Tensor | None = None) -> Tensor:
    """The features' local NCC of each image with its fixed image: (B,) mean local NCC of ``images`` and ``fixed``
    (B, 1, *S, intensities in [0, 1]) in a :data:`LNCC_KERNEL` window on the grid halved by 2x2x2 averaging, over the
    foreground of ``fixed`` (above :data:`FOREGROUND_LEVEL`; all voxels when it has none). The one rule for "how alike
    are two images" of the quality estimate and of the refinement's similarity guard (``engines/refinement.py``).
    ``mask`` (B, 1, *S, bool): only its voxels too (the guard's cost-function masks; a halved voxel is inside when
    most of it is), or None. Without gradients."""
    if images.shape != fixed.shape or images.ndim not in (4, 5) or images.shape[1] != 1:
        raise ValueError(
            f"images and fixed must both have shape (B, 1, *S) with 2 or 3 spatial axes; got {tuple(images.shape)} "
            f"and {tuple(fixed.shape)}"
        )
    dims = images.ndim - 2
    with torch.no_grad():
        lncc = LocalNormalizedCrossCorrelationLoss(spatial_dims=dims, kernel_size=LNCC_KERNEL, reduction="none")
        pool = torch.nn.functional.avg_pool3d if dims == 3 else torch.nn.functional.avg_pool2d
        half_images, half_fixed = (pool(x.float(), 2, ceil_mode=True) for x in (images, fixed))
        values = []
        masks = [None] * len(fixed) if mask is None else mask
        for image, reference, full, given in zip(half_images, half_fixed, fixed, masks):
            inside = pool((full > FOREGROUND_LEVEL).float()[None], 2, ceil_mode=True)[0, 0] > 0.5
            if given is not None:
                allowed = pool(given.float()[None], 2, ceil_mode=True)[0, 0] > 0.5
                # the foreground inside the mask; the mask alone when they share nothing
                inside = inside & allowed if bool((inside & allowed).any()) else allowed
            if not bool(inside.any()):
                inside = torch.ones_like(inside)
            values.append(-lncc(image[None], reference[None])[0, 0][inside].mean())
        return torch.stack(values)


@torch.inference_mode()
def quality_features(
    moving: Tensor,
    fixed: Tensor,
    warped: Tensor,
    displacement: Tensor,
    entropy: Tensor,
    spacing: Sequence[float] | None = None,
    jacobian: Tensor | None = None,
) -> QualityFeatures:
    """The features of one registration.

    Args:
        moving, fixed, warped: (*S) network inputs and the warped moving image, intensities in [0, 1].
        displacement: (D, *S) voxels of the same grid, channel k = tensor axis k.
        entropy: (*S) calibrated velocity entropy on the same grid.
        spacing: voxel size in mm per axis (None: 1 mm).
        jacobian: (*S) det of the displacement's Jacobian when the caller has it (else computed here).

    Raises:
        ValueError: shapes that do not match ``fixed``, a wrong spacing, or a fixed image with (almost) no foreground.
    """
    fixed = torch.as_tensor(fixed).float()
    shape = tuple(fixed.shape)
    dims = len(shape)
    if dims not in (2, 3):
        raise ValueError(f"fixed must be a 2-d or 3-d image (*S); got shape {shape}")
    for name, value in (("moving", moving), ("warped", warped), ("entropy", entropy), ("jacobian", jacobian)):
        if value is not None:
            _check(name, torch.as_tensor(value), shape)
    _check("displacement", torch.as_tensor(displacement), shape, dims)
    spacing_t = torch.ones(dims) if spacing is None else torch.as_tensor([float(s) for s in spacing])
    if spacing_t.numel() != dims or bool((spacing_t <= 0).any()):
        raise ValueError(f"spacing must be {dims} positive numbers (mm); got {spacing!r}")
    moving, warped = torch.as_tensor(moving).float(), torch.as_tensor(warped).float()
    displacement, entropy = torch.as_tensor(displacement).float(), torch.as_tensor(entropy).float()
    mask = fixed > FOREGROUND_LEVEL
    if int(mask.sum()) < _MIN_FOREGROUND:
        raise ValueError(
            f"the fixed image has {int(mask.sum())} voxels above {FOREGROUND_LEVEL} of its [0, 1] range; "
            f"quality features need at least {_MIN_FOREGROUND}"
        )
    lncc_before, lncc_after = local_ncc(torch.stack([moving, warped])[:, None], fixed.expand(2, 1, *shape))
    # one feature after the other, each one's temporaries gone before the next one's are made (the same values)
    ncc_before, ncc_after = _ncc(moving, fixed, mask), _ncc(warped, fixed, mask)
    entropy_mean = float(entropy[mask].mean())
    displacement_mm = float(_length_mm(displacement, spacing_t)[mask].mean())
    det = (jacobian_determinant(displacement[None])[0] if jacobian is None else torch.as_tensor(jacobian).float())[mask]
    positive = det[det > 0]
    std_log_jacobian = float(positive.log().std()) if positive.numel() > 1 else 0.0
    del positive
    return QualityFeatures(
        ncc_before=ncc_before,
        ncc_after=ncc_after,
        lncc_before=float(lncc_before),
        lncc_after=float(lncc_after),
        entropy=entropy_mean,
        displacement_mm=displacement_mm,
        std_log_jacobian=std_log_jacobian,
        folding_percent=100.0 * float((det <= 0).float().mean()),
    )
