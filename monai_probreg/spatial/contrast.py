"""A second contrast made the first one's: the moving image's intensities mapped onto the fixed image's contrast.

``register --contrast other --match-contrast`` (a skull-stripped T2-weighted or FLAIR brain onto a T1-weighted atlas)
feeds the network, its refinement and the quality estimate the moving image with every intensity replaced by the mean
fixed intensity of the voxels that have it, after the affine stage: the conditional mean ``E[fixed | moving]`` read
off the pair's joint histogram, the least-squares map from one image's intensities to the other's (Guimond, Roche,
Ayache and Meunier, "Three-dimensional multimodal brain warping using the demons algorithm and adaptive intensity
corrections", IEEE TMI 2001). The network was trained on pairs of one contrast; after the map, a pair of two is one,
and its local correlation sees what it was fitted to. The files written are the original scan resampled.

Written by hand: histogram matching (ITK's ``HistogramMatchingImageFilter``, ANTs' ``--use-histogram-matching``,
scikit-image's ``match_histograms``) and MONAI's histogram equalisation (``HistogramNormalize``) are monotone and
cannot turn white matter dark into white matter bright; no library of ours offers the conditional mean.

The affine stage leaves the pair a few millimetres apart, so the map averages over tissue boundaries; the bins of
fluid, grey and white matter each hold many thousands of voxels and their means stand. Where tissues of different
fixed intensities share a moving intensity (skin, fat and bone of a whole head against brain tissue), one mean mixes
them: on whole heads the map lowered Dice (docs/accuracy.md), hence an option for brains. Where a bin has fewer than
``min_count`` voxels its value is interpolated linearly from the nearest bins that have enough.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["CONTRAST_MATCH_MIN_COUNT", "check_contrast_match_bins", "match_contrast"]

CONTRAST_MATCH_MIN_COUNT = 20  # voxels a bin needs for its own mean (else interpolated from its neighbours)


def check_contrast_match_bins(value: object) -> int:
    """``value`` as a number of bins for the map: 0 (no map) or an integer >= 2 (a bool, a float or a string is not);
    ValueError otherwise. The one rule for the command's options and the config's ``contrast_match_bins``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value == 1 or value < 0:
        raise ValueError(f"contrast_match_bins must be 0 (none) or an integer >= 2; got {value!r}")
    return int(value)


def match_contrast(
    moving: np.ndarray,
    fixed: np.ndarray,
    num_bins: int,
    inside: np.ndarray | None = None,
    min_count: int = CONTRAST_MATCH_MIN_COUNT,
) -> np.ndarray:
    """``moving`` with each intensity replaced by the mean ``fixed`` intensity of its bin (module docstring).

    ``moving``, ``fixed``: one grid, intensities in [0, 1] (the network's input scale,
    :func:`~monai_probreg.spatial.intensity.normalise_intensity`), any shape; ``num_bins`` equal bins of [0, 1] of the
    moving intensity; the map is piecewise linear between the bins' centres, constant beyond the first and last.
    Counted: the voxels where either image is above 0 (the background both share says nothing of the contrast),
    and inside ``inside`` (bool, same shape: the cost-function masks) when given. The moving image's 0 stays 0
    (its background). float32 out. ValueError for shapes that differ, ``num_bins`` < 2, or fewer than two bins
    with ``min_count`` voxels (no map to read: the images share too little)."""
    moving, fixed = np.asarray(moving), np.asarray(fixed)
    if moving.shape != fixed.shape:
        raise ValueError(f"moving and fixed must be on one grid; got shapes {moving.shape} and {fixed.shape}")
    if inside is not None and np.shape(inside) != moving.shape:
        raise ValueError(f"inside must have the images' shape {moving.shape}; got {np.shape(inside)}")
    if int(num_bins) != num_bins or num_bins < 2:
        raise ValueError(f"num_bins must be an integer >= 2; got {num_bins!r}")
    num_bins = int(num_bins)
    # in torch: multi-threaded, the model grid's millions of voxels in a few passes (numpy's interp is one thread)
    m = torch.from_numpy(np.ascontiguousarray(moving, dtype=np.float32)).reshape(-1)
    f = torch.from_numpy(np.ascontiguousarray(fixed, dtype=np.float32)).reshape(-1)
    counted = (m > 0) | (f > 0)
    if inside is not None:
        counted &= torch.from_numpy(np.ascontiguousarray(inside, dtype=bool)).reshape(-1)
    # the voxels that do not count go to one more bin, dropped (cheaper than selecting the others)
    bins = torch.where(counted, (m * num_bins).long().clamp_(0, num_bins - 1), num_bins)
    counts = torch.bincount(bins, minlength=num_bins + 1)[:num_bins].double()
    sums = torch.bincount(bins, weights=f.double(), minlength=num_bins + 1)[:num_bins]
    kept = (counts >= min_count).numpy()
    if kept.sum() < 2:
        raise ValueError(
            f"expected at least 2 intensity bins with {min_count} voxels where the images overlap; got "
            f"{int(kept.sum())}: the two images share too little to map one contrast onto the other"
        )
    centres = (np.arange(num_bins) + 0.5) / num_bins
    means = np.interp(centres, centres[kept], (sums / counts.clamp_min(1)).numpy()[kept])
    # linear between the bins' centres, constant beyond the first and last: value at position t = m * bins - 0.5
    position = (m * num_bins - 0.5).clamp_(0, num_bins - 1)
    lower = position.floor().long().clamp_(max=num_bins - 2)
    weight = position - lower
    table = torch.from_numpy(means).float()
    out = table[lower] * (1 - weight) + table[lower + 1] * weight
    out[m <= 0] = 0.0
    return out.reshape(np.shape(moving)).numpy()
