"""Calibration metrics on toys with known answers: a perfectly calibrated Gaussian, an over-confident one, ties."""

import math

import numpy as np
import pytest
import torch
from monai.metrics import compute_roc_auc

from monai_probreg.metrics.calibration import (
    auroc,
    gaussian_interval_z,
    interval_coverage,
    interval_z,
    reliability_bins,
    spearman,
    uncertainty_calibration_error,
)

N = 200_000


@pytest.fixture
def calibrated():
    """std varies over voxels (log-normal); error ~ N(0, std^2) exactly: a perfectly calibrated prediction."""
    rng = np.random.default_rng(0)
    std = np.exp(rng.normal(0.0, 0.7, N))
    return std, std * rng.standard_normal(N)


def test_gaussian_interval_z_known_quantiles():
    assert gaussian_interval_z(0.95) == pytest.approx(1.959964, abs=1e-6)
    assert gaussian_interval_z(0.68) == pytest.approx(0.994458, abs=1e-6)


@pytest.mark.parametrize("level", [0.0, 1.0, -0.1, 1.5])
def test_gaussian_interval_z_rejects_bad_level(level):
    with pytest.raises(ValueError, match="level"):
        gaussian_interval_z(level)


@pytest.mark.parametrize("level", [0.5, 0.68, 0.95])
def test_interval_z_is_the_gaussian_without_dof_and_the_cauchy_at_one_dof(level):
    assert interval_z(level) == gaussian_interval_z(level)
    assert interval_z(level, 1.0) == pytest.approx(math.tan(math.pi * level / 2), rel=1e-9)  # closed form
    assert interval_z(level, 1e6) == pytest.approx(gaussian_interval_z(level), rel=1e-5)  # t -> Gaussian
    assert interval_z(level, 3.0) > interval_z(level, 30.0) > gaussian_interval_z(level)  # heavier tails: wider


@pytest.mark.parametrize("dof", [0.0, -2.0, math.inf, math.nan])
def test_interval_z_rejects_bad_dof(dof):
    with pytest.raises(ValueError, match="dof must be a positive finite number or None"):
        interval_z(0.95, dof)


@pytest.mark.parametrize("level", [0.0, 1.0])
def test_interval_z_rejects_bad_level_with_dof(level):
    with pytest.raises(ValueError, match="level"):
        interval_z(level, 3.0)


@pytest.mark.parametrize("level", [0.5, 0.68, 0.95])
def test_student_t_errors_are_covered_by_their_own_intervals_not_the_gaussians(level):
    rng = np.random.default_rng(1)
    std = np.exp(rng.normal(0.0, 0.7, N))
    error = std * rng.standard_t(3.0, N)
    assert interval_coverage(std, error, level, 3.0) == pytest.approx(level, abs=0.005)
    if level == 0.95:  # the Gaussian interval misses the tails
        assert interval_coverage(std, error, level) < 0.92


@pytest.mark.parametrize("level", [0.5, 0.68, 0.95])
def test_calibrated_gaussian_covers_its_nominal_level(calibrated, level):
    assert interval_coverage(*calibrated, level) == pytest.approx(level, abs=0.005)


def test_overconfident_gaussian_undercovers(calibrated):
    std, error = calibrated
    # claims half the real spread: P(|n| <= 1.96 / 2) = 0.673
    assert interval_coverage(std / 2, error, 0.95) == pytest.approx(0.673, abs=0.005)


def test_uce_is_zero_when_calibrated_and_the_gap_when_not(calibrated):
    std, error = calibrated
    assert uncertainty_calibration_error(std, error) < 0.01 * std.mean()
    constant = np.full(N, 0.5)
    wide_error = np.random.default_rng(1).normal(0.0, 1.0, N)  # true spread 1, claimed 0.5: gap 0.5
    assert uncertainty_calibration_error(constant, wide_error) == pytest.approx(0.5, abs=0.01)


def test_reliability_bins_quantile_has_equal_counts_and_matching_rms(calibrated):
    bins = reliability_bins(*calibrated, num_bins=15)
    assert len(bins.count) == 15 and bins.count.sum() == N
    assert np.all(np.abs(bins.count - N / 15) <= 1)
    np.testing.assert_allclose(bins.rms_error, bins.rms_std, rtol=0.03)
    assert np.all(np.diff(bins.rms_std) > 0)


def test_reliability_bins_uniform_edges_and_empty_bins_dropped():
    std = np.array([0.0, 0.1, 0.9, 1.0])
    bins = reliability_bins(std, np.zeros(4), num_bins=10, binning="uniform")
    np.testing.assert_allclose(bins.edges, np.linspace(0, 1, 11))
    assert bins.count.tolist() == [1, 1, 2]  # 0.0 | 0.1 | 0.9 and the maximum 1.0 in the last bin


def test_spearman_monotone_and_reversed():
    x = np.random.default_rng(2).random(1000)
    assert spearman(x, np.exp(3 * x)) == pytest.approx(1.0)
    assert spearman(x, -x) == pytest.approx(-1.0)


def test_spearman_std_flags_error_on_calibrated_toy(calibrated):
    std, error = calibrated
    assert spearman(std, np.abs(error)) > 0.3


def test_auroc_separating_reversed_and_uninformative():
    outcome = np.array([0, 0, 0, 1, 1], dtype=bool)
    assert auroc(np.array([0.1, 0.2, 0.3, 0.8, 0.9]), outcome) == 1.0
    assert auroc(np.array([0.9, 0.8, 0.7, 0.1, 0.2]), outcome) == 0.0
    assert auroc(np.ones(5), outcome) == 0.5


def test_auroc_matches_monai_with_ties():
    rng = np.random.default_rng(3)
    score = rng.integers(0, 5, 500).astype(float)  # many ties, like label entropy from K samples
    outcome = rng.random(500) < 0.2 + 0.1 * score
    expected = compute_roc_auc(torch.as_tensor(score), torch.as_tensor(outcome.astype(np.int64)))
    assert auroc(score, outcome) == pytest.approx(expected, abs=1e-12)


def test_shape_mismatch_is_rejected():
    with pytest.raises(ValueError, match="same shape"):
        interval_coverage(np.ones(3), np.ones(4), 0.95)
    with pytest.raises(ValueError, match="same shape"):
        spearman(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="same shape"):
        auroc(np.ones(3), np.ones(4))


def test_negative_std_nan_and_empty_are_rejected():
    with pytest.raises(ValueError, match=">= 0"):
        uncertainty_calibration_error(-np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="finite"):
        interval_coverage(np.ones(3), np.array([0.0, np.nan, 1.0]), 0.68)
    with pytest.raises(ValueError, match="empty"):
        interval_coverage(np.ones(0), np.ones(0), 0.68)


def test_bad_binning_arguments_are_rejected():
    with pytest.raises(ValueError, match="num_bins"):
        reliability_bins(np.ones(3), np.ones(3), num_bins=0)
    with pytest.raises(ValueError, match="binning"):
        reliability_bins(np.ones(3), np.ones(3), binning="log")  # type: ignore[arg-type]


def test_auroc_needs_binary_outcome_with_both_classes():
    with pytest.raises(ValueError, match="0/1"):
        auroc(np.ones(3), np.array([0.0, 0.5, 1.0]))
    with pytest.raises(ValueError, match="both classes"):
        auroc(np.ones(3), np.ones(3))
