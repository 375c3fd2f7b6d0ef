"""The ``affine`` and ``resample`` stages of one registration: the moving scan aligned to the fixed image, then
brought onto the model grid as the network's input.

- ``affine``: rigid + affine registration of the raw moving scan to the fixed image
  (:func:`monai_probreg.spatial.affine.align`: torch by default, or ITK), started from an earlier registration's
  affine or replaced by it (:class:`~monai_probreg.registration.options.InitialTransform`), or the identity without
  the stage; for a pair of two contrasts (or as ``AffineSettings.local_stage`` says, :func:`local_stage_runs`) then
  refined by the squared local correlation (:mod:`monai_probreg.spatial.affine_local`);
- ``resample``: the moving scan onto the fixed grid through the affine (one linear interpolation, the scan's minimum
  outside it and outside the fixed image's brain mask, :mod:`monai_probreg.spatial.brain_mask`), percentile intensity
  scaling to [0, 1] exactly as in training (:mod:`monai_probreg.spatial.intensity`), then onto the model grid
  (:class:`~monai_probreg.spatial.model_grid.ModelGrid`: RAS, padded to the bundle's divisor); the cost-function masks
  come along for the refinement; with ``--match-contrast`` (:func:`matched_input`) its intensities are then mapped
  onto the fixed image's contrast (:mod:`monai_probreg.spatial.contrast`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from monai_probreg.registration.compose import affine_resample
from monai_probreg.registration.inputs import FixedSpace, MovingScan
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.spatial.affine import AffineResult, AffineSettings, align
from monai_probreg.spatial.affine_local import refine_by_local_correlation
from monai_probreg.spatial.brain_mask import hide_outside
from monai_probreg.spatial.contrast import match_contrast
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.masks import MASK_LEVEL
from monai_probreg.spatial.volume_io import Volume
from monai_probreg.utils.errors import InputError

__all__ = ["ModelInput", "affine_stage", "local_stage_runs", "matched_input", "model_input"]


def local_stage_runs(settings: AffineSettings, contrast: str) -> bool:
    """Whether the affine stage ends with the local-correlation step for a pair of ``contrast`` (one of
    :data:`~monai_probreg.registration.options.CONTRASTS`): ``settings.local_stage`` "always", or "other-contrast"
    (the default) and ``contrast == "other"``."""
    return settings.local_stage == "always" or (settings.local_stage == "other-contrast" and contrast == "other")


def affine_stage(fixed: FixedSpace, moving: MovingScan, options: RegistrationOptions) -> AffineResult:
    """The affine, fixed LPS -> moving LPS: ``options.initial`` itself when it is used ``as-affine``, the identity
    without affine settings, else :func:`~monai_probreg.spatial.affine.align`'s (inside the cost-function masks),
    refined by the local squared correlation when :func:`local_stage_runs` (its report appended to the stages)."""
    initial = options.initial
    if initial is not None and initial.use == "as-affine":
        return AffineResult(initial.matrix, initial.center, initial.matrix, [])
    if options.affine is None:
        return AffineResult(np.eye(4), np.zeros(3), np.eye(4), [])
    settings = options.affine
    local = local_stage_runs(settings, options.contrast)
    # with the local step and no initial transform: mutual information from each of its starts (the initializers)
    starts = settings.local_starts if local and initial is None else (settings.initializer,)
    results = []
    for start in starts:
        run = dataclasses.replace(settings, initializer=start)
        results.append(
            align(
                fixed.image,
                moving.image,
                run,
                fixed.itk_image if run.backend == "itk" else None,
                fixed.samples_for(run),
                None if initial is None else initial.matrix,
                fixed.mask,
                moving.mask,
            )
        )
    if not local:
        return results[0]
    refined = refine_by_local_correlation(
        fixed.image,
        moving.image,
        [result.matrix for result in results],
        settings,
        None if fixed.mask is None else fixed.mask.array,
        None if moving.mask is None else moving.mask.array,
    )
    chosen = results[refined.start]
    # the ITK transform, if the backend made one, is the old matrix's: built again from the new one on first use
    return dataclasses.replace(
        chosen, matrix=refined.matrix, stages=[*chosen.stages, refined.report], itk_transform=None
    )


class ModelInput(NamedTuple):
    """The moving scan as the network reads it: ``image`` on the model grid, scaled to [0, 1]; ``masks``: the
    refinement's masks there (fixed, moving; float32 0/1, None each without), or None without any."""

    image: np.ndarray
    masks: tuple[np.ndarray | None, np.ndarray | None] | None


def model_input(fixed: FixedSpace, moving: MovingScan, affine: np.ndarray) -> ModelInput:
    """The ``resample`` stage (module docstring) through ``affine`` (4, 4), fixed LPS -> moving LPS."""
    scan = moving.image
    background = float(scan.array.min())
    moving_on_fixed = affine_resample(scan, fixed.image, affine, background)
    image = fixed.grid.to_model(normalise_intensity(hide_outside(moving_on_fixed, fixed.brain_mask, background)))
    del moving_on_fixed
    return ModelInput(image, _model_grid_masks(fixed, moving.mask, affine))


def matched_input(
    image: np.ndarray,
    fixed_image: np.ndarray,
    masks: tuple[np.ndarray | None, np.ndarray | None] | None,
    num_bins: int,
) -> np.ndarray:
    """``image`` (the moving scan on the model grid, :func:`model_input`'s) in ``fixed_image``'s contrast, counted
    inside the cost-function ``masks`` (:func:`~monai_probreg.spatial.contrast.match_contrast`, ``num_bins`` bins);
    InputError with one line when the two images share too little for a map."""
    inside = None
    for part in masks or ():
        if part is not None:
            inside = part >= MASK_LEVEL if inside is None else inside & (part >= MASK_LEVEL)
    try:
        return match_contrast(image, fixed_image, num_bins, inside)
    except ValueError as err:
        raise InputError(f"--match-contrast: {err}") from None


def _model_grid_masks(
    fixed: FixedSpace, moving_mask: Volume | None, affine: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None] | None:
    """The refinement's masks on the model grid, float32 0/1 (:class:`~monai_probreg.engines.refinement.RefinementMasks`
    as arrays), or None without any: the fixed mask re-indexed (exact; the padding outside), the moving mask carried
    onto the fixed grid through the affine as the scan is (linear, 0 beyond its grid, inside from
    :data:`~monai_probreg.spatial.masks.MASK_LEVEL`)."""
    if fixed.mask is None and moving_mask is None:
        return None
    grid = fixed.grid
    fixed_part = None if fixed.mask is None else grid.to_model(fixed.mask.array.astype(np.float32))
    moving_part = None
    if moving_mask is not None:
        on_fixed = affine_resample(
            moving_mask.with_array(moving_mask.array.astype(np.float32)), fixed.image, affine, 0.0
        )
        moving_part = grid.to_model((on_fixed >= MASK_LEVEL).astype(np.float32))
    return fixed_part, moving_part
