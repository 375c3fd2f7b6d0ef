"""The first-order displacement spread: closed forms (a constant std, a std that changes along one axis, mm), its
meaning (a velocity perturbation shared by its neighbours integrates to the map times that perturbation), the damping
of the diagonal posterior's samples that the calibration's sample_gain undoes, and one test per bad argument."""

from __future__ import annotations

import math

import pytest
import torch

from monai_probreg.blocks.integration import ScalingAndSquaring, resize_displacement
from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.uncertainty.spread import displacement_variance


@pytest.mark.parametrize(("grid", "size"), [((5, 4), (9, 7)), ((5, 4, 3), (9, 7, 5))])
def test_a_constant_std_is_that_std_in_voxels_of_the_image_grid(grid, size):
    dims = len(grid)
    sigma = torch.tensor([0.2, 0.5, 0.3][:dims])
    log_var = (2 * sigma.log()).view(1, dims, *[1] * dims).expand(1, dims, *grid)
    variance = displacement_variance(log_var, size)
    assert variance.shape == (1, dims, *size)
    # component c along axis c, in voxels of the image grid: times (m_c - 1) / (n_c - 1)
    scale = torch.tensor([(m - 1) / (n - 1) for n, m in zip(grid, size)])
    expected = (sigma * scale).square().view(1, dims, *[1] * dims).expand_as(variance)
    torch.testing.assert_close(variance, expected, rtol=1e-5, atol=0)


def test_between_two_velocity_voxels_the_std_is_interpolated_not_the_variance():
    """Linear interpolation of the std: a voxel half-way between stds 0.1 and 0.3 reads 0.2 (the variances' average
    would read sqrt(0.05) = 0.224; independent noise, sqrt(0.25 (0.01 + 0.09)) = 0.158)."""
    log_var = torch.empty(1, 3, 2, 2, 2)
    log_var[:, :, 0], log_var[:, :, 1] = 2 * math.log(0.1), 2 * math.log(0.3)
    std = displacement_variance(log_var, (3, 2, 2)).sqrt()  # axis 0: 2 -> 3 voxels, its component doubled
    torch.testing.assert_close(std[0, 0, :, 0, 0], torch.tensor([0.2, 0.4, 0.6]), rtol=1e-5, atol=0)
    torch.testing.assert_close(std[0, 1, :, 0, 0], torch.tensor([0.1, 0.2, 0.3]), rtol=1e-5, atol=0)


def test_spacing_gives_mm_squared_per_axis():
    log_var = torch.full((1, 3, 4, 4, 4), 2 * math.log(0.5))
    spacing = (1.0, 2.0, 0.5)
    variance = displacement_variance(log_var, (4, 4, 4), spacing)
    torch.testing.assert_close(variance[0, :, 1, 2, 3], torch.tensor([0.25, 1.0, 0.0625]), rtol=1e-5, atol=0)


def test_a_perturbation_shared_by_its_neighbours_moves_the_displacement_by_the_map():
    """The map's meaning, at the identity: a constant velocity perturbation sigma * xi integrates to the translation
    sigma * xi, resized onto the image grid: the displacement moves by exactly the map's std times xi."""
    grid, size = (6, 5, 4), (11, 9, 7)
    sigma = torch.tensor([0.3, 0.2, 0.4]).view(1, 3, 1, 1, 1)
    xi = torch.tensor([1.0, -2.0, 0.5]).view(1, 3, 1, 1, 1)
    displacement = resize_displacement(ScalingAndSquaring(7)((sigma * xi).expand(1, 3, *grid).contiguous()), size)
    std = displacement_variance((2 * sigma.log()).expand(1, 3, *grid), size).sqrt()
    torch.testing.assert_close(displacement, std * xi, rtol=1e-4, atol=1e-6)


def test_independent_samples_spread_less_than_the_map_which_sample_gain_undoes():
    """Samples of the diagonal posterior are independent per velocity voxel: their displacement variance is the map's
    on the velocity grid's voxels but lower between them (sum_k w_k^2 sigma^2, a pattern of the grid), so their mean
    variance is a fraction kappa of the map's; samples widened by 1 / sqrt(kappa) spread nearly as far as the map on
    average (the integration is not linear in the noise: the fit measures kappa again at the gain,
    CalibrationProbes.sample_gain_for)."""
    torch.manual_seed(0)
    grid, size, samples = (8, 8, 8), (15, 15, 15), 400
    log_var = torch.full((1, 3, *grid), 2 * math.log(0.05))
    mean = torch.zeros(1, 3, *grid)
    draws = sample_velocity(mean, log_var, samples)[:, 0]
    sampled = resize_displacement(ScalingAndSquaring(7)(draws), size).var(0)  # (3, *size)
    mapped = displacement_variance(log_var, size)[0]
    nodes = (slice(None), slice(0, None, 2), slice(0, None, 2), slice(0, None, 2))  # on the velocity grid's voxels
    middles = (slice(None), slice(1, None, 2), slice(1, None, 2), slice(1, None, 2))  # at the cells' centres
    assert float((sampled[nodes] / mapped[nodes]).mean()) == pytest.approx(1.0, abs=0.15)
    assert float((sampled[middles] / mapped[middles]).mean()) == pytest.approx(1 / 8, abs=0.05)
    kappa = float(sampled.mean() / mapped.mean())
    assert 0.2 < kappa < 0.6
    widened = resize_displacement(ScalingAndSquaring(7)(draws / math.sqrt(kappa)), size).var(0)
    assert float(widened.mean() / mapped.mean()) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("shape", [(3, 4, 4, 4), (1, 2, 4, 4, 4), (1, 3, 4, 4, 4, 4)])
def test_a_log_var_of_the_wrong_shape_is_refused(shape):
    with pytest.raises(ValueError, match="expected log_var"):
        displacement_variance(torch.zeros(shape), (4, 4, 4)[: len(shape) - 2])


def test_sizes_of_another_dimension_are_refused():
    with pytest.raises(ValueError, match="expected 3 sizes"):
        displacement_variance(torch.zeros(1, 3, 4, 4, 4), (8, 8))


def test_spacing_of_the_wrong_length_is_refused():
    with pytest.raises(ValueError, match="one spacing per axis"):
        displacement_variance(torch.zeros(1, 3, 4, 4, 4), (8, 8, 8), (1.0, 1.0))


@pytest.mark.parametrize("spacing", [(1.0, 0.0, 1.0), (1.0, -1.0, 1.0)])
def test_spacing_that_is_not_positive_is_refused(spacing):
    with pytest.raises(ValueError, match="spacing must be positive"):
        displacement_variance(torch.zeros(1, 3, 4, 4, 4), (8, 8, 8), spacing)
