"""How well a registration recovered a known transform: displacement error in mm, and interval coverage.

Fields follow :mod:`monai_probreg.spatial.physical`: ``D(p) = phi(p) - p`` (*S, 3), LPS mm on the fixed grid, ``phi``
mapping a fixed point into the moving image. With the known ``D_true`` and the estimate ``D``:

- ``before``: ``|D_true|``, the error of doing nothing (the identity);
- ``affine``: ``|A(p) - phi_true(p)|``, the error of the affine stage alone (``A``: fixed LPS -> moving LPS);
- ``after``: ``|D - D_true|``, the error of the whole registration;
- ``coverage``: the fraction of error components inside the central ``level`` interval of the calibrated posterior.
  The posterior is the deformable step's, in the fixed image's frame before ``A`` (``phi = A o (id + d)``), so the
  error is taken there, ``delta = L^-1 (phi(p) - phi_true(p))`` with ``L`` the linear part of ``A``, and split along
  the axes the sampled variances belong to (``variance_axes``, columns: unit LPS vectors); a component is inside when
  ``|delta_c| <= z sigma_c``, ``z`` the two-sided Gaussian quantile of ``level`` (the calibration is fitted the same
  way, per component: :mod:`monai_probreg.uncertainty.calibration`).

Each error is summarised by its median and 95th percentile over the voxels of ``mask`` (the brain).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from monai_probreg.metrics.calibration import interval_coverage

__all__ = ["DisplacementRecovery", "ErrorSummary", "displacement_recovery"]

ERROR_PERCENTILE = 95.0  # the upper summary of an error distribution, besides its median


class ErrorSummary(NamedTuple):
    """Median and 95th percentile of an error magnitude, mm."""

    median_mm: float
    p95_mm: float


class DisplacementRecovery(NamedTuple):
    """:func:`displacement_recovery`'s result; ``coverage`` is None without variances."""

    before: ErrorSummary
    affine: ErrorSummary | None
    after: ErrorSummary
    coverage: float | None
    level: float

    def as_dict(self) -> dict:
        out = {
            name: (None if value is None else value._asdict())
            for name, value in (("before", self.before), ("affine_only", self.affine), ("after", self.after))
        }
        return {**out, "coverage": self.coverage, "coverage_level": self.level}


def _summary(error: np.ndarray) -> ErrorSummary:
    return ErrorSummary(round(float(np.median(error)), 4), round(float(np.percentile(error, ERROR_PERCENTILE)), 4))


def displacement_recovery(
    true_warp: np.ndarray,
    warp: np.ndarray,
    mask: np.ndarray,
    points: np.ndarray | None = None,
    affine: np.ndarray | None = None,
    variance: np.ndarray | None = None,
    variance_axes: np.ndarray | None = None,
    level: float = 0.95,
    interval_dof: float | None = None,
) -> DisplacementRecovery:
    """Errors of ``warp`` against ``true_warp`` (both (*S, 3) LPS mm) inside ``mask`` (*S) (module docstring).

    ``points`` (*S, 3): the fixed grid's LPS points and ``affine`` (4, 4): the affine stage, for the affine-only
    error and the frame of the coverage (without ``affine``: the identity). ``variance`` (*S, 3) mm^2 per
    component along the columns of ``variance_axes`` (3, 3): the calibrated posterior, for the coverage at ``level``
    of its intervals (Student-t with ``interval_dof`` degrees of freedom; None: Gaussian).
    """
    true_warp, warp, mask = np.asarray(true_warp), np.asarray(warp), np.asarray(mask, bool)
    if true_warp.shape != warp.shape or true_warp.shape[-1] != 3 or true_warp.shape[:-1] != mask.shape:
        raise ValueError(
            f"expected two (*S, 3) fields and a (*S) mask; got {true_warp.shape}, {warp.shape} and {mask.shape}"
        )
    if not mask.any():
        raise ValueError("the mask selects no voxel")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1); got {level}")
    truth, estimate = true_warp[mask].astype(np.float64), warp[mask].astype(np.float64)
    error = estimate - truth
    affine_summary = None
    if affine is not None:
        if points is None:
            raise ValueError("the affine-only error needs the fixed grid's points")
        inside = np.asarray(points)[mask].astype(np.float64)
        affine = np.asarray(affine, np.float64)
        affine_summary = _summary(np.linalg.norm(inside @ affine[:3, :3].T + affine[:3, 3] - inside - truth, axis=1))
    coverage = None
    if variance is not None:
        if variance_axes is None or np.shape(variance) != true_warp.shape:
            raise ValueError(
                f"expected a (*S, 3) variance {true_warp.shape} and its (3, 3) axes; got "
                f"{np.shape(variance)} and {None if variance_axes is None else np.shape(variance_axes)}"
            )
        linear = np.eye(3) if affine is None else affine[:3, :3]
        components = np.linalg.solve(linear, error.T).T @ np.asarray(variance_axes, np.float64)
        sigma = np.sqrt(np.maximum(np.asarray(variance)[mask].astype(np.float64), 0.0))
        coverage = round(interval_coverage(sigma, components, level, interval_dof), 4)
    return DisplacementRecovery(
        _summary(np.linalg.norm(truth, axis=1)),
        affine_summary,
        _summary(np.linalg.norm(error, axis=1)),
        coverage,
        level,
    )
