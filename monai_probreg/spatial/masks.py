"""Cost-function masks (``--fixed-mask``, ``--moving-mask``; ANTs' ``antsRegistration -x [fixedMask,movingMask]``):
which voxels of each image the affine metric and the refinement's image term may look at.

A mask is a volume on its own image's grid (the same grid: :func:`~monai_probreg.spatial.volume_io.check_same_grid`),
read as any volume is (:func:`~monai_probreg.spatial.volume_io.read_volume`: every check of an image file but the
constant-image one), and, as ANTs reads it, **every nonzero voxel is inside** (a label map or a probability map works
as a mask of its nonzero voxels). A mask with no nonzero voxel is refused (nothing to compare).

What they mean (ITK's ``SetFixedImageMask`` / ``SetMovingImageMask``):

- the **fixed mask** says where, on the fixed grid, the metric is evaluated: the affine's sample points are drawn
  inside it only, the refinement's local NCC is summed inside it only; it also replaces the fixed image's support as
  the brain mask that hides the moving scan (:mod:`monai_probreg.spatial.brain_mask`, dilated by the same margin);
- the **moving mask** drops the fixed points whose mapped position falls outside it (a lesion, or an artefact only the
  moving scan has): the affine metric weighs each sample by the moving mask at its mapped point, the refinement's local
  NCC weighs each voxel by the moving mask warped with the current displacement (no gradient through the mask).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from monai_probreg.spatial.volume_io import Volume, check_same_grid, read_volume
from monai_probreg.utils.errors import InputError

__all__ = ["MASK_ADVICE", "MASK_LEVEL", "mask_record", "read_mask"]

MASK_ADVICE = "resample the mask onto its image first (nearest neighbour)"
# a mask resampled linearly onto another grid (the moving mask through the affine) is inside where it is at least this
MASK_LEVEL = 0.5


def read_mask(path: str | os.PathLike, role: str, image: Volume, image_role: str) -> Volume:
    """The mask file ``path`` (``role`` names it in errors, e.g. ``"--fixed-mask"``) as a boolean :class:`Volume`
    (nonzero = inside) on ``image``'s grid; InputError (one line naming the file) for an unreadable file, a mask on
    another grid than ``image`` (``image_role``) or one with no voxel inside."""
    volume = read_volume(path, role, np.float64)  # float64: integer-valued masks read exactly
    check_same_grid(volume, image, role, image_role, MASK_ADVICE)
    inside = volume.array != 0
    if not inside.any():
        raise InputError(f"{role} {str(path)!r}: expected a mask with at least one nonzero voxel (inside), got none")
    return Volume(inside, volume.index_to_lps, volume.path)


def mask_record(mask: Volume | None) -> dict | None:
    """A mask as ``summary.json`` records it: its file and the fraction of its grid inside; None without one."""
    if mask is None:
        return None
    return {"path": str(Path(mask.path).resolve()), "fraction_inside": round(float(mask.array.mean()), 4)}
