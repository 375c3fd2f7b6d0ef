"""experiments/error_model.py: the features' shapes and closed-form values, the model's prediction, the scoring
helpers, the skip without a dataset."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import load_script

study = load_script("experiments", "error_model")


def _pair(shape=(16, 18, 20)):
    generator = torch.Generator().manual_seed(0)
    fixed = torch.zeros(1, 1, *shape)
    fixed[0, 0, 3:-3, 4:-4, 5:-5] = 0.5 + 0.1 * torch.rand(
        shape[0] - 6, shape[1] - 8, shape[2] - 10, generator=generator
    )
    warped = fixed.roll(1, dims=2)
    grid = tuple(s // 2 for s in shape)
    mean = 0.1 * torch.randn(1, 3, *grid, generator=generator)
    log_var = torch.full((1, 3, *grid), math.log(0.01))
    displacement = torch.nn.functional.interpolate(mean, size=shape, mode="trilinear")
    return warped, fixed, mean, log_var, displacement


def test_features_are_one_map_per_name_on_the_image_grid():
    warped, fixed, mean, log_var, displacement = _pair()
    features = study.pair_features(warped, fixed, mean, log_var, displacement)
    assert features.shape == (len(study.FEATURES), 16, 18, 20)
    assert np.isfinite(features).all()
    names = list(study.FEATURES)
    # the network's variance is 0.01 everywhere: its log
    assert np.allclose(features[names.index("log network velocity variance")], math.log(0.01 + study.LOG_FLOOR))
    # the intensity is the fixed image's, the edge distance 0 outside it and positive inside
    assert np.allclose(features[names.index("fixed intensity")], fixed[0, 0].numpy())
    edge = features[names.index("distance to the fixed image's edge")]
    assert edge[0, 0, 0] == 0 and edge[8, 9, 10] > 0


def test_the_torch_features_are_one_map_per_name_on_the_velocity_grid():
    warped, fixed, mean, log_var, displacement = _pair()
    features = study.velocity_grid_features(warped, fixed, mean, log_var, displacement)
    assert features.shape == (1, len(study.FEATURES), 8, 9, 10)
    assert bool(torch.isfinite(features).all())
    names = list(study.FEATURES)
    variance = features[0, names.index("log network velocity variance")]
    assert torch.allclose(variance, torch.full_like(variance, math.log(0.01 + study.LOG_FLOOR)))
    # the residual over 9 voxels is the calibration's own residual (its log)
    residual = study.residual_variance(warped, fixed, (8, 9, 10))
    assert torch.allclose(features[0, 0], (residual[0, 0] + study.LOG_FLOOR).log())
    inside = features[0, names.index("distance to the fixed image's edge")]
    assert float(inside.min()) >= 0 and float(inside.max()) <= 1 and float(inside[4, 4, 5]) > float(inside[0, 0, 0])


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_torch_laplacian_energy_of_a_parabola_is_four_inside(axis):
    shape = (8, 9, 10)
    coord = torch.arange(shape[axis], dtype=torch.float32)
    view = [1, 1, 1]
    view[axis] = shape[axis]
    field = torch.zeros(1, 3, *shape)
    field[0, 1] = coord.view(view).square().expand(shape)
    energy = study._laplacian_energy_torch(field, 1)
    assert energy.shape == (1, 1, *shape)
    assert torch.allclose(energy[0, 0, 1:-1, 1:-1, 1:-1], torch.full((6, 7, 8), 4.0))


@pytest.mark.parametrize("feature_set", list(study.FEATURE_SETS))
def test_a_model_of_only_an_intercept_predicts_its_exponential_on_the_velocity_grid(feature_set):
    warped, fixed, mean, log_var, displacement = _pair()
    coef = np.zeros(len(study.FEATURES) + 1)
    coef[-1] = math.log(0.3)
    variance = study.ErrorModel(coef, feature_set).variance(warped, fixed, mean, log_var, displacement)
    assert variance.shape == (1, 1, 8, 9, 10)
    assert torch.allclose(variance, torch.full_like(variance, 0.3))


@pytest.mark.parametrize("feature_set", list(study.FEATURE_SETS))
def test_a_model_of_the_residual_alone_follows_the_residual(feature_set):
    warped, fixed, mean, log_var, displacement = _pair()
    coef = np.zeros(len(study.FEATURES) + 1)
    coef[0] = 1.0  # exp(log(residual + floor)): the residual itself
    variance = study.ErrorModel(coef, feature_set).variance(warped, fixed, mean, log_var, displacement)
    residual = study.residual_variance(warped, fixed, tuple(mean.shape[2:]))
    assert float(np.corrcoef(variance.flatten().numpy(), residual.flatten().numpy())[0, 1]) > 0.9


def test_scaled_matches_the_residual_mean_and_ranking_reads_absolute_errors():
    residual = torch.tensor([1.0, 3.0])
    assert torch.allclose(study.scaled(torch.tensor([10.0, 30.0]), residual), residual)
    std = np.tile(np.arange(1.0, 6.0), (3, 1))
    assert math.isclose(study.ranking(std, -std), 1.0)  # |error| grows with the std: a perfect ranking


def test_the_posterior_std_is_the_calibrated_velocity_std_upsampled():
    calibration = study.Calibration(2.0, 0.0, None, 100.0)
    log_var = torch.full((1, 3, 4, 4, 4), math.log(0.01))
    residual = torch.full((1, 1, 4, 4, 4), 0.0003)
    std = study.posterior_std(calibration, torch.zeros(1, 3, 4, 4, 4), log_var, residual, (8, 8, 8))
    assert std.shape == (3, 8, 8, 8)
    assert torch.allclose(std, torch.full_like(std, 2.0 * math.sqrt(0.01 + 0.03)))


def test_no_dataset_is_a_clean_skip(tmp_path, capsys):
    assert study.main(["--dataset-dir", str(tmp_path / "missing"), "--out-dir", str(tmp_path)]) == 0
    assert "skipped" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.json"))


def test_cross_fitted_coverage_of_errors_drawn_from_twice_the_std_is_nominal():
    rng = np.random.default_rng(0)

    def case(n=4000):
        std = rng.uniform(0.2, 2.0, (3, n))
        return std, 2.0 * std * rng.standard_normal((3, n)), np.zeros((3, n))  # the samples' std is half the truth's

    coverage = study.cross_fitted_coverage([case() for _ in range(4)], [case() for _ in range(4)])
    for probe in ("population", "subject"):
        assert abs(coverage[probe]["68%"] - 0.68) < 0.03 and abs(coverage[probe]["95%"] - 0.95) < 0.02
    # unrefitted, the same intervals would cover far less: the refit widened them
    std, error, _ = case()
    assert float(np.mean(np.abs(error) <= 1.96 * std)) < 0.75
