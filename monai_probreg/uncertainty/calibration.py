"""Post-hoc calibration of the posterior: a velocity std scale, a bias fraction, the pair's residual and the
intervals' tails.

Variational posteriors are over-confident (the KL pulls sigma^2 towards 1/(lambda D), whatever the real error).
We keep the network as trained and temper its posterior afterwards:

    sigma_calibrated = std_scale * sigma        i.e.   log_var_calibrated = log_var + 2 log(std_scale)

The posterior's spread is not the whole error: the prior also pulls the mean registration short of large
displacements, a bias that grows with the displacement and that the raw posterior does not show. The calibrated
posterior therefore gets a second, isotropic variance term per component (written by hand: no library offers it):

    sigma^2_calibrated,c = std_scale^2 * sigma^2_c + (bias_fraction * |mu|)^2

with mu the posterior mean velocity at that voxel (|mu| its length over the D components; sigma and mu in voxels of
the velocity grid, so ``bias_fraction`` is unitless).

The network's sigma is amortised: it hardly depends on how well this pair ended up aligned, so it ranks the errors of
the answer (the refined mean) only weakly. The pair itself says where the answer is least held: where the registered
images still differ (:mod:`monai_probreg.uncertainty.residual`, ``r``: the local mean squared difference of the warped
moving and the fixed image, on the velocity grid). A fourth number weighs it in before the scale:

    sigma^2_calibrated,c = std_scale^2 * (sigma^2_c + residual_weight * r) + (bias_fraction * |mu|)^2

``residual_weight`` (velocity-grid voxels^2 per squared intensity of the [0, 1] inputs; 0: the network's spread
alone) is chosen by the fit among a few values, as the one whose std map ranks the errors best
(:meth:`monai_probreg.fitting.calibration_probes.CalibrationProbes.residual_weight_for`); the coverage matching then
fits the other numbers at that weight. It stays a diagonal Gaussian on the velocity grid, so the velocity entropy, the
displacement std and the samples all follow from the calibrated ``log_var``. The displacement std is first order, the
calibrated velocity std resized onto the image grid (:mod:`monai_probreg.uncertainty.spread`, no sampling), so its
variance is about std_scale^2 times the raw map's plus (bias_fraction |u|)^2 (u the displacement, about mu once
integrated), which is how :func:`fit_calibration` fits both scalars from one set of maps: the pair whose intervals
cover closest to nominal at :data:`FIT_LEVELS` (``python -m monai_probreg.fitting`` recomputes the maps at the fitted
pair and refits, :mod:`monai_probreg.fitting.calibration_probes`). Samples of the posterior (the label entropy reads
K of them) are independent per velocity voxel, and their displacement spread is damped by interpolation and
integration; a fifth number, ``sample_gain``, widens their velocity std beyond the calibrated one so that it matches
the map on average (the fit's measured damping, kappa: ``sample_gain = 1 / sqrt(kappa)``).

A third number says how the intervals are read. The calibrated std ranks the errors only weakly, so the error over
the std is a Gaussian of uncertain variance: heavier-tailed than a Gaussian, and one scale cannot cover both the 68%
and the 95% level. The intervals are therefore Student-t (``interval_dof`` degrees of freedom, fitted with the
scale; None = Gaussian):

    p-interval of a component  =  +- interval_z(p, interval_dof) * sigma_calibrated

(:func:`monai_probreg.metrics.calibration.interval_z`). The std maps and the samples stay the calibrated Gaussian
posterior's; only the width of an interval at a given level follows the fitted tails.
They are stored next to the weights they belong to, as ``<weights stem>.calibration.json``, with the weights'
SHA-256 so that a retrained model is never paired with an old calibration; a field an older sidecar lacks reads as
its neutral value (``bias_fraction`` 0, ``refinement`` None, ``interval_dof`` None, ``residual_weight`` 0), but one
without ``sample_gain`` was fitted on the sampled std of an older bundle and is refused with the refit command. Raw
(uncalibrated) values: ``std_scale = 1``, ``bias_fraction = 0``, Gaussian intervals (``interval_dof = None``), no
residual term. Held-out coverage and how well
the std ranks the errors: ``benchmarks/uncertainty_calibration.py``.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from monai_probreg.metrics.calibration import interval_z
from monai_probreg.uncertainty.error_model import ERROR_FEATURES, check_error_model
from monai_probreg.uncertainty.residual import PLAIN_RESIDUAL_FORM, residual_form
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.utils.sidecars import read_sidecar, sidecar_path, write_sidecar

__all__ = [
    "POSTERIOR_SAMPLES",
    "FIT_LEVELS",
    "INTERVAL_DOFS",
    "Calibration",
    "RAW",
    "CalibrationRecord",
    "calibrate_log_var",
    "check_calibration",
    "bias_variance",
    "fit_calibration",
    "fit_std_scale",
    "calibration_path",
    "calibration_record_for",
    "save_calibration",
    "load_calibration",
    "calibration_for",
    "std_scale_for",
]

CALIBRATION_SIDECAR = "calibration"  # models/model.pt -> models/model.calibration.json (utils.sidecars)

# posterior samples K the label entropy reads by default, and the fit draws to measure the samples' damping (its
# sidecar's num_samples; the std map is first order and needs none, uncertainty.spread). The one home of that count:
# inference.yaml's num_samples, the demo, the fit's and the benchmarks' --samples read it
POSTERIOR_SAMPLES = 16

FIT_LEVELS: tuple[float, ...] = (0.5, 0.68, 0.8, 0.9, 0.95)  # nominal interval levels whose coverage the fit matches
_GRID_POINTS = 1024  # candidate scales searched between the per-level solutions (log-spaced)
BIAS_FRACTIONS: tuple[float, ...] = tuple(i / 100 for i in range(101))  # bias fractions fit_calibration tries
# Student-t degrees of freedom of the intervals fit_calibration tries (None: the Gaussian, the search's start)
INTERVAL_DOFS: tuple[float | None, ...] = (None, 50.0, 30.0, 20.0, 15.0, 10.0, 8.0, 6.0, 5.0, 4.0, 3.0, 2.5, 2.0, 1.5)
SEARCH_ROUNDS = 2  # rounds of the coordinate search over (bias fraction, interval dof), the scale exact for each
_SEARCH_POINTS = 200_000  # entries fit_calibration searches the bias fraction and the dof on
_MIN_SCALE = 1e-6  # lower bound of a fitted scale (a bias term alone may cover a level: the scale must stay > 0)


class Calibration(NamedTuple):
    """The numbers inference uses (raw posterior: 1, 0 and Gaussian intervals)."""

    std_scale: float
    bias_fraction: float
    interval_dof: float | None = None  # Student-t dof of the intervals; None: Gaussian
    # velocity variance per unit of the pair's term (uncertainty.error_model.pair_term: the error model's predicted
    # squared error, or the pair's residual without one), added before the scale; 0: the network's spread alone
    residual_weight: float = 0.0
    # the error model's coefficients (one per uncertainty.error_model.ERROR_FEATURES, the intercept last); None: the
    # term reads the pair's residual (uncertainty.residual)
    error_model: tuple[float, ...] | None = None
    # the factor the samples' velocity std is widened by beyond the calibrated one (the label entropy reads them), so
    # that their displacement spread matches the first-order std map on average (uncertainty.spread); 1: none
    sample_gain: float = 1.0


RAW = Calibration(1.0, 0.0, None)  # the raw posterior: no scale, no bias term, Gaussian intervals


@dataclass(frozen=True)
class CalibrationRecord:
    """What is stored next to the weights. ``std_scale`` and ``bias_fraction`` are the numbers inference uses."""

    std_scale: float
    weights_file: str
    weights_sha256: str
    fitted_on: list[str] = field(default_factory=list)
    num_samples: int = 0
    levels: list[float] = field(default_factory=lambda: list(FIT_LEVELS))
    method: str = (
        "coverage matching: (std_scale, bias_fraction, interval_dof) of sigma^2 = std_scale^2 (sigma^2 + "
        "residual_weight r) + (bias_fraction |mean velocity|)^2 and the intervals +- t_interval_dof(level) sigma "
        "minimise the sum over levels and probes of (coverage - level)^2 of the first-order displacement std (the "
        "calibrated velocity std resized onto the image grid; r: the registered pair's error_model prediction, or its "
        "local residual without one; residual_weight chosen first, by the population probe's ranking); sample_gain: "
        "the samples' velocity std widened until their displacement variance matches the map's on average over the "
        "population probe"
    )
    bias_fraction: float = 0.0
    # the refinement settings (RefinementSettings.as_dict()) of the registrations it was fitted on: the maps describe
    # that mean; {} = the network's own mean; None = not recorded (an older sidecar)
    refinement: dict | None = None
    # Student-t degrees of freedom of the intervals; None: Gaussian (also an older sidecar without the field)
    interval_dof: float | None = None
    # the residual term's weight (Calibration.residual_weight); 0: none (also an older sidecar without the field)
    residual_weight: float = 0.0
    # the boxes of the pair's residual the weight is per unit of (uncertainty.residual.residual_form()); None: an
    # older sidecar, fitted with PLAIN_RESIDUAL_FORM
    residual: dict | None = None
    # the error model the term reads (Calibration.error_model) and the features its coefficients are for
    # (uncertainty.error_model.ERROR_FEATURES); None: the residual itself (also an older sidecar)
    error_model: list[float] | None = None
    error_features: list[str] | None = None
    # Calibration.sample_gain; None: an older sidecar, fitted on the sampled displacement std (refused: the std map is
    # first order)
    sample_gain: float | None = None

    def calibration(self) -> Calibration:
        """The numbers inference uses."""
        error_model = None if self.error_model is None else tuple(float(c) for c in self.error_model)
        gain = 1.0 if self.sample_gain is None else float(self.sample_gain)
        return Calibration(
            self.std_scale, self.bias_fraction, self.interval_dof, self.residual_weight, error_model, gain
        )


def check_calibration(
    std_scale: float,
    bias_fraction: float,
    interval_dof: float | None = None,
    residual_weight: float = 0.0,
    sample_gain: float = 1.0,
) -> None:
    """ValueError unless ``std_scale`` > 0, ``bias_fraction`` >= 0, ``residual_weight`` >= 0 and ``sample_gain`` > 0,
    all finite, and ``interval_dof`` None or a positive finite number."""
    _check_scale(std_scale)
    if not (
        isinstance(sample_gain, (int, float))
        and not isinstance(sample_gain, bool)
        and math.isfinite(sample_gain)
        and sample_gain > 0
    ):
        raise ValueError(f"sample_gain must be a positive finite number; got {sample_gain!r}")
    _check_bias_fraction(bias_fraction)
    _check_dof(interval_dof)
    if not (
        isinstance(residual_weight, (int, float))
        and not isinstance(residual_weight, bool)
        and math.isfinite(residual_weight)
        and residual_weight >= 0
    ):
        raise ValueError(f"residual_weight must be a finite number >= 0; got {residual_weight!r}")


def _check_dof(interval_dof: float | None) -> None:
    if interval_dof is not None and not (
        isinstance(interval_dof, (int, float))
        and not isinstance(interval_dof, bool)
        and math.isfinite(interval_dof)
        and interval_dof > 0
    ):
        raise ValueError(f"interval_dof must be None (Gaussian) or a positive finite number; got {interval_dof!r}")


def _check_scale(std_scale: float) -> None:
    if not (math.isfinite(std_scale) and std_scale > 0):
        raise ValueError(f"std_scale must be a positive finite number; got {std_scale}")


def _check_bias_fraction(bias_fraction: float) -> None:
    if not (math.isfinite(bias_fraction) and bias_fraction >= 0):
        raise ValueError(f"bias_fraction must be a finite number >= 0; got {bias_fraction}")


def calibrate_log_var(
    log_var: Tensor,
    std_scale: float,
    mean: Tensor | None = None,
    bias_fraction: float = 0.0,
    residual: Tensor | None = None,
    residual_weight: float = 0.0,
) -> Tensor:
    """log sigma^2 of the calibrated posterior:
    ``log(std_scale^2 (exp(log_var) + residual_weight residual) + (bias_fraction |mean|)^2)``, i.e.
    ``log_var + 2 log(std_scale)`` without the bias and residual terms. ``log_var`` (B, D, *V) (any shape without
    them); with ``bias_fraction`` > 0, ``mean`` the posterior mean velocity, same shape as ``log_var``; with
    ``residual_weight`` > 0, ``residual`` (B, 1, *V) from :func:`~monai_probreg.uncertainty.residual.residual_variance`
    on the velocity grid."""
    check_calibration(std_scale, bias_fraction, None, residual_weight)
    if bias_fraction == 0 and residual_weight == 0:
        return log_var + 2.0 * math.log(std_scale)
    variance = log_var.exp()
    if residual_weight > 0:
        expected = (log_var.shape[0], 1, *log_var.shape[2:])
        if residual is None or tuple(residual.shape) != expected:
            raise ValueError(
                f"residual_weight > 0 needs the residual {expected} of the log_var's grid; "
                f"got {None if residual is None else tuple(residual.shape)}"
            )
        variance = variance + residual_weight * residual.to(variance.dtype)
    variance = std_scale**2 * variance
    if bias_fraction > 0:
        if mean is None or mean.shape != log_var.shape:
            raise ValueError(
                f"bias_fraction > 0 needs the posterior mean of the log_var's shape {tuple(log_var.shape)}; "
                f"got {None if mean is None else tuple(mean.shape)}"
            )
        variance = variance + bias_variance(mean, bias_fraction)
    return torch.log(variance)


def bias_variance(mean: Tensor, bias_fraction: float) -> Tensor:
    """(B, 1, *S) ``(bias_fraction * |mean|)^2`` for a field ``mean`` (B, D, *S) (the posterior mean velocity): the
    variance the calibration adds to every component (units of ``mean``, squared)."""
    _check_bias_fraction(bias_fraction)
    if mean.dim() < 3:
        raise ValueError(f"expected a field (B, D, *S); got shape {tuple(mean.shape)}")
    return bias_fraction**2 * mean.float().pow(2).sum(1, keepdim=True)


def _array(x: Tensor | np.ndarray) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, Tensor) else np.asarray(x, np.float64)


def _fit_scale(
    s: np.ndarray, e: np.ndarray, b: np.ndarray, z: np.ndarray, levels: np.ndarray, groups: np.ndarray
) -> tuple[float, float]:
    """(scale, cost) for one bias variance ``b``: ``|e| <= z_p sqrt(scale^2 s^2 + b)`` <=> ``r_p <= scale^2`` with
    ``r_p = (e^2 / z_p^2 - b) / s^2``, so each level's coverage is a sorted search and each level alone has an exact
    solution per group; the scale is searched between those. The cost sums (coverage - level)^2 over the levels and
    the groups (``groups``: one small integer per entry)."""
    r = (e[None, :] ** 2 / z[:, None] ** 2 - b[None, :]) / s[None, :] ** 2  # (levels, N)
    per_group = [np.sort(r[:, groups == g], axis=1) for g in np.unique(groups)]
    per_level = np.sqrt(
        np.maximum([np.quantile(r_p, p) for r_g in per_group for r_p, p in zip(r_g, levels)], _MIN_SCALE**2)
    )
    low, high = per_level.min(), per_level.max()
    candidates = np.geomspace(low, high, _GRID_POINTS) if high > low else np.array([low])
    cost = np.zeros(len(candidates))
    for r_g in per_group:
        coverage = np.stack([np.searchsorted(r_p, candidates**2, side="right") for r_p in r_g], 1) / r_g.shape[1]
        cost += ((coverage - levels[None, :]) ** 2).sum(axis=1)
    best = int(np.argmin(cost))
    return float(candidates[best]), float(cost[best])


def fit_calibration(
    std: Tensor | np.ndarray,
    error: Tensor | np.ndarray,
    displacement_norm: Tensor | np.ndarray,
    levels: Sequence[float] = FIT_LEVELS,
    bias_fractions: Sequence[float] = BIAS_FRACTIONS,
    groups: Tensor | np.ndarray | None = None,
    interval_dofs: Sequence[float | None] = INTERVAL_DOFS,
) -> Calibration:
    """(scale s, bias fraction a, dof) for which the intervals ``|error| <= z_p sqrt(s^2 std^2 + a^2 n^2)``, z_p the
    quantile of level p of the Student-t with dof degrees of freedom (None: Gaussian), cover closest to p over
    ``levels`` (least squares in coverage). a and dof are searched over ``bias_fractions`` and ``interval_dofs`` by
    coordinates (``SEARCH_ROUNDS`` rounds from their first entries, on a fixed subset), s exactly for each pair.

    ``std`` > 0, ``error`` and ``displacement_norm`` n = |mean displacement| (>= 0): same shape, any shape, one
    entry per voxel and component. ``s`` multiplies the std the samples were drawn with. ``groups`` (same shape,
    integers; None: one group): entries from different probes, each group's coverage matched on its own (the cost
    sums over groups, so a large group does not drown a small one)."""
    s, e, n = _array(std).reshape(-1), _array(error).reshape(-1), _array(displacement_norm).reshape(-1)
    if not (s.shape == e.shape == n.shape) or s.size == 0:
        raise ValueError(
            f"std, error and displacement_norm must have the same non-empty shape; got "
            f"{_array(std).shape}, {_array(error).shape} and {_array(displacement_norm).shape}"
        )
    if not (
        np.isfinite(s).all() and np.isfinite(e).all() and (s > 0).all() and np.isfinite(n).all() and (n >= 0).all()
    ):
        raise ValueError("std must be positive and finite, error finite, displacement_norm finite and >= 0")
    g = np.zeros(s.size, np.int64) if groups is None else np.asarray(groups).reshape(-1)
    if g.shape != s.shape or not np.issubdtype(g.dtype, np.integer):
        raise ValueError(f"groups must be integers of the shape of std {_array(std).shape}; got {np.shape(groups)}")
    if not levels or not bias_fractions or not interval_dofs:
        raise ValueError(
            f"levels, bias_fractions and interval_dofs must not be empty; got {list(levels)}, {list(bias_fractions)}"
            f" and {list(interval_dofs)}"
        )
    for a in bias_fractions:
        _check_bias_fraction(a)
    for dof in interval_dofs:
        _check_dof(dof)
    p = np.asarray(levels, np.float64)

    def quantiles(dof: float | None) -> np.ndarray:
        return np.array([interval_z(level, dof) for level in levels])

    bias_fraction, dof = float(bias_fractions[0]), interval_dofs[0]
    if len(bias_fractions) > 1 or len(interval_dofs) > 1:  # on a fixed random subset: seconds, not minutes
        pick = _search_subset(g)

        def cost(a: float, d: float | None) -> float:
            return _fit_scale(s[pick], e[pick], (a * n[pick]) ** 2, quantiles(d), p, g[pick])[1]

        for _ in range(SEARCH_ROUNDS):
            if len(bias_fractions) > 1:
                bias_fraction = float(bias_fractions[int(np.argmin([cost(a, dof) for a in bias_fractions]))])
            if len(interval_dofs) > 1:
                dof = interval_dofs[int(np.argmin([cost(bias_fraction, d) for d in interval_dofs]))]
    scale = _fit_scale(s, e, (bias_fraction * n) ** 2, quantiles(dof), p, g)[0]  # the scale on all entries
    return Calibration(scale, bias_fraction, None if dof is None else float(dof))


def _search_subset(groups: np.ndarray) -> np.ndarray:
    """A fixed random subset of at most ``_SEARCH_POINTS`` entries, shared equally by the groups."""
    rng, labels = np.random.default_rng(0), np.unique(groups)
    per_group = _SEARCH_POINTS // len(labels)
    return np.concatenate([rng.permutation(np.flatnonzero(groups == g))[:per_group] for g in labels])


def fit_std_scale(std: Tensor | np.ndarray, error: Tensor | np.ndarray, levels: Sequence[float] = FIT_LEVELS) -> float:
    """The scale s for which the Gaussian intervals ``|error| <= z_p * s * std`` cover closest to p over ``levels``
    (least squares in coverage): :func:`fit_calibration` without a bias term, with Gaussian intervals. ``std`` > 0 and ``error``, same shape."""
    return fit_calibration(std, error, np.zeros(np.shape(_array(std))), levels, (0.0,), interval_dofs=(None,)).std_scale


def calibration_path(weights_file: str | os.PathLike) -> Path:
    """Where the calibration of ``weights_file`` lives: ``models/model.pt`` -> ``models/model.calibration.json``."""
    return sidecar_path(weights_file, CALIBRATION_SIDECAR)


def save_calibration(
    weights_file: str | os.PathLike,
    std_scale: float,
    fitted_on: Sequence[str] = (),
    num_samples: int = 0,
    levels: Sequence[float] = FIT_LEVELS,
    bias_fraction: float = 0.0,
    refinement: Mapping[str, Any] | None = None,
    interval_dof: float | None = None,
    path: str | os.PathLike | None = None,
    residual_weight: float = 0.0,
    error_model: Sequence[float] | None = None,
    sample_gain: float = 1.0,
) -> CalibrationRecord:
    """Write the sidecar JSON of ``weights_file`` atomically (temporary file, then rename) and return it.
    ``refinement``: the settings of the refined mean it was fitted on (``RefinementSettings.as_dict()``; None: the
    network's mean); ``interval_dof``: the intervals' Student-t dof (None: Gaussian); ``path``: where to write it
    (default: next to the weights, :func:`calibration_path`); ``residual_weight``: the residual term's weight (0: none),
    per unit of the residual this package computes (recorded as ``residual``); ``error_model``: the coefficients of
    the error model the term reads (recorded with the features they are for), or None (the residual);
    ``sample_gain``: :attr:`Calibration.sample_gain`."""
    check_calibration(std_scale, bias_fraction, interval_dof, residual_weight, sample_gain)
    check_error_model(error_model)
    record = CalibrationRecord(
        float(std_scale),
        Path(weights_file).name,
        file_sha256(weights_file),
        list(fitted_on),
        int(num_samples),
        [float(p) for p in levels],
        bias_fraction=float(bias_fraction),
        refinement=dict(refinement or {}),
        interval_dof=None if interval_dof is None else float(interval_dof),
        residual_weight=float(residual_weight),
        residual=residual_form(),
        error_model=None if error_model is None else [float(c) for c in error_model],
        error_features=None if error_model is None else list(ERROR_FEATURES),
        sample_gain=float(sample_gain),
    )
    write_sidecar(weights_file, CALIBRATION_SIDECAR, asdict(record), path)
    return record


def load_calibration(weights_file: str | os.PathLike) -> CalibrationRecord:
    """Read the sidecar of ``weights_file``; refuses one fitted for other weights (SHA-256 mismatch), with a residual
    term for another form of the pair's residual (:func:`~monai_probreg.uncertainty.residual.residual_form`), or on
    the sampled displacement std of an older bundle (no ``sample_gain``)."""
    path = calibration_path(weights_file)
    data = read_sidecar(weights_file, CALIBRATION_SIDECAR, "calibration record", " or use std_scale 1 (raw)")
    try:
        record = CalibrationRecord(**data)
    except TypeError as err:
        raise ValueError(f"{path}: not a calibration record ({err})") from None
    if record.sample_gain is None:
        raise ValueError(
            f"{path}: fitted on the sampled displacement std of an older bundle; this package's std map is first "
            "order (uncertainty.spread); refit it: python -m monai_probreg.fitting --only calibration"
        )
    try:
        check_calibration(
            record.std_scale, record.bias_fraction, record.interval_dof, record.residual_weight, record.sample_gain
        )
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {err}") from None
    if record.refinement is not None and not isinstance(record.refinement, dict):
        raise ValueError(
            f"{path}: refinement must be a mapping of refinement settings or absent; got "
            f"{type(record.refinement).__name__}"
        )
    fitted_residual = PLAIN_RESIDUAL_FORM if record.residual is None else record.residual
    if record.residual_weight > 0 and fitted_residual != residual_form():
        raise ValueError(
            f"{path}: fitted for the pair's residual {fitted_residual}, this package computes {residual_form()}; "
            "refit it: python -m monai_probreg.fitting --only calibration"
        )
    if record.error_model is not None:
        if record.error_features != list(ERROR_FEATURES):
            raise ValueError(
                f"{path}: an error model of the features {record.error_features}, this package computes "
                f"{list(ERROR_FEATURES)}; refit it: python -m monai_probreg.fitting --only calibration"
            )
        try:
            check_error_model(record.error_model)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
    return record


def calibration_record_for(weights_file: str | os.PathLike, calibrate: bool = True) -> CalibrationRecord | None:
    """The sidecar of ``weights_file`` to use (read and checked once), or None for the raw posterior: when
    ``calibrate`` is false or, with a warning, when the weights have no calibration."""
    if not calibrate:
        return None
    try:
        return load_calibration(weights_file)
    except FileNotFoundError:
        warnings.warn(
            f"{weights_file} has no calibration ({calibration_path(weights_file).name}); "
            "uncertainty maps are the raw, uncalibrated posterior",
            stacklevel=3,
        )
        return None


def calibration_for(weights_file: str | os.PathLike, calibrate: bool = True) -> Calibration:
    """The calibration to use with ``weights_file``: its sidecar's, or the raw posterior's (1, 0, Gaussian) when
    ``calibrate`` is false or, with a warning, when the weights have no calibration."""
    record = calibration_record_for(weights_file, calibrate)
    if record is None:
        return Calibration(1.0, 0.0)
    return record.calibration()


def std_scale_for(weights_file: str | os.PathLike, calibrate: bool = True) -> float:
    """:func:`calibration_for`'s ``std_scale`` alone."""
    return calibration_for(weights_file, calibrate).std_scale
