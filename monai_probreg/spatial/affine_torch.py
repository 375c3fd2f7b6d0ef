"""Affine pre-alignment in torch: the same two stages as :mod:`monai_probreg.spatial.affine`'s ITK backend, faster.

Why a second implementation: ITK's v4 registration cost this command most of its time (loading ITK's lazily imported
registration modules, then registering; docs/speed.md, "The command's levers"), and its Mattes metric is only
reproducible in one work unit (ITK pull request #6622). Nothing in MONAI or torch registers two images affinely, and
MONAI's ``GlobalMutualInformationLoss`` is too slow for an optimiser's inner loop
(:func:`mutual_information`), so the loop and the metric are written here; the rest is borrowed: MONAI's
``ScaleIntensityRangePercentiles`` and ``GaussianSmooth``, ``torch.nn.functional.grid_sample`` for interpolation and
``torch.optim.LBFGS``.

The method, stage by stage as ``antsRegistration -t Rigid -t Affine`` (and the ITK backend) runs it:

- **initialisation** (``"moments"``): the intensity centres of mass matched (ITK's ``CenteredTransformInitializer``
  in moments mode); ``"geometry"``: the grid centres; or a given ``initial`` transform (an earlier registration's,
  ``--initial-transform``), which both stages then refine by a map of the fixed space, ``A = initial o S``: what
  ``antsRegistration -r`` does (its composite transform applies the stage's transform to a fixed point first);
- **pyramid**: per level, both images averaged over blocks of about the level's voxel size (the fixed grid's
  times the shrink factor) and smoothed by ``smoothing_sigmas_mm`` (in mm, per axis of each grid);
  ``sampling_percentage`` of the fixed level's voxels are drawn once per level with a seeded generator (``seed``):
  the metric's sample points;
- **rigid** (rotation vector + translation, 6 parameters), then **affine** (12 parameters) from the rigid result;
  L-BFGS with a strong-Wolfe line search (``torch.optim.LBFGS``) on parameters measured in millimetres (a
  rotation or shear is scaled by the fixed image's radius, so one unit moves the brain's edge by about 1 mm, as
  ITK's ``RegistrationParameterScalesFromPhysicalShift`` does); the sample points stay fixed within a level, so
  the line search sees one deterministic function (ITK's backend: conjugate gradient, golden-section search);
- **metric**: negative mutual information of the intensities (each image scaled to [0, 1] between its
  ``LOWER/UPPER_PERCENTILE`` percentiles) at the sample points, moving sampled by trilinear interpolation; a
  sample mapped outside the moving grid sees the moving image's background (0 after scaling);
- **masks** (``--fixed-mask``, ``--moving-mask``; :mod:`monai_probreg.spatial.masks`): the sample points drawn
  inside the fixed mask only (:func:`fixed_samples`), each weighted in the histogram by the moving mask at its mapped
  point (:func:`mutual_information`'s ``weights``); each image's intensity percentiles and centre of mass (the
  ``"moments"`` start) are those of its voxels inside its mask, so that what is left out moves neither.

Deterministic: a seeded sample and torch's CPU kernels (no atomic reductions; the histogram is a ``bincount``)
give the same transform on every run with the same inputs and settings; another thread count changes the matrix
by less than 1e-5 (tested).

The result maps a point of the **fixed** space to the **moving** space (LPS mm), as the ITK backend's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from monai.transforms import GaussianSmooth, ScaleIntensityRangePercentiles
from monai.utils import convert_to_tensor

from monai_probreg.blocks.grid_coords import index_to_grid_matrix
from monai_probreg.blocks.warp import split_grid_sample
from monai_probreg.spatial.affine_settings import AffineResult, AffineSettings, StageReport
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE
from monai_probreg.spatial.volume_io import Volume

__all__ = [
    "FixedSamples",
    "fixed_samples",
    "mutual_information",
    "optimise_levels",
    "pooled_level",
    "register_affine_torch",
    "rotation_matrix",
    "scaled_intensities",
]

LBFGS_HISTORY = 10  # L-BFGS's memory (curvature pairs)
GRADIENT_TOLERANCE = 1e-9  # stop a level when the metric's gradient (per mm) or its change falls below these
CHANGE_TOLERANCE = 1e-12
_TINY = torch.finfo(torch.float64).tiny  # keeps log(0) finite in the histogram
# a coarse pyramid level's block is inside the fixed mask when at least this fraction of its voxels is (the mask's
# majority; a mask smaller than every block falls back to the blocks it touches)
MASK_BLOCK_FRACTION = 0.5


def rotation_matrix(rotation: torch.Tensor) -> torch.Tensor:
    """Rotation vector (3,) in radians -> (3, 3) rotation (Rodrigues' formula, differentiable at 0)."""
    angle_sq = (rotation * rotation).sum()
    angle = torch.sqrt(angle_sq + 1e-24)
    k = torch.zeros(3, 3, dtype=rotation.dtype)
    k = k.index_put((torch.tensor([2, 0, 1]), torch.tensor([1, 2, 0])), rotation)
    k = k - k.T  # the cross-product matrix [r]_x
    # sin(a)/a and (1 - cos(a))/a^2 by their series below 1e-4 rad (exact to float64 there)
    small = angle < 1e-4
    a = torch.where(small, 1 - angle_sq / 6, torch.sin(angle) / angle)
    b = torch.where(small, 0.5 - angle_sq / 24, (1 - torch.cos(angle)) / (angle * angle))
    return torch.eye(3, dtype=rotation.dtype) + a * k + b * (k @ k)


def _cubic_bspline(x: torch.Tensor) -> torch.Tensor:
    """The cubic B-spline kernel at ``x`` (support [-2, 2], sums to 1 over integer shifts)."""
    a = x.abs()
    inner = (4 - 6 * a**2 + 3 * a**3) / 6
    outer = torch.clamp(2 - a, min=0) ** 3 / 6
    return torch.where(a < 1, inner, outer)


def mutual_information(
    moving: torch.Tensor, fixed_bins: torch.Tensor, bins: int, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Mutual information (nats) of moving intensities in [0, 1] (N,) and fixed bin indices (N,), differentiable in
    the moving intensities: a joint histogram with Mattes et al.'s Parzen windows (cubic B-spline for the moving
    image, zero order for the fixed), as ITK's Mattes metric.

    Written here because MONAI's ``GlobalMutualInformationLoss`` weighs every sample against every bin
    (O(N x bins) per evaluation, too slow for an optimiser's inner loop) and a differentiable ``index_add`` into the
    histogram is slower still; here each sample adds to the 4 bins its window covers (``bincount``) and the
    gradient is the exact one, ``dMI/dJ[a, b] = (log p[a, b] - log p_moving[b]) / N`` chained through the window
    weights (each sample's weights sum to 1, so the other terms of dMI/dJ cancel).

    ``weights`` (N,) in [0, 1], no gradient: each sample's share of the histogram (the moving mask at its mapped
    point, :mod:`monai_probreg.spatial.masks`), normalised by their sum W in place of N; None: all 1 (N)."""
    position = 1 + torch.clamp(moving, 0, 1) * (bins - 4)  # in [1, bins - 3]: the 4 bins stay inside
    covered = (torch.floor(position).long() - 1)[:, None] + torch.arange(4)  # (N, 4) moving bins
    weight = _cubic_bspline(position[:, None] - covered.to(position.dtype))  # (N, 4), differentiable
    index = fixed_bins[:, None] * bins + covered
    if weights is not None:  # the samples' shares: no gradient through the mask
        weight = weight * weights.detach().to(weight.dtype)[:, None]
    with torch.no_grad():
        # every sample outside the moving mask: an empty histogram (MI 0, no gradient), not a division by 0
        total = moving.numel() if weights is None else max(float(weights.detach().double().sum()), _TINY)
        joint = (
            torch.bincount(index.reshape(-1), weights=weight.detach().reshape(-1).double(), minlength=bins * bins).view(
                bins, bins
            )
            / total
        )
        log_joint = torch.log(joint + _TINY)
        log_moving = torch.log(joint.sum(dim=0, keepdim=True) + _TINY)
        log_fixed = torch.log(joint.sum(dim=1, keepdim=True) + _TINY)
        value = (joint * (log_joint - log_fixed - log_moving)).sum()
        slope = ((log_joint - log_moving) / total).to(weight.dtype).reshape(-1)
    linear = (slope[index] * weight).sum()  # its gradient is MI's; its value is taken away again
    return value.to(moving.dtype) + linear - linear.detach()


def scaled_intensities(volume: Volume, mask: np.ndarray | None = None) -> torch.Tensor:
    """``volume`` scaled to [0, 1] between its LOWER/UPPER_PERCENTILE percentiles, clipped; with ``mask`` (bool,
    the volume's grid), the percentiles of the voxels inside it: a bright part the mask leaves out (an artefact)
    would otherwise squeeze what the metric compares into a few histogram bins."""
    if mask is not None:
        values = np.asarray(volume.array, np.float32)
        low, high = np.percentile(values[np.asarray(mask, bool)], [LOWER_PERCENTILE, UPPER_PERCENTILE])
        if high > low:
            return torch.from_numpy(np.clip((values - low) / (high - low), 0.0, 1.0).astype(np.float32))
    scale = ScaleIntensityRangePercentiles(
        lower=LOWER_PERCENTILE, upper=UPPER_PERCENTILE, b_min=0.0, b_max=1.0, clip=True
    )
    # plain tensors from here on: MONAI's MetaTensor would track every operation of the optimisation (several times
    # slower)
    return convert_to_tensor(scale(torch.from_numpy(np.asarray(volume.array, np.float32))[None]), track_meta=False)[0]


def _smoothed(image: torch.Tensor, spacing: np.ndarray, sigma_mm: float) -> torch.Tensor:
    if sigma_mm <= 0:
        return image
    sigma_voxels = tuple(float(sigma_mm / s) for s in spacing)
    return convert_to_tensor(GaussianSmooth(sigma=sigma_voxels)(image[None]), track_meta=False)[0]


def _centre(scaled: torch.Tensor, index_to_lps: np.ndarray, moments: bool) -> np.ndarray:
    """LPS centre of mass of the intensities scaled to [0, 1] (moments: the same for any intensity units, negative
    ones included), or of the grid (geometry, also when the scaled image is all 0)."""
    weights = scaled.double().numpy()
    total = weights.sum()
    if moments and total > 0:
        index = np.array(
            [
                (weights.sum(axis=tuple(a for a in range(3) if a != axis)) * np.arange(weights.shape[axis])).sum()
                / total
                for axis in range(3)
            ]
        )
    else:
        index = (np.asarray(weights.shape, np.float64) - 1) / 2
    return index_to_lps[:3, :3] @ index + index_to_lps[:3, 3]


def pooled_level(
    image: torch.Tensor, index_to_lps: np.ndarray, factors: tuple[int, ...], sigma_mm: float
) -> tuple[torch.Tensor, np.ndarray]:
    """``image`` averaged over blocks of ``factors`` voxels, then smoothed by ``sigma_mm``; with the pooled grid's
    (4, 4) index -> LPS (a block's centre: old index ``f * i + (f - 1) / 2``)."""
    pooled = F.avg_pool3d(image[None, None], kernel_size=factors, stride=factors)[0, 0] if max(factors) > 1 else image
    block = np.eye(4)
    block[:3, :3] = np.diag(factors)
    block[:3, 3] = (np.asarray(factors, np.float64) - 1) / 2
    grid = np.asarray(index_to_lps, np.float64) @ block
    return _smoothed(pooled, np.linalg.norm(grid[:3, :3], axis=0), sigma_mm), grid


class FixedSamples(NamedTuple):
    """The fixed image's part of the metric, the same for every moving scan (so a batch prepares it once,
    :func:`fixed_samples`): its centre (the initializer's) and, per pyramid level, the sample points (N, 3) LPS,
    their fixed bins (N,) and the level's voxel size in mm."""

    centre: torch.Tensor
    points: list[torch.Tensor]
    bins: list[torch.Tensor]
    level_mm: list[float]


def fixed_samples(fixed: Volume, settings: AffineSettings, mask: np.ndarray | None = None) -> FixedSamples:
    """Per level of ``settings``: the fixed image averaged over blocks of ``shrink`` voxels and smoothed by
    ``sigma_mm``; ``sampling_percentage`` of its voxels (at most ``max_samples``) drawn by a generator seeded with
    ``settings.seed``, and the bin of each (zero-order window, as Mattes et al. and ITK).

    ``mask`` (the fixed grid's shape, bool; ``--fixed-mask``): the points are drawn among the level's blocks inside
    it (at least :data:`MASK_BLOCK_FRACTION` of the block's voxels; the full-resolution level: the mask's voxels),
    ``sampling_percentage`` of those (the density of the unmasked metric, where ITK samples the whole grid and drops
    the points outside). None: the whole grid, as before masks existed (the same points)."""
    generator = torch.Generator().manual_seed(int(settings.seed))
    image = scaled_intensities(fixed, mask)
    inside = None if mask is None else torch.from_numpy(np.asarray(mask, dtype=np.float32))
    # the moments of what the metric sees: a bright part the mask leaves out would move the start towards it
    moments = image if inside is None else image * inside
    centre = torch.from_numpy(_centre(moments, fixed.index_to_lps, settings.initializer == "moments"))
    samples = FixedSamples(centre, [], [], [])
    bins = settings.histogram_bins
    for shrink, sigma in zip(settings.shrink_factors, settings.smoothing_sigmas_mm):
        level, grid = pooled_level(image, fixed.index_to_lps, (int(shrink),) * 3, float(sigma))
        values = level.reshape(-1)
        candidates = None
        if inside is not None:
            fraction = pooled_level(inside, fixed.index_to_lps, (int(shrink),) * 3, 0.0)[0].reshape(-1)
            candidates = torch.nonzero(fraction >= MASK_BLOCK_FRACTION).view(-1)
            if candidates.numel() == 0:
                candidates = torch.nonzero(fraction > 0).view(-1)
        available = values.numel() if candidates is None else candidates.numel()
        count = max(1, round(settings.sampling_percentage * available))
        count = count if settings.max_samples is None else min(count, settings.max_samples)
        chosen = torch.randperm(available, generator=generator)[:count]
        if candidates is not None:
            chosen = candidates[chosen]
        index = torch.stack(torch.unravel_index(chosen, level.shape), dim=-1).to(torch.float64)
        g = torch.from_numpy(grid)
        samples.points.append(index @ g[:3, :3].T + g[:3, 3])
        samples.bins.append(torch.clamp((values[chosen] * (bins - 1)).round().long(), 0, bins - 1))
        samples.level_mm.append(int(shrink) * float(np.mean(fixed.spacing)))
    return samples


class _Level:
    """The metric at one pyramid level: the fixed sample points and their bins (:func:`fixed_samples`), the moving
    image averaged over blocks of about the level's voxel size (ITK's registration shrinks both images too) and
    smoothed by ``sigma_mm``."""

    def __init__(
        self,
        points: torch.Tensor,
        fixed_bins: torch.Tensor,
        level_mm: float,
        moving: Volume,
        moving_image: torch.Tensor,
        sigma_mm: float,
        bins: int,
        moving_mask: torch.Tensor | None = None,
    ) -> None:
        factors = tuple(max(1, int(level_mm // s)) for s in moving.spacing)
        moving_level, moving_grid = pooled_level(moving_image, moving.index_to_lps, factors, sigma_mm)
        self.points, self.fixed_bins = points, fixed_bins
        self.moving = moving_level[None, None]
        # the moving mask on the same blocks (the fraction of each inside; not smoothed): sampled with the image
        self.moving_mask = None
        if moving_mask is not None:
            self.moving_mask = pooled_level(moving_mask, moving.index_to_lps, factors, 0.0)[0][None, None]
        lps_to_index = torch.from_numpy(np.linalg.inv(moving_grid))
        # LPS -> grid_sample's normalised coordinates, in its (x, y, z) order (blocks.grid_coords)
        self.lps_to_normalised = index_to_grid_matrix([int(n) for n in moving_level.shape]) @ lps_to_index
        self.bins = bins

    def loss(self, matrix: torch.Tensor) -> torch.Tensor:
        """Negative MI with the moving image sampled at ``matrix`` (4, 4, fixed -> moving) of the points."""
        full = self.lps_to_normalised @ matrix
        normalised = self.points @ full[:3, :3].T + full[:3, 3]
        grid = normalised.to(torch.float32).view(1, -1, 1, 1, 3)  # already in grid_sample's (x, y, z) order
        # over the CPU threads (one grid_sample call runs a single item on one thread); the same samples
        sampled = split_grid_sample(self.moving, grid, mode="bilinear", padding_mode="zeros")
        if self.moving_mask is None:
            return -mutual_information(sampled.view(-1), self.fixed_bins, self.bins)
        # the moving mask at the same points, linearly (0 beyond the moving grid): each sample's share of the
        # histogram, 0 outside the mask, 1 inside, between across its edge, so the metric stays continuous for the
        # line search where ITK's dropping of the points outside would jump; no gradient through it
        with torch.no_grad():
            weights = split_grid_sample(self.moving_mask, grid.detach(), mode="bilinear", padding_mode="zeros")
        return -mutual_information(sampled.view(-1), self.fixed_bins, self.bins, weights.view(-1))


def optimise_levels(
    levels: Sequence[_Level],
    iterations: tuple[int, ...],
    parameters: torch.Tensor,
    to_matrix: Callable[[torch.Tensor], torch.Tensor],
) -> tuple[float, list[int]]:
    """L-BFGS with a strong-Wolfe line search on ``parameters`` (mm), level by level (at most ``iterations[l]``
    iterations; the sample points are fixed within a level, so the metric is a deterministic function there): any
    ``levels`` with a ``loss(matrix)`` (also :mod:`monai_probreg.spatial.affine_local`'s). Returns the last metric
    value and the iterations run per level."""
    value, done = float("nan"), []
    for level, count in zip(levels, iterations):
        if count == 0:
            done.append(0)
            continue
        optimizer = torch.optim.LBFGS(
            [parameters],
            lr=1.0,
            max_iter=int(count),
            history_size=LBFGS_HISTORY,
            line_search_fn="strong_wolfe",
            tolerance_grad=GRADIENT_TOLERANCE,
            tolerance_change=CHANGE_TOLERANCE,
        )

        def closure(optimizer: torch.optim.LBFGS = optimizer, level: _Level = level) -> torch.Tensor:
            optimizer.zero_grad(set_to_none=True)
            loss = level.loss(to_matrix(parameters))
            loss.backward()
            return loss

        value = float(optimizer.step(closure).detach())
        done.append(int(optimizer.state[parameters]["n_iter"]))
    return value, done


def register_affine_torch(
    fixed: Volume,
    moving: Volume,
    settings: AffineSettings,
    samples: FixedSamples | None = None,
    initial: np.ndarray | None = None,
    fixed_mask: np.ndarray | None = None,
    moving_mask: np.ndarray | None = None,
) -> AffineResult:
    """Rigid then affine registration of ``moving`` to ``fixed`` (module docstring). Returns the fixed -> moving
    transform; the ITK transform in the result is an ``AffineTransform`` centred on the fixed image's centre.
    ``samples``: :func:`fixed_samples` of ``fixed``, ``settings`` and ``fixed_mask`` when the caller has them (a
    batch), else made. ``initial`` (4, 4), fixed LPS -> moving LPS: start from it instead of the centres (module
    docstring). ``fixed_mask``, ``moving_mask``: bool arrays on each image's grid, or None
    (:mod:`monai_probreg.spatial.masks`): the sample points drawn inside the first, weighted by the second."""
    samples = samples if samples is not None else fixed_samples(fixed, settings, fixed_mask)
    fixed_centre = samples.centre
    moving_image = scaled_intensities(moving, moving_mask)
    moving_inside = None if moving_mask is None else torch.from_numpy(np.asarray(moving_mask, dtype=np.float32))
    radius = float(np.mean(np.asarray(fixed.shape) * fixed.spacing)) / 2  # mm: 1 unit of rotation = 1 mm there
    levels = [
        _Level(points, bins, level_mm, moving, moving_image, float(sigma), settings.histogram_bins, moving_inside)
        for points, bins, level_mm, sigma in zip(
            samples.points, samples.bins, samples.level_mm, settings.smoothing_sigmas_mm
        )
    ]

    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)
    if initial is None:
        moments = moving_image if moving_inside is None else moving_image * moving_inside  # as the fixed centre's
        moving_centre = torch.from_numpy(_centre(moments, moving.index_to_lps, settings.initializer == "moments"))

        def matrix_of(linear: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
            # A(p) = L (p - c_fixed) + c_moving + t
            top = torch.cat([linear, (moving_centre + translation - linear @ fixed_centre)[:, None]], dim=1)
            return torch.cat([top, bottom], dim=0)

    else:
        start = torch.from_numpy(np.asarray(initial, dtype=np.float64).copy())

        def matrix_of(linear: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
            # A(p) = initial(L (p - c_fixed) + c_fixed + t): the same parameters, a map of the fixed space composed
            # before the initial transform (the identity at 0, so the stages start exactly at it)
            top = torch.cat([linear, (fixed_centre + translation - linear @ fixed_centre)[:, None]], dim=1)
            return start @ torch.cat([top, bottom], dim=0)

    def rigid_matrix(p: torch.Tensor) -> torch.Tensor:
        return matrix_of(rotation_matrix(p[:3] / radius), p[3:])

    rigid = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    initial = rigid_matrix(rigid).detach().numpy()
    stages = [_stage("rigid", levels, settings.rigid_iterations, rigid, rigid_matrix)]
    result = rigid_matrix(rigid).detach()
    if not settings.rigid_only:
        with torch.no_grad():
            rotation, shift = rotation_matrix(rigid[:3] / radius), rigid[3:].clone()

        def affine_matrix(p: torch.Tensor) -> torch.Tensor:
            return matrix_of(rotation + p[:9].view(3, 3) / radius, shift + p[9:])

        affine = torch.zeros(12, dtype=torch.float64, requires_grad=True)
        stages.append(_stage("affine", levels, settings.affine_iterations, affine, affine_matrix))
        result = affine_matrix(affine).detach()
    matrix = result.numpy()
    if not np.isfinite(matrix).all():
        raise RuntimeError(
            f"the torch affine registration diverged (non-finite matrix); settings {settings}. "
            "Try --affine-backend itk, or report the scan"
        )
    return AffineResult(matrix, fixed_centre.numpy(), initial, stages)


def _stage(
    name: str,
    levels: list[_Level],
    iterations: tuple[int, ...],
    parameters: torch.Tensor,
    to_matrix: Callable[[torch.Tensor], torch.Tensor],
) -> StageReport:
    value, done = optimise_levels(levels, iterations, parameters, to_matrix)
    return StageReport(name, done, value, f"torch backend: L-BFGS, at most {list(iterations)} iterations per level")
