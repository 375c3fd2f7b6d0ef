"""How the label entropy's posterior samples are drawn from the calibrated posterior.

The calibrated posterior (:mod:`monai_probreg.uncertainty.calibration`) is described to first order by the
displacement std map (:mod:`monai_probreg.uncertainty.spread`) and by Student-t intervals with the calibration's
``interval_dof``. The label entropy reads K samples of it; two rules make those samples that posterior:

- their velocity std is the calibrated one widened by ``sample_gain`` (:func:`sample_log_var`): the integration damps
  independent per-voxel noise, and the gain, fitted by the refit, makes the samples' displacement variance match the
  map's on average;
- they are Student-t, as the intervals are (:func:`sample_scales`): the multivariate t with ``interval_dof`` degrees of
  freedom as a Gaussian scale mixture, z_k = mean + w_k sigma eps_k with w_k^2 = dof / chi^2_dof, one w_k for the
  whole field of sample k. Its one-dimensional scale is integrated by K equal-probability strata, each sample at its
  stratum's middle quantile, so the K scales are the same for every seed (only the Gaussian part is drawn): at
  K = 16 and 3 dof they run from 3.4 down to 0.58 times the Gaussian sample's spread.
  ``interval_dof`` None (Gaussian intervals): every w_k is 1.

The gain is fitted for Gaussian samples (w = 1); the t's wide samples are damped by the integration more, as a wider
Gaussian sample would be. Written here: no library draws a scale mixture of a diagonal Gaussian field.
"""

from __future__ import annotations

import math

import torch
from scipy import stats
from torch import Tensor

from monai_probreg.uncertainty.calibration import check_calibration

__all__ = ["sample_log_var", "sample_scales"]


def sample_log_var(log_var: Tensor, sample_gain: float) -> Tensor:
    """The log-variance the posterior's samples are drawn with: the calibrated ``log_var`` (any shape) with its std
    widened by ``sample_gain`` (:attr:`~monai_probreg.uncertainty.calibration.Calibration.sample_gain`),
    ``log_var + 2 log(sample_gain)``."""
    check_calibration(1.0, 0.0, sample_gain=sample_gain)
    return log_var + 2.0 * math.log(sample_gain)


def sample_scales(num_samples: int, interval_dof: float | None) -> Tensor:
    """(num_samples,) float32 the factor each sample's deviation from the mean is multiplied by (module docstring):
    sqrt(dof / q_k), q_k the chi^2_dof quantile at (k + 1/2) / num_samples, largest first; all 1 when
    ``interval_dof`` is None."""
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
        raise ValueError(f"num_samples must be an integer >= 1; got {num_samples!r}")
    check_calibration(1.0, 0.0, interval_dof)
    if interval_dof is None:
        return torch.ones(num_samples)
    levels = (torch.arange(num_samples, dtype=torch.float64) + 0.5) / num_samples
    quantiles = torch.from_numpy(stats.chi2.ppf(levels.numpy(), float(interval_dof)))
    return (float(interval_dof) / quantiles).sqrt().float()
