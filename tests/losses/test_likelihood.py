"""Tests of the image likelihood terms: the paper's Gaussian term and the LNCC factory."""

from __future__ import annotations

import math

import pytest
import torch
from monai.losses import LocalNormalizedCrossCorrelationLoss

from monai_probreg import GaussianImageLoss, gaussian_image_loss, make_image_loss
from monai_probreg.losses.lncc import BoxLNCCLoss

SHAPES = {2: (2, 1, 9, 10), 3: (2, 1, 6, 7, 8)}


def _pair(ndims, seed=0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    return (
        torch.rand(SHAPES[ndims], generator=gen, dtype=dtype),
        torch.rand(SHAPES[ndims], generator=gen, dtype=dtype),
    )


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("sigma", [0.035, 0.5, 2.0])
def test_gaussian_sum_reduction(ndims, sigma):
    warped, fixed = _pair(ndims)
    expected = torch.sum((fixed - warped) ** 2).item() / (2 * sigma**2)
    # float64, identical arithmetic up to the order of the division: 1e-12 relative
    assert gaussian_image_loss(warped, fixed, sigma, "sum").item() == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("sigma", [0.035, 0.5])
def test_gaussian_mean_reduction_is_over_all_elements(ndims, sigma):
    warped, fixed = _pair(ndims)
    n_elements = math.prod(SHAPES[ndims])  # B * C * N
    expected = torch.sum((fixed - warped) ** 2).item() / n_elements / (2 * sigma**2)
    # float64: 1e-12 relative
    assert gaussian_image_loss(warped, fixed, sigma).item() == pytest.approx(expected, rel=1e-12)
    assert gaussian_image_loss(warped, fixed, sigma, "mean").item() == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_gaussian_zero_when_equal(reduction):
    warped, _ = _pair(3)
    assert gaussian_image_loss(warped, warped.clone(), 0.1, reduction).item() == 0.0


def test_gaussian_is_differentiable_with_expected_gradient():
    warped, fixed = _pair(2)
    warped.requires_grad_(True)
    sigma = 0.2
    (grad,) = torch.autograd.grad(gaussian_image_loss(warped, fixed, sigma, "sum"), warped)
    # d/dw (f - w)^2 / (2 sigma^2) = (w - f) / sigma^2; float64
    torch.testing.assert_close(grad, (warped - fixed).detach() / sigma**2, rtol=1e-12, atol=1e-12)


def test_voxelmorph_image_term_conversion():
    # kl.py docstring: VoxelMorph's mean((x - y)^2) / sigma_v^2 is our "mean" Gaussian term with sigma_v / sqrt(2)
    warped, fixed = _pair(3)
    sigma_v = 0.07
    voxelmorph = torch.mean((fixed - warped) ** 2).item() / sigma_v**2
    # float64: 1e-12 relative
    assert gaussian_image_loss(warped, fixed, sigma_v / math.sqrt(2), "mean").item() == pytest.approx(
        voxelmorph, rel=1e-12
    )


@pytest.mark.parametrize("sigma", [0.0, -0.1])
def test_gaussian_bad_sigma_raises(sigma):
    warped, fixed = _pair(2)
    with pytest.raises(ValueError, match=r"image_sigma must be > 0"):
        gaussian_image_loss(warped, fixed, sigma)
    with pytest.raises(ValueError, match=r"image_sigma must be > 0"):
        GaussianImageLoss(sigma)


def test_gaussian_shape_mismatch_raises():
    with pytest.raises(ValueError, match=r"same shape.*\(1, 1, 4, 4\).*\(1, 1, 4, 5\)"):
        gaussian_image_loss(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 5), 0.1)


def test_gaussian_bad_reduction_raises():
    warped, fixed = _pair(2)
    with pytest.raises(ValueError, match=r"reduction must be 'mean' or 'sum'; got 'none'"):
        gaussian_image_loss(warped, fixed, 0.1, reduction="none")


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_gaussian_module_equals_function(reduction):
    warped, fixed = _pair(3)
    module = GaussianImageLoss(0.3, reduction)
    # same code path: bitwise
    assert module(warped, fixed).item() == gaussian_image_loss(warped, fixed, 0.3, reduction).item()


def test_make_image_loss_gaussian():
    module = make_image_loss("gaussian", image_sigma=0.25, reduction="sum")
    assert isinstance(module, GaussianImageLoss)
    assert module.image_sigma == 0.25 and module.reduction == "sum"


@pytest.mark.parametrize("ndims", [2, 3])
def test_make_image_loss_lncc_is_monais_and_minus_one_for_identical_images(ndims):
    module = make_image_loss("lncc", spatial_dims=ndims, lncc_kernel_size=5)
    assert isinstance(module, BoxLNCCLoss) and isinstance(module, LocalNormalizedCrossCorrelationLoss)
    gen = torch.Generator().manual_seed(0)
    shape = (2, 1) + (12,) * ndims
    image = torch.rand(shape, generator=gen, dtype=torch.float64)
    value = module(image, image.clone()).item()
    # squared local NCC of an image with itself is (v^2 + 1e-5) / v^2 per window, v the local sum of squared
    # deviations (~ kernel_vol / 12 >> 1e-5 for uniform noise): the deviation from -1 is < 1e-4
    assert value == pytest.approx(-1.0, abs=1e-4)
    # and an unrelated image scores clearly worse (closer to 0)
    other = torch.rand(shape, generator=gen, dtype=torch.float64)
    assert module(image, other).item() > -0.5


def test_make_image_loss_unknown_name_raises():
    with pytest.raises(ValueError, match=r"one of \('gaussian', 'lncc', 'mind'\); got 'mse'"):
        make_image_loss("mse")
