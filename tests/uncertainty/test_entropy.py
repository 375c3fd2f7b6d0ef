"""Tests of the uncertainty maps: velocity entropy (closed form) and empirical displacement uncertainty."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Normal

from monai_probreg import DisplacementUncertainty, displacement_uncertainty, velocity_entropy

VEL_SHAPES = {2: (4, 5), 3: (3, 4, 5)}


def _normal_entropy(variance):
    """sum_c H(N(0, var_c)) with torch.distributions, channel axis 1 kept."""
    return Normal(torch.zeros_like(variance), variance.sqrt()).entropy().sum(dim=1, keepdim=True)


@pytest.mark.parametrize("ndims", [2, 3])
def test_velocity_entropy_closed_form(ndims):
    gen = torch.Generator().manual_seed(0)
    log_var = 2.0 * torch.randn(2, ndims, *VEL_SHAPES[ndims], generator=gen, dtype=torch.float64) - 3.0
    ent = velocity_entropy(log_var)
    assert ent.shape == (2, 1, *VEL_SHAPES[ndims])
    expected = 0.5 * torch.log(2 * math.pi * math.e * log_var.exp()).sum(dim=1, keepdim=True)
    # float64, log/exp round trip: 1e-12
    torch.testing.assert_close(ent, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ent, _normal_entropy(log_var.exp()), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("ndims", [2, 3])
def test_velocity_entropy_resized_constant(ndims):
    value = -2.5
    log_var = torch.full((2, ndims, *VEL_SHAPES[ndims]), value)
    size = tuple(2 * n for n in VEL_SHAPES[ndims])
    ent = velocity_entropy(log_var, spatial_size=size)
    assert ent.shape == (2, 1, *size)
    expected = 0.5 * ndims * (math.log(2 * math.pi * math.e) + value)
    # float32; linear interpolation of a constant is a convex combination of equal values: ~1e-7
    torch.testing.assert_close(ent, torch.full_like(ent, expected), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("ndims", [2, 3])
def test_velocity_entropy_resize_keeps_corners_and_range(ndims):
    # align-corners linear resampling: corner voxels are kept and values stay within the input's range
    gen = torch.Generator().manual_seed(1)
    log_var = torch.randn(1, ndims, *VEL_SHAPES[ndims], generator=gen, dtype=torch.float64)
    low = velocity_entropy(log_var)
    size = tuple(2 * n - 1 for n in VEL_SHAPES[ndims])
    high = velocity_entropy(log_var, spatial_size=size)
    assert high.shape == (1, 1, *size)
    for corner in [(0,) * ndims, tuple(n - 1 for n in VEL_SHAPES[ndims])]:
        hi_corner = tuple(2 * c for c in corner)
        # float64 interpolation weights of exactly 1 at the corners
        assert high[(0, 0) + hi_corner].item() == pytest.approx(low[(0, 0) + corner].item(), rel=1e-12)
    assert high.min() >= low.min() - 1e-12 and high.max() <= low.max() + 1e-12


def test_velocity_entropy_same_size_is_identity():
    log_var = torch.randn(1, 3, 3, 4, 5)
    assert torch.equal(velocity_entropy(log_var, spatial_size=(3, 4, 5)), velocity_entropy(log_var))


@pytest.mark.parametrize(
    "shape", [(1, 2, 4, 4, 4), (1, 3, 4, 4), (1, 1, 4), (2, 3)], ids=["2ch-3d", "3ch-2d", "1d", "2d-tensor"]
)
def test_velocity_entropy_bad_shape_raises(shape):
    with pytest.raises(ValueError, match=r"\(B, spatial_dims, \*V\)"):
        velocity_entropy(torch.zeros(shape))


# ---------------------------------------------------------------------------------------------------
# displacement_uncertainty
# ---------------------------------------------------------------------------------------------------

K = 2000
DISP_SHAPES = {2: (4, 5), 3: (3, 4, 5)}


def _gaussian_samples(ndims, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = (2, ndims, *DISP_SHAPES[ndims])
    mean = torch.randn(shape, generator=gen, dtype=torch.float64)
    std = 0.5 + 1.5 * torch.rand(shape, generator=gen, dtype=torch.float64)
    samples = mean + std * torch.randn((K, *shape), generator=gen, dtype=torch.float64)
    return samples, mean, std


@pytest.mark.parametrize("ndims", [2, 3])
def test_displacement_uncertainty_estimates_known_gaussian(ndims):
    samples, mean, std = _gaussian_samples(ndims)
    out = displacement_uncertainty(samples)
    assert isinstance(out, DisplacementUncertainty)
    assert out.mean.shape == mean.shape and out.variance.shape == mean.shape
    assert out.entropy.shape == (2, 1, *DISP_SHAPES[ndims])
    var = std**2
    # Statistical tolerances, 5 standard errors (fixed seed, so deterministic; with <= 120 estimates a
    # 5-sigma excursion would have probability < 1e-4 anyway):
    # sample mean: SE = s / sqrt(K)
    assert ((out.mean - mean).abs() <= 5 * std / math.sqrt(K)).all()
    # unbiased sample variance of a Gaussian: SE = s^2 sqrt(2 / (K - 1)) (~3.2% at K = 2000)
    se_var = var * math.sqrt(2.0 / (K - 1))
    assert ((out.variance - var).abs() <= 5 * se_var).all()
    # entropy: delta method, H_hat - H = 1/2 sum_c log(var_hat_c / s_c^2), each log-ratio with SD sqrt(2/(K-1))
    se_ent = 0.5 * math.sqrt(ndims) * math.sqrt(2.0 / (K - 1))
    true_entropy = _normal_entropy(var)
    assert ((out.entropy - true_entropy).abs() <= 5 * se_ent).all()
    # and the entropy is exactly the closed form of the estimated variance (float64: 1e-12)
    torch.testing.assert_close(out.entropy, _normal_entropy(out.variance), rtol=1e-12, atol=1e-12)


def test_displacement_uncertainty_variance_is_unbiased():
    gen = torch.Generator().manual_seed(3)
    samples = torch.randn(2, 1, 3, 4, 5, 6, generator=gen, dtype=torch.float64)
    out = displacement_uncertainty(samples)
    # K = 2: unbiased variance (K - 1 denominator) is (x1 - x2)^2 / 2; float64
    torch.testing.assert_close(out.variance, (samples[0] - samples[1]) ** 2 / 2, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(out.mean, (samples[0] + samples[1]) / 2, rtol=1e-12, atol=1e-15)


def test_displacement_uncertainty_floors_zero_variance():
    samples = torch.ones(4, 1, 2, 5, 6, dtype=torch.float64)
    out = displacement_uncertainty(samples, eps=1e-12)
    assert torch.equal(out.variance, torch.zeros_like(out.variance))
    expected = 0.5 * 2 * (math.log(2 * math.pi * math.e) + math.log(1e-12))
    # float64: 1e-12 relative
    torch.testing.assert_close(out.entropy, torch.full_like(out.entropy, expected), rtol=1e-12, atol=0)


def test_displacement_uncertainty_needs_two_samples():
    with pytest.raises(ValueError, match=r"at least 2 samples.*got 1"):
        displacement_uncertainty(torch.zeros(1, 1, 3, 4, 4, 4))


@pytest.mark.parametrize(
    "shape",
    [(4, 1, 2, 4, 4, 4), (4, 1, 3, 4, 4), (4, 3, 4, 4, 4), (4, 1, 1, 4)],
    ids=["2ch-3d", "3ch-2d", "no-batch", "1d"],
)
def test_displacement_uncertainty_bad_shape_raises(shape):
    with pytest.raises(ValueError, match=r"\(K, B, spatial_dims, \*S\)"):
        displacement_uncertainty(torch.zeros(shape))


def test_label_entropy_closed_forms():
    from monai_probreg.uncertainty.entropy import label_entropy

    agree = torch.full((4, 3, 3), 7)
    assert torch.all(label_entropy(agree) == 0)
    half = torch.tensor([1, 1, 2, 2]).view(4, 1)
    assert label_entropy(half).item() == pytest.approx(math.log(2))
    distinct = torch.tensor([0, 5, 9, 3]).view(4, 1)
    assert label_entropy(distinct).item() == pytest.approx(math.log(4))


def test_label_entropy_matches_counting():
    from collections import Counter

    from monai_probreg.uncertainty.entropy import label_entropy

    samples = torch.randint(0, 3, (6, 5, 4), generator=torch.Generator().manual_seed(0))
    out = label_entropy(samples)
    for idx in [(0, 0), (2, 3), (4, 1)]:
        counts = Counter(samples[(slice(None),) + idx].tolist())
        expected = -sum(c / 6 * math.log(c / 6) for c in counts.values())
        assert out[idx].item() == pytest.approx(expected, abs=1e-6)


def test_label_entropy_rejects_float_labels():
    from monai_probreg.uncertainty.entropy import label_entropy

    with pytest.raises(ValueError, match="integer"):
        label_entropy(torch.zeros(3, 4))


def test_sampled_moments_keep_a_small_spread_far_from_zero():
    """The streamed float32 sums are of deviations from the first sample: a spread of 0.01 voxel on displacements of
    10^4 voxels keeps its variance (sums of the values themselves in float32 would lose it to cancellation)."""
    from monai_probreg.blocks.sampling import sample_velocity
    from monai_probreg.uncertainty.entropy import sampled_displacement_moments

    mean, log_var = torch.zeros(1, 2, 6, 7), torch.full((1, 2, 6, 7), math.log(0.01**2))
    offset = 1.0e4
    moments = sampled_displacement_moments(
        mean, log_var, lambda z: z + offset, 9, generator=torch.Generator().manual_seed(0), chunk=4
    )
    generator = torch.Generator().manual_seed(0)
    draws = torch.cat([sample_velocity(mean, log_var, n, generator=generator) for n in (4, 4, 1)])
    displacements = (draws + offset).double()  # the same float32 displacements, their moments in float64
    torch.testing.assert_close(moments[1].double(), displacements.var(0, unbiased=True), rtol=1e-3, atol=0)
    torch.testing.assert_close(moments[0].double(), displacements.mean(0), rtol=0, atol=1e-3)
    assert float(moments[1].mean()) == pytest.approx(0.01**2, rel=0.5)
