"""The two images of a registration: the fixed image prepared once (:class:`FixedSpace`, :func:`prepare_fixed`: its
geometry, model grid, normalised model input, brain mask; a batch pays for it once) and the moving scan read with its
label map and cost-function mask (:func:`read_moving`, the ``read`` stage), each checked on the way in
(:mod:`monai_probreg.spatial.volume_io`, :mod:`monai_probreg.spatial.masks`)."""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from typing import NamedTuple

import itk
import numpy as np

from monai_probreg.spatial.affine import AffineSettings
from monai_probreg.spatial.affine_torch import FixedSamples, fixed_samples
from monai_probreg.spatial.brain_mask import DEFAULT_MARGIN_MM, dilated_mask, fixed_brain_mask
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.masks import read_mask
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.volume_io import Volume, check_same_grid, read_image, read_label, volume_to_itk

__all__ = ["FixedSpace", "MovingScan", "compact_label", "label_dtype", "prepare_fixed", "read_moving"]


def label_dtype(array: np.ndarray) -> type:
    """The smallest of uint8 / int16 / int32 that holds a label map's values."""
    top = int(array.max()) if array.size else 0
    return np.uint8 if top < 256 else np.int16 if top < 32768 else np.int32


def compact_label(label: Volume) -> Volume:
    """``label`` (non-negative, as :func:`~monai_probreg.spatial.volume_io.read_label` reads it: int32) in
    :func:`label_dtype`, its values unchanged: a registration holds several label maps (the two read, and those
    resampled from them, which keep their type), each a quarter of the size for fewer than 256 labels; their files
    are written in that type anyway."""
    dtype = label_dtype(label.array)
    return label if label.array.dtype == dtype else label.with_array(label.array.astype(dtype))


@dataclass
class FixedSpace:
    """The fixed image prepared once: geometry, model grid, normalised model input; :attr:`itk_image` (for the ITK
    affine backend) and :attr:`points` (for a caller's ``check``) are computed on first use, once."""

    image: Volume
    label: Volume | None
    grid: ModelGrid
    model_input: np.ndarray
    label_ids: list[int] = field(default_factory=list)
    brain_mask: np.ndarray | None = None  # where the moving scan stays visible (monai_probreg.spatial.brain_mask)
    brain_mask_margin_mm: float | None = None  # its margin; None = no mask
    affine_samples: dict[AffineSettings, FixedSamples] = field(default_factory=dict, repr=False)  # samples_for's
    mask: Volume | None = None  # --fixed-mask (bool, the fixed grid): where the metrics look (spatial.masks)

    @functools.cached_property
    def itk_image(self) -> itk.Image:
        return volume_to_itk(self.image)  # loads ITK's core modules (slow): not on the torch backend's path

    def samples_for(self, settings: AffineSettings) -> FixedSamples | None:
        """The torch affine backend's fixed-image samples for ``settings``, made on first use and kept (the same
        for every scan of a batch, so made once); None for the ITK backend."""
        if settings.backend != "torch":
            return None
        if settings not in self.affine_samples:
            self.affine_samples[settings] = fixed_samples(
                self.image, settings, None if self.mask is None else self.mask.array
            )
        return self.affine_samples[settings]

    @functools.cached_property
    def points(self) -> np.ndarray:
        """The fixed grid's LPS voxel centres (*S, 3), float64: not used by the registration itself (every sampling
        goes through :func:`~monai_probreg.spatial.physical.mapped_index`), only by
        :class:`~monai_probreg.registration.scan.Registered`."""
        return grid_points(self.image.shape, self.image.index_to_lps)


def prepare_fixed(
    path: str | os.PathLike,
    label_path: str | os.PathLike | None = None,
    divisor: int = 16,
    brain_mask_margin_mm: float | None = DEFAULT_MARGIN_MM,
    mask_path: str | os.PathLike | None = None,
) -> FixedSpace:
    """``brain_mask_margin_mm``: hide the moving scan outside the fixed image's support dilated by this many mm
    (:mod:`monai_probreg.spatial.brain_mask`); None: show the network the whole moving scan. ``mask_path``: the
    fixed image's cost-function mask (``--fixed-mask``, :mod:`monai_probreg.spatial.masks`), which is also the
    support that margin dilates (in place of the voxels above the image's minimum)."""
    image = read_image(path, "--fixed")
    label = None
    if label_path is not None:
        label = compact_label(read_label(label_path, "--fixed-label"))
        check_same_grid(label, image, "--fixed-label", "--fixed")
    fixed_mask = None if mask_path is None else read_mask(mask_path, "--fixed-mask", image, "--fixed")
    grid = ModelGrid.for_volume(image, divisor)
    ids = [int(v) for v in np.unique(label.array) if v != 0] if label is not None else []
    if brain_mask_margin_mm is None:
        mask = None
    elif fixed_mask is None:
        mask = fixed_brain_mask(image.array, image.spacing, brain_mask_margin_mm)
    else:
        mask = dilated_mask(fixed_mask.array, image.spacing, brain_mask_margin_mm)
    return FixedSpace(
        image,
        label,
        grid,
        grid.to_model(normalise_intensity(image.array)),
        ids,
        mask,
        brain_mask_margin_mm,
        mask=fixed_mask,
    )


class MovingScan(NamedTuple):
    """The scan to register, its label map and its cost-function mask (``--moving-mask``), None each without."""

    image: Volume
    label: Volume | None
    mask: Volume | None


def read_moving(
    path: str | os.PathLike | Volume,
    label_path: str | os.PathLike | None = None,
    mask_path: str | os.PathLike | None = None,
) -> MovingScan:
    """The ``read`` stage: the scan (or a :class:`~monai_probreg.spatial.volume_io.Volume` already in memory, taken
    as it is), its labels on its grid and its mask; InputError (one line) for an unusable file."""
    moving = path if isinstance(path, Volume) else read_image(path, "--moving")
    label = compact_label(read_label(label_path, "--moving-label")) if label_path is not None else None
    if label is not None:
        check_same_grid(label, moving, "--moving-label", "--moving")
    mask = None
    if mask_path is not None:
        mask = read_mask(mask_path, "--moving-mask", moving, "--moving")
    return MovingScan(moving, label, mask)
