"""The fixed image's brain mask, to hide what the fixed image does not show (skull, neck) in the moving scan.

Templates and atlases are usually skull-stripped (LPBA40's, the MNI152 template nilearn ships); raw scans are not.
A network trained on brain-to-brain pairs, shown a whole head against a brain, pulls brain tissue towards the skull
(seen on the native S20 scan; docs/cli.md, "Registering your own scans"). After the affine pre-alignment the fixed
image's own support says where the brain is: ``mask = dilate(fixed > min(fixed), margin_mm)``, and the moving scan
on the fixed grid is set to its background value outside it before intensity scaling. For a fixed image with a head
around the brain (no background at its minimum), the mask is the whole grid or the head: nothing of the brain is
hidden. Given a fixed mask (``--fixed-mask``), its voxels are the support instead, dilated by the same margin
(:func:`dilated_mask`).

The dilation is a (separable) max-pool with a per-axis radius of ``ceil(margin_mm / spacing)`` voxels (a box, written
here because the package does not otherwise depend on scipy.ndimage; a box of radius r contains the ball of radius
r).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["DEFAULT_MARGIN_MM", "dilated_mask", "fixed_brain_mask", "hide_outside"]

DEFAULT_MARGIN_MM = 3.0  # room for the affine's residual error and for the brain's edge voxels


def fixed_brain_mask(
    array: np.ndarray, spacing: Sequence[float], margin_mm: float = DEFAULT_MARGIN_MM
) -> np.ndarray | None:
    """Boolean mask (same shape as the 3-d ``array``) of the voxels above the minimum, dilated by ``margin_mm``; None
    when that is the whole grid (no background: nothing to hide)."""
    if array.ndim != 3 or len(spacing) != 3:
        raise ValueError(f"expected a 3-d image and 3 spacings; got shape {array.shape} and spacing {tuple(spacing)}")
    return dilated_mask(array > array.min(), spacing, margin_mm)


def dilated_mask(
    support: np.ndarray, spacing: Sequence[float], margin_mm: float = DEFAULT_MARGIN_MM
) -> np.ndarray | None:
    """Boolean ``support`` (3-d) dilated by ``margin_mm`` (the module's box); None when that is the whole grid. The
    brain mask of :func:`fixed_brain_mask`, or of a given fixed mask (``--fixed-mask``: its voxels are the support)."""
    if support.ndim != 3 or len(spacing) != 3:
        raise ValueError(f"expected a 3-d mask and 3 spacings; got shape {support.shape} and spacing {tuple(spacing)}")
    if not margin_mm >= 0:
        raise ValueError(f"margin_mm must be >= 0; got {margin_mm}")
    if support.all():
        return None
    radius = [math.ceil(margin_mm / float(s) - 1e-9) for s in spacing]
    mask = torch.from_numpy(support.astype(np.float32))[None, None]
    for axis, r in enumerate(radius):  # a box is separable: three 1-d max-pools, 3 x 7 instead of 7^3 comparisons
        if r:
            kernel, padding = [1, 1, 1], [0, 0, 0]
            kernel[axis], padding[axis] = 2 * r + 1, r
            mask = F.max_pool3d(mask, kernel_size=kernel, stride=1, padding=padding)
    mask = mask[0, 0].numpy() > 0
    return None if mask.all() else mask


def hide_outside(array: np.ndarray, mask: np.ndarray | None, fill: float) -> np.ndarray:
    """``array`` with the voxels outside ``mask`` set to ``fill`` (unchanged when ``mask`` is None)."""
    if mask is None:
        return array
    if mask.shape != array.shape:
        raise ValueError(f"mask shape {mask.shape} does not match the image's {array.shape}")
    return np.where(mask, array, np.asarray(fill, dtype=array.dtype))
