"""uncertainty/error_model.py: the features in closed form, the prediction, the fit recovers a known model, the rule
of which map the calibration's term reads, one test per bad argument."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_probreg.uncertainty.error_model import (
    ERROR_FEATURES,
    LOG_FLOOR,
    check_error_model,
    error_features,
    fit_error_model,
    pair_term,
    predicted_variance,
    squared_gradient,
    squared_laplacian,
)
from monai_probreg.uncertainty.residual import residual_variance

SIZE, GRID = (16, 18, 20), (8, 9, 10)
NAMES = list(ERROR_FEATURES)


def _pair(displacement=None):
    generator = torch.Generator().manual_seed(0)
    fixed = torch.zeros(1, 1, *SIZE)
    fixed[0, 0, 3:-3, 4:-4, 5:-5] = 0.5 + 0.1 * torch.rand(10, 10, 10, generator=generator)
    warped = fixed.roll(1, dims=2)
    mean = 0.1 * torch.randn(1, 3, *GRID, generator=generator)
    log_var = torch.full((1, 3, *GRID), math.log(0.01))
    if displacement is None:
        displacement = torch.nn.functional.interpolate(mean, size=SIZE, mode="trilinear")
    return warped, fixed, mean, log_var, displacement


def test_one_feature_per_name_on_the_image_grid():
    features = error_features(*_pair())
    assert features.shape == (1, len(ERROR_FEATURES), *SIZE) and bool(torch.isfinite(features).all())


def test_the_first_feature_is_the_calibrations_residual_upsampled_as_the_posterior():
    warped, fixed, mean, log_var, displacement = _pair()
    residual = torch.nn.functional.interpolate(residual_variance(warped, fixed, GRID), size=SIZE, mode="trilinear")
    assert torch.allclose(
        error_features(warped, fixed, mean, log_var, displacement)[0, 0], (residual[0, 0] + LOG_FLOOR).log()
    )


def test_the_network_variance_and_the_intensity_are_read_as_given():
    warped, fixed, mean, log_var, displacement = _pair()
    features = error_features(warped, fixed, mean, log_var, displacement)[0]
    variance = features[NAMES.index("log network velocity variance")]
    assert torch.allclose(variance, torch.full_like(variance, math.log(0.01 + LOG_FLOOR)))
    assert torch.equal(features[NAMES.index("fixed intensity")], fixed[0, 0])


def test_a_uniform_shift_has_no_bending_and_its_length():
    shift = torch.zeros(1, 3, *SIZE)
    shift[:, 1] = 2.0
    features = error_features(*_pair(shift))[0]
    for window in (5, 9, 15):
        bending = features[NAMES.index(f"log squared Laplacian of the displacement, {window}-voxel box")]
        assert torch.allclose(bending, torch.full_like(bending, math.log(LOG_FLOOR)))
    length = features[NAMES.index("log displacement length")]
    assert torch.allclose(length, torch.full_like(length, math.log(2.0)))


def test_a_parabola_bends_by_its_second_derivative():
    # u_0 = x^2 along the first axis: Laplacian 2, squared 4 away from the borders (replicated) and boxes
    coord = torch.arange(SIZE[0], dtype=torch.float32).view(-1, 1, 1).expand(SIZE)
    field = torch.zeros(1, 3, *SIZE)
    field[0, 0] = 0.01 * coord.square()
    features = error_features(*_pair(field))[0]
    bending = features[NAMES.index("log squared Laplacian of the displacement, 5-voxel box")]
    assert torch.allclose(bending[3:-3, 3:-3, 3:-3], torch.full((10, 12, 14), math.log(4e-4)), atol=1e-4)


def test_the_foreground_fraction_is_one_deep_inside_and_zero_far_outside():
    fixed = torch.zeros(1, 1, 40, 40, 40)
    fixed[0, 0, 10:30, 10:30, 10:30] = 0.6
    grid = (20, 20, 20)
    features = error_features(
        fixed, fixed, torch.zeros(1, 3, *grid), torch.zeros(1, 3, *grid), torch.zeros(1, 3, 40, 40, 40)
    )
    inside = features[0, NAMES.index("fixed foreground fraction, 15-voxel box")]
    assert float(inside[20, 20, 20]) == pytest.approx(1.0) and float(inside[0, 0, 0]) == 0.0


def test_the_prediction_is_the_exponential_of_the_linear_model_averaged_onto_the_velocity_grid():
    pair = _pair()
    features = error_features(*pair)
    coefficients = np.linspace(-0.5, 0.5, len(ERROR_FEATURES) + 1)
    linear = (features * torch.as_tensor(coefficients[:-1], dtype=torch.float32).view(1, -1, 1, 1, 1)).sum(1)
    expected = torch.nn.functional.avg_pool3d((linear + coefficients[-1]).exp()[:, None], 2)
    assert torch.allclose(predicted_variance(tuple(coefficients), *pair), expected, rtol=1e-5)


def test_the_fit_recovers_a_known_model():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=len(ERROR_FEATURES) + 1)
    features = [rng.normal(size=(500, len(ERROR_FEATURES))) for _ in range(3)]
    squared = [np.exp(f @ truth[:-1] + truth[-1]) for f in features]
    assert fit_error_model(features, squared, 1e-12) == pytest.approx(tuple(truth), abs=1e-6)


def test_pair_term_reads_the_residual_without_an_error_model_and_the_prediction_with_one():
    pair = _pair()
    assert torch.equal(pair_term(None, *pair), residual_variance(pair[0], pair[1], GRID))
    constant = (0.0,) * len(ERROR_FEATURES) + (math.log(0.5),)
    assert torch.allclose(pair_term(constant, *pair), torch.full((1, 1, *GRID), 0.5))


@pytest.mark.parametrize(
    "coefficients", [(), (1.0,) * len(ERROR_FEATURES), (float("inf"),) * 13, (None,) * 13, (False,) * 13]
)
def test_a_bad_error_model_is_refused(coefficients):
    with pytest.raises(ValueError, match="an error model is 13 finite numbers"):
        check_error_model(coefficients)
    check_error_model(None)  # no error model: the residual


def test_mismatched_images_are_refused():
    warped, fixed, mean, log_var, displacement = _pair()
    with pytest.raises(ValueError, match=r"expected the warped and fixed images \(1, 1, \*S\)"):
        error_features(warped[..., :-1], fixed, mean, log_var, displacement)


def test_a_posterior_of_another_shape_is_refused():
    warped, fixed, mean, log_var, displacement = _pair()
    with pytest.raises(ValueError, match=r"expected mean and log_var \(1, 3, \*V\)"):
        error_features(warped, fixed, mean, log_var[:, :2], displacement)


def test_a_displacement_of_another_grid_is_refused():
    warped, fixed, mean, log_var, displacement = _pair()
    with pytest.raises(ValueError, match=r"expected a displacement \(1, 3, \*\(16, 18, 20\)\)"):
        error_features(warped, fixed, mean, log_var, displacement[..., :-1])


def test_the_fit_refuses_mismatched_or_empty_cases():
    with pytest.raises(ValueError, match="expected one features array per squared-error array"):
        fit_error_model([np.zeros((3, len(ERROR_FEATURES)))], [], 1e-6)
    with pytest.raises(ValueError, match=r"expected features \(N, 12\) and N squared errors"):
        fit_error_model([np.zeros((3, 5))], [np.ones(3)], 1e-6)
    with pytest.raises(ValueError, match="must be finite"):
        fit_error_model([np.full((3, len(ERROR_FEATURES)), np.nan)], [np.ones(3)], 1e-6)


@pytest.mark.parametrize("shape", [(5, 2, 7), (6, 9, 4), (1, 4, 3)])
def test_the_squared_gradient_is_torchs_gradient_squared(shape):
    image = torch.rand(1, 1, *shape, generator=torch.Generator().manual_seed(1))
    axes = [a for a in range(2, 5) if image.shape[a] > 1]
    expected = sum(g.square() for g in torch.gradient(image, dim=tuple(axes)))
    assert torch.allclose(squared_gradient(image), expected, atol=1e-6)


def test_the_squared_laplacian_is_the_explicit_neighbour_sum():
    field = torch.rand(1, 3, 5, 6, 7, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    padded = torch.nn.functional.pad(field, [1] * 6, mode="replicate")
    expected = torch.zeros(1, 1, 5, 6, 7, dtype=torch.float64)
    for c in range(3):
        for i in range(5):
            for j in range(6):
                for k in range(7):
                    p = padded[0, c]
                    centre = p[i + 1, j + 1, k + 1]
                    neighbours = (
                        p[i, j + 1, k + 1]
                        + p[i + 2, j + 1, k + 1]
                        + p[i + 1, j, k + 1]
                        + p[i + 1, j + 2, k + 1]
                        + p[i + 1, j + 1, k]
                        + p[i + 1, j + 1, k + 2]
                    )
                    expected[0, 0, i, j, k] += (neighbours - 6 * centre) ** 2
    assert torch.allclose(squared_laplacian(field), expected)
    assert squared_laplacian(field).shape == (1, 1, 5, 6, 7)
