"""The affine stage's last step for a pair of two contrasts: the affine found by mutual information, refined by the
local squared correlation (``AffineSettings.local_stage``; :func:`refine_by_local_correlation`).

Why: mutual information over the fixed grid can prefer a wrong answer when a head of one contrast meets a
skull-stripped brain of another. A T2-weighted head (bright fluid and fat, dark bone) shrunk into a T1-weighted brain
pairs the brain's empty background with the air around the head, and on renderings of SynthSeg's label maps that
scored higher than the right alignment (measured in docs/accuracy.md, "Another contrast"). The squared local correlation (the deformable refinement's own image term, MONAI's local
normalised cross-correlation; ANTs' ``CC`` metric) reads each window on its own: an edge must sit on an edge of
either sign, so inverted tissue contrast still matches, and what lies outside the fixed image's support does not
count.

The method:

- **start**: the mutual-information stages' result ``A_mi`` (either backend), run from each of
  ``local_starts`` (the initializers: centres of mass and grid centres; a start far off can end in the shrunken
  head), the one with the lowest loss at the first level kept; the parameters are a map ``S`` of the fixed
  space composed before it, ``A = A_mi o S``, the identity at 0: 12 parameters in mm (the linear part scaled by
  the fixed image's radius, as :mod:`monai_probreg.spatial.affine_torch`'s);
- **levels** (``local_levels_mm``, coarse to fine): both images scaled to [0, 1] between their intensity
  percentiles (the MI stages' scaling, their masks' voxels) and averaged over blocks of about the level's voxel
  size, smoothed by half of it; every fixed level voxel is a point, the moving image sampled at its mapped
  position (trilinear, 0 outside);
- **loss**: minus the squared local correlation in windows of ``local_kernels`` level voxels
  (:class:`~monai_probreg.losses.lncc.BoxLNCCLoss`), averaged over the fixed image's support (its voxels above its
  minimum, or the fixed mask) widened by half a window, each point weighted by the moving mask at its mapped
  position when there is one;
- **optimiser**: L-BFGS with a strong-Wolfe line search, at most ``local_iterations`` per level.

Written here: ITK's ``ANTSNeighborhoodCorrelationImageToImageMetricv4`` would do the same through the v4
framework that the torch backend replaces for speed (docs/speed.md), and neither MONAI nor torch registers
affinely.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from monai_probreg.blocks.grid_coords import index_to_grid_matrix
from monai_probreg.blocks.warp import split_grid_sample
from monai_probreg.losses.lncc import BoxLNCCLoss
from monai_probreg.spatial.affine_settings import AffineSettings, StageReport
from monai_probreg.spatial.affine_torch import optimise_levels, pooled_level, scaled_intensities
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.volume_io import Volume

__all__ = ["LocalResult", "refine_by_local_correlation"]

MASK_LEVEL = 0.5  # a level voxel (a block of fixed voxels) is inside the support when at least half of it is


class _Level:
    """The loss at one level: the fixed points, the fixed level image and where the loss counts, and the moving
    level image in grid_sample's normalised coordinates."""

    def __init__(
        self,
        fixed: Volume,
        fixed_image: torch.Tensor,
        support: torch.Tensor,
        moving: Volume,
        moving_image: torch.Tensor,
        moving_mask: torch.Tensor | None,
        level_mm: float,
        kernel: int,
    ) -> None:
        fixed_factors = tuple(max(1, round(level_mm / s)) for s in fixed.spacing)
        level, grid = pooled_level(fixed_image, fixed.index_to_lps, fixed_factors, level_mm / 2)
        self.fixed = level[None, None]
        self.shape = tuple(int(n) for n in level.shape)
        inside = pooled_level(support, fixed.index_to_lps, fixed_factors, 0.0)[0] >= MASK_LEVEL
        # widened by half a window: the windows astride the support's edge count (their edge is the evidence)
        self.inside = F.max_pool3d(inside[None, None].float(), kernel, stride=1, padding=kernel // 2)[0, 0] > 0
        self.points = torch.from_numpy(grid_points(self.shape, grid).reshape(-1, 3))  # every level voxel, LPS
        moving_factors = tuple(max(1, round(level_mm / s)) for s in moving.spacing)
        moving_level, moving_grid = pooled_level(moving_image, moving.index_to_lps, moving_factors, level_mm / 2)
        self.moving = moving_level[None, None]
        self.moving_mask = None
        if moving_mask is not None:
            self.moving_mask = pooled_level(moving_mask, moving.index_to_lps, moving_factors, 0.0)[0][None, None]
        # LPS -> grid_sample's normalised coordinates, in its (x, y, z) order (blocks.grid_coords)
        self.lps_to_normalised = index_to_grid_matrix(list(moving_level.shape)) @ torch.from_numpy(
            np.linalg.inv(moving_grid)
        )
        self.similarity = BoxLNCCLoss(spatial_dims=3, kernel_size=kernel, reduction="none")

    def loss(self, matrix: torch.Tensor) -> torch.Tensor:
        """Minus the mean squared local correlation where it counts, the moving image at ``matrix`` (fixed -> moving)
        of the points."""
        full = self.lps_to_normalised @ matrix
        grid = (self.points @ full[:3, :3].T + full[:3, 3]).to(torch.float32).view(1, *self.shape, 3)
        warped = split_grid_sample(self.moving, grid, mode="bilinear", padding_mode="zeros")
        similarity = self.similarity(warped, self.fixed)[0, 0]
        if self.moving_mask is None:
            return similarity[self.inside].mean()
        # each point weighted by the moving mask at its mapped position (linear, no gradient through it): continuous
        # for the line search where dropping the points outside would jump (as the MI stages' histogram weights)
        with torch.no_grad():
            weights = split_grid_sample(self.moving_mask, grid, mode="bilinear", padding_mode="zeros")[0, 0]
            weights = weights * self.inside
            total = weights.sum()
        if float(total) == 0.0:  # everything mapped outside the moving mask: nothing to compare
            return warped.sum() * 0.0
        return (similarity * weights).sum() / total


class LocalResult(NamedTuple):
    """``matrix``: the refined affine (4, 4, fixed LPS -> moving LPS); ``start``: the index of the candidate it
    started from; ``report``: the stage's (its ``metric``: the last level's loss, minus the mean squared local
    correlation)."""

    matrix: np.ndarray
    start: int
    report: StageReport


def refine_by_local_correlation(
    fixed: Volume,
    moving: Volume,
    candidates: Sequence[np.ndarray],
    settings: AffineSettings,
    fixed_mask: np.ndarray | None = None,
    moving_mask: np.ndarray | None = None,
) -> LocalResult:
    """The best of ``candidates`` (each (4, 4), fixed LPS -> moving LPS: mutual information's results from several
    starts), refined by the module's method over ``settings``' ``local_*`` levels: the one with the lowest loss at
    the first level is refined. ``fixed_mask``, ``moving_mask``: bool arrays on each image's grid, or None."""
    if len(candidates) == 0:
        raise ValueError("expected at least one affine to refine, got none")
    fixed_image = scaled_intensities(fixed, fixed_mask)
    support = torch.from_numpy(
        np.asarray(fixed.array > fixed.array.min() if fixed_mask is None else fixed_mask, dtype=np.float32)
    )
    moving_image = scaled_intensities(moving, moving_mask)
    moving_inside = None if moving_mask is None else torch.from_numpy(np.asarray(moving_mask, dtype=np.float32))
    levels = [
        _Level(fixed, fixed_image, support, moving, moving_image, moving_inside, float(mm), int(kernel))
        for mm, kernel in zip(settings.local_levels_mm, settings.local_kernels)
    ]
    chosen = 0
    if len(candidates) > 1:  # the start: the candidate the first level scores best (the others are dropped)
        with torch.no_grad():
            losses = [float(levels[0].loss(torch.from_numpy(np.asarray(c, np.float64)))) for c in candidates]
        chosen = int(np.argmin(losses))
    start = torch.from_numpy(np.asarray(candidates[chosen], dtype=np.float64).copy())
    index_centre = (np.asarray(fixed.shape, np.float64) - 1) / 2
    centre = torch.from_numpy(fixed.index_to_lps[:3, :3] @ index_centre + fixed.index_to_lps[:3, 3])
    radius = float(np.mean(np.asarray(fixed.shape) * fixed.spacing)) / 2  # mm: 1 unit of shear = 1 mm there
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)

    def matrix_of(p: torch.Tensor) -> torch.Tensor:
        # A = A_mi o S, S(x) = L (x - c) + c + t with L = I + p[:9] / radius: the identity at 0
        linear = torch.eye(3, dtype=torch.float64) + p[:9].view(3, 3) / radius
        top = torch.cat([linear, (centre + p[9:] - linear @ centre)[:, None]], dim=1)
        return start @ torch.cat([top, bottom], dim=0)

    parameters = torch.zeros(12, dtype=torch.float64, requires_grad=True)
    value, done = optimise_levels(levels, settings.local_iterations, parameters, matrix_of)
    refined = matrix_of(parameters).detach().numpy()
    if not np.isfinite(refined).all():
        raise RuntimeError(f"the local-correlation affine stage diverged (non-finite matrix); settings {settings}")
    report = StageReport(
        "local correlation",
        done,
        value,
        f"L-BFGS on the squared local correlation, at most {list(settings.local_iterations)} iterations per level, "
        f"from start {chosen} of {len(candidates)}",
    )
    return LocalResult(refined, chosen, report)
