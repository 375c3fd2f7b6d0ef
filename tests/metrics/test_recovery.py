"""monai_probreg.metrics.recovery: errors against a known transform, and the coverage of the posterior intervals."""

from __future__ import annotations

import numpy as np
import pytest

from monai_probreg.metrics.calibration import gaussian_interval_z
from monai_probreg.metrics.recovery import displacement_recovery
from monai_probreg.spatial.physical import grid_points

SHAPE = (6, 7, 5)
Z95 = gaussian_interval_z(0.95)


@pytest.fixture
def case():
    rng = np.random.default_rng(0)
    points = grid_points(SHAPE, np.diag([-1.0, -1.0, 1.0, 1.0]))
    truth = rng.normal(0, 3, (*SHAPE, 3))
    mask = np.ones(SHAPE, bool)
    mask[0] = False  # a slab outside the brain
    return points, truth, mask


def test_a_perfect_estimate_has_no_error_and_full_coverage(case):
    points, truth, mask = case
    result = displacement_recovery(truth, truth.copy(), mask, points, np.eye(4), np.full(truth.shape, 1e-4), np.eye(3))
    assert result.after.median_mm == 0 and result.after.p95_mm == 0 and result.coverage == 1.0
    norms = np.linalg.norm(truth[mask], axis=1)
    assert result.before.median_mm == pytest.approx(np.median(norms), abs=1e-4)
    assert result.before.p95_mm == pytest.approx(np.percentile(norms, 95), abs=1e-4)
    assert result.affine == result.before  # the identity affine does nothing


def test_a_constant_error_is_reported_in_mm(case):
    _points, truth, mask = case
    result = displacement_recovery(truth, truth + [0.0, 2.0, 0.0], mask)
    assert result.after == (2.0, 2.0) and result.affine is None and result.coverage is None


def test_the_affine_alone_is_scored_against_the_truth(case):
    points, _, mask = case
    affine = np.eye(4)
    affine[:3, 3] = [1.0, -2.0, 0.5]
    truth = np.broadcast_to(affine[:3, 3], (*SHAPE, 3)) + 0.0
    result = displacement_recovery(truth, truth, mask, points, affine)
    assert result.affine == (0.0, 0.0)  # the translation is the whole truth
    assert result.before.median_mm == pytest.approx(np.linalg.norm(affine[:3, 3]), abs=1e-4)


def test_coverage_counts_components_along_the_variance_axes(case):
    _points, truth, mask = case
    error = np.array([1.0, 0.0, 0.0])  # along L only
    tight_on_l = np.broadcast_to([(0.1 / Z95) ** 2, 100.0, 100.0], truth.shape)
    result = displacement_recovery(truth, truth + error, mask, variance=tight_on_l, variance_axes=np.eye(3))
    assert result.coverage == pytest.approx(2 / 3, abs=1e-4)
    # the same variances along permuted axes: the tight component now lies along P, where there is no error
    permuted = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    result = displacement_recovery(truth, truth + error, mask, variance=tight_on_l, variance_axes=permuted)
    assert result.coverage == 1.0


def test_coverage_is_taken_in_the_fixed_frame_before_the_affine(case):
    points, truth, mask = case
    affine = np.diag([2.0, 2.0, 2.0, 1.0])  # the moving scan is twice as large
    # 1.5 mm of error in moving space is 0.75 mm of the deformable step's error: inside 1.96 x 0.5 mm, not 1.96 x 0.35
    inside = displacement_recovery(truth, truth + 1.5, mask, points, affine, np.full(truth.shape, 0.25), np.eye(3))
    outside = displacement_recovery(truth, truth + 1.5, mask, points, affine, np.full(truth.shape, 0.35**2), np.eye(3))
    assert inside.coverage == 1.0 and outside.coverage == 0.0


def test_the_level_sets_the_interval(case):
    _points, truth, mask = case
    variance = np.ones(truth.shape)
    error = np.array([1.5, 1.5, 1.5])  # 1.5 sigma: inside the 95% interval (1.96), outside the 80% one (1.28)
    assert displacement_recovery(truth, truth + error, mask, variance=variance, variance_axes=np.eye(3)).coverage == 1
    assert (
        displacement_recovery(
            truth, truth + error, mask, variance=variance, variance_axes=np.eye(3), level=0.8
        ).coverage
        == 0
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"warp": np.zeros((2, 2, 2, 3))}, "expected two"),
        ({"mask": np.zeros(SHAPE, bool)}, "no voxel"),
        ({"level": 1.0}, "level"),
        ({"variance": np.ones((*SHAPE, 3))}, "axes"),
        ({"affine": np.eye(4)}, "points"),
    ],
)
def test_bad_arguments_are_refused(case, kwargs, match):
    _, truth, mask = case
    arguments = {"true_warp": truth, "warp": truth, "mask": mask} | kwargs
    with pytest.raises(ValueError, match=match):
        displacement_recovery(**arguments)


def test_coverage_reads_student_t_intervals_when_the_calibration_says(case):
    """An error of 2.5 sigma on every component: outside the Gaussian 95% interval (1.96 sigma), inside the
    Student-t one with 3 dof (3.18 sigma)."""
    _points, truth, mask = case
    variance = np.ones(truth.shape)
    error = truth + 2.5
    gaussian = displacement_recovery(truth, error, mask, variance=variance, variance_axes=np.eye(3))
    student = displacement_recovery(truth, error, mask, variance=variance, variance_axes=np.eye(3), interval_dof=3.0)
    assert gaussian.coverage == 0.0 and student.coverage == 1.0
