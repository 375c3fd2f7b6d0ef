"""Post-hoc calibration of the velocity posterior: one scalar that scales its standard deviation.

Variational posteriors are over-confident (the KL pulls sigma^2 towards 1/(lambda D), whatever the real error).
We keep the network as trained and temper its posterior afterwards:

    sigma_calibrated = std_scale * sigma        i.e.   log_var_calibrated = log_var + 2 log(std_scale)

Sampling, the velocity entropy and the displacement std all follow from the calibrated ``log_var``; for the small
sigmas of a trained model the displacement std scales (to first order) by the same factor, which is how
:func:`fit_std_scale` can fit the scale from one set of samples (the benchmark then checks coverage with samples
drawn from the calibrated posterior). The scale is fitted on subjects with a known true displacement
(``benchmarks/uncertainty_calibration.py``) and stored next to the weights it belongs to, as
``<weights stem>.calibration.json``, with the weights' SHA-256 so that a retrained model is never paired with an
old scale. Raw (uncalibrated) values: ``std_scale = 1``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from monai_probreg.metrics.calibration import gaussian_interval_z

__all__ = [
    "FIT_LEVELS",
    "CalibrationRecord",
    "calibrate_log_var",
    "fit_std_scale",
    "calibration_path",
    "save_calibration",
    "load_calibration",
    "std_scale_for",
]

FIT_LEVELS: tuple[float, ...] = (0.5, 0.68, 0.8, 0.9, 0.95)  # nominal interval levels whose coverage the fit matches
_GRID_POINTS = 1024  # candidate scales searched between the per-level solutions (log-spaced)


@dataclass(frozen=True)
class CalibrationRecord:
    """What is stored next to the weights. ``std_scale`` is the only number inference uses."""

    std_scale: float
    weights_file: str
    weights_sha256: str
    fitted_on: list[str] = field(default_factory=list)
    num_samples: int = 0
    levels: list[float] = field(default_factory=lambda: list(FIT_LEVELS))
    method: str = "coverage matching: std_scale minimises sum over levels of (coverage - level)^2"


def calibrate_log_var(log_var: Tensor, std_scale: float) -> Tensor:
    """log sigma^2 of the calibrated posterior: ``log_var + 2 log(std_scale)`` (any shape)."""
    if not (math.isfinite(std_scale) and std_scale > 0):
        raise ValueError(f"std_scale must be a positive finite number; got {std_scale}")
    return log_var + 2.0 * math.log(std_scale)


def fit_std_scale(std: Tensor | np.ndarray, error: Tensor | np.ndarray, levels: Sequence[float] = FIT_LEVELS) -> float:
    """The scale s for which the intervals ``|error| <= z_p * s * std`` cover closest to p over ``levels``
    (least squares in coverage). ``std`` > 0 and ``error`` same shape, any shape."""
    s = std.detach().cpu().double().numpy() if isinstance(std, Tensor) else np.asarray(std, np.float64)
    e = error.detach().cpu().double().numpy() if isinstance(error, Tensor) else np.asarray(error, np.float64)
    if s.shape != e.shape or s.size == 0:
        raise ValueError(f"std and error must have the same non-empty shape; got {s.shape} and {e.shape}")
    if not (np.isfinite(s).all() and np.isfinite(e).all() and (s > 0).all()):
        raise ValueError("std must be positive and finite, error finite")
    if not levels:
        raise ValueError("levels must not be empty")
    ratio = np.sort((np.abs(e) / s).reshape(-1))
    z = np.array([gaussian_interval_z(p) for p in levels])
    per_level = np.array([np.quantile(ratio, p) for p in levels]) / z  # each one alone makes its coverage exact
    low, high = max(per_level.min(), 1e-12), max(per_level.max(), 1e-12)
    candidates = np.geomspace(low, high, _GRID_POINTS) if high > low else np.array([low])
    coverage = np.searchsorted(ratio, z[None, :] * candidates[:, None], side="right") / ratio.size
    cost = ((coverage - np.asarray(levels)[None, :]) ** 2).sum(axis=1)
    return float(candidates[int(np.argmin(cost))])


def _sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def calibration_path(weights_file: str | os.PathLike) -> Path:
    """Where the calibration of ``weights_file`` lives: ``models/model.pt`` -> ``models/model.calibration.json``."""
    path = Path(weights_file)
    return path.with_name(path.stem + ".calibration.json")


def save_calibration(weights_file: str | os.PathLike, std_scale: float, fitted_on: Sequence[str] = (),
                     num_samples: int = 0, levels: Sequence[float] = FIT_LEVELS) -> CalibrationRecord:
    """Write the sidecar JSON of ``weights_file`` atomically (temporary file, then rename) and return it."""
    calibrate_log_var(np.zeros(1), std_scale)  # validates the scale
    record = CalibrationRecord(float(std_scale), Path(weights_file).name, _sha256(weights_file), list(fitted_on),
                               int(num_samples), [float(p) for p in levels])
    target = calibration_path(weights_file)
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(asdict(record), f, indent=2)
    os.replace(tmp, target)
    return record


def load_calibration(weights_file: str | os.PathLike) -> CalibrationRecord:
    """Read the sidecar of ``weights_file``; refuses one fitted for other weights (SHA-256 mismatch)."""
    path = calibration_path(weights_file)
    try:
        data = json.loads(path.read_text())
        record = CalibrationRecord(**data)
    except FileNotFoundError:
        raise
    except (OSError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: not a calibration record ({err})") from err
    actual = _sha256(weights_file)
    if record.weights_sha256 != actual:
        raise ValueError(f"{path} was fitted for weights with SHA-256 {record.weights_sha256[:12]}..., but "
                         f"{weights_file} has {actual[:12]}...; refit it (benchmarks/uncertainty_calibration.py) "
                         "or use std_scale 1 (raw)")
    calibrate_log_var(np.zeros(1), record.std_scale)
    return record


def std_scale_for(weights_file: str | os.PathLike, calibrate: bool = True) -> float:
    """The std scale to use with ``weights_file``: its sidecar's, or 1 (raw) when ``calibrate`` is false or, with a
    warning, when the weights have no calibration."""
    if not calibrate:
        return 1.0
    try:
        return load_calibration(weights_file).std_scale
    except FileNotFoundError:
        warnings.warn(f"{weights_file} has no calibration ({calibration_path(weights_file).name}); "
                      "uncertainty maps are the raw, uncalibrated posterior", stacklevel=2)
        return 1.0
