"""Is the predicted uncertainty worth anything? Calibration metrics for per-voxel Gaussian predictions.

Every function takes a predicted standard deviation ``std`` and an observed ``error`` (prediction minus truth) of
the same shape, any shape, compared element-wise (e.g. one element per voxel and displacement component), and
reads them as the claim ``error ~ N(0, std^2)`` (or, for the intervals, ``error / std`` Student-t with ``dof``
degrees of freedom: a Gaussian whose variance is itself uncertain, heavier-tailed; ``dof=None`` is the Gaussian):

- :func:`interval_coverage`: the fraction of elements with ``|error| <= z_p * std``, z_p the two-sided quantile of
  nominal level p (:func:`interval_z`; Gaussian: 68% -> 0.994, 95% -> 1.960); calibrated = coverage ~ p.
- :func:`reliability_bins`: elements grouped into bins of predicted std; per bin the RMS predicted std and the RMS
  observed error (calibrated = equal; this is the reliability diagram).
- :func:`uncertainty_calibration_error` (UCE, Laves et al. 2020): bin-weighted mean of |RMS error - RMS std|, in
  the units of ``std``; 0 when calibrated. Bins hold equal counts by default (``binning="quantile"``): the std
  of registration posteriors is heavy-tailed, and equal-width bins would put almost every voxel in the first one.
- :func:`spearman`: rank correlation between std and |error| (does a larger std flag a larger error?).
- :func:`auroc`: area under the ROC curve of a score for a binary outcome (e.g. label entropy for "wrongly
  labelled"), ties counted half, through scipy's Mann-Whitney U statistic.

Written here (a thin layer over scipy): no library offers these for dense registration posteriors.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import numpy as np
import torch
from scipy import stats
from torch import Tensor

__all__ = [
    "gaussian_interval_z",
    "interval_z",
    "interval_coverage",
    "ReliabilityBins",
    "reliability_bins",
    "uncertainty_calibration_error",
    "spearman",
    "auroc",
]

ArrayLike = Tensor | np.ndarray


def _flat(name: str, values: ArrayLike) -> np.ndarray:
    array = values.detach().cpu().double().numpy() if isinstance(values, Tensor) else np.asarray(values, np.float64)
    array = array.reshape(-1)
    if array.size == 0:
        raise ValueError(f"{name} is empty; expected at least one element")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite; got {int((~np.isfinite(array)).sum())} non-finite elements")
    return array


def _pair(std: ArrayLike, error: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    if tuple(std.shape) != tuple(error.shape):
        raise ValueError(f"std and error must have the same shape; got {tuple(std.shape)} and {tuple(error.shape)}")
    s, e = _flat("std", std), _flat("error", error)
    if (s < 0).any():
        raise ValueError(f"std must be >= 0; got minimum {s.min()}")
    return s, e


def gaussian_interval_z(level: float) -> float:
    """Half-width, in standard deviations, of the central Gaussian interval holding ``level`` (0 < level < 1)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1); got {level}")
    return math.sqrt(2.0) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()


def interval_z(level: float, dof: float | None = None) -> float:
    """Half-width, in units of ``std``, of the central interval holding ``level``: Gaussian (``dof`` None) or
    Student-t with ``dof`` > 0 degrees of freedom (scipy's quantile; 1 dof is the Cauchy: tan(pi level / 2))."""
    if dof is None:
        return gaussian_interval_z(level)
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1); got {level}")
    if not (math.isfinite(dof) and dof > 0):
        raise ValueError(f"dof must be a positive finite number or None (Gaussian); got {dof}")
    return float(stats.t.ppf(0.5 + level / 2.0, dof))


def interval_coverage(std: ArrayLike, error: ArrayLike, level: float, dof: float | None = None) -> float:
    """Fraction of elements with ``|error| <= interval_z(level, dof) * std``: the empirical coverage of the nominal
    interval (``dof`` None: Gaussian)."""
    s, e = _pair(std, error)
    return float(np.mean(np.abs(e) <= interval_z(level, dof) * s))


class ReliabilityBins(NamedTuple):
    """Per bin of predicted std (arrays of length num_bins; empty bins are dropped):
    ``rms_std`` predicted, ``rms_error`` observed, ``count`` elements, ``edges`` the bins' std bounds (num_bins + 1)."""

    rms_std: np.ndarray
    rms_error: np.ndarray
    count: np.ndarray
    edges: np.ndarray


def reliability_bins(
    std: ArrayLike, error: ArrayLike, num_bins: int = 15, binning: Literal["quantile", "uniform"] = "quantile"
) -> ReliabilityBins:
    """Group elements by predicted std into ``num_bins`` bins (equal counts, or equal widths over [min, max])."""
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1; got {num_bins}")
    s, e = _pair(std, error)
    if binning == "quantile":
        edges = np.quantile(s, np.linspace(0.0, 1.0, num_bins + 1))
    elif binning == "uniform":
        edges = np.linspace(s.min(), s.max(), num_bins + 1)
    else:
        raise ValueError(f"binning must be 'quantile' or 'uniform'; got {binning!r}")
    index = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, num_bins - 1)
    count = np.bincount(index, minlength=num_bins)
    mean_sq_std = np.bincount(index, weights=s**2, minlength=num_bins) / np.maximum(count, 1)
    mean_sq_err = np.bincount(index, weights=e**2, minlength=num_bins) / np.maximum(count, 1)
    keep = count > 0
    return ReliabilityBins(np.sqrt(mean_sq_std[keep]), np.sqrt(mean_sq_err[keep]), count[keep], edges)


def uncertainty_calibration_error(
    std: ArrayLike, error: ArrayLike, num_bins: int = 15, binning: Literal["quantile", "uniform"] = "quantile"
) -> float:
    """UCE = sum_b (n_b / N) |RMS error_b - RMS std_b|, in the units of ``std``."""
    bins = reliability_bins(std, error, num_bins, binning)
    return float(np.sum(bins.count * np.abs(bins.rms_error - bins.rms_std)) / np.sum(bins.count))


def spearman(x: ArrayLike, y: ArrayLike) -> float:
    """Spearman rank correlation of two same-shaped arrays (average ranks for ties)."""
    if tuple(x.shape) != tuple(y.shape):
        raise ValueError(f"x and y must have the same shape; got {tuple(x.shape)} and {tuple(y.shape)}")
    return float(stats.spearmanr(_flat("x", x), _flat("y", y)).statistic)


def auroc(score: ArrayLike, outcome: ArrayLike) -> float:
    """P(score of a positive > score of a negative) + 1/2 P(equal); ``outcome`` is boolean (or 0/1), both classes
    must occur."""
    if tuple(score.shape) != tuple(outcome.shape):
        raise ValueError(
            f"score and outcome must have the same shape; got {tuple(score.shape)} and {tuple(outcome.shape)}"
        )
    s = _flat("score", score)
    o = _flat("outcome", outcome)
    if not np.isin(o, (0.0, 1.0)).all():
        raise ValueError("outcome must be boolean or 0/1")
    positives, negatives = s[o == 1], s[o == 0]
    if positives.size == 0 or negatives.size == 0:
        raise ValueError(f"outcome needs both classes; got {positives.size} positives and {negatives.size} negatives")
    u = stats.mannwhitneyu(positives, negatives, alternative="two-sided", method="asymptotic").statistic
    return float(u / (positives.size * negatives.size))
