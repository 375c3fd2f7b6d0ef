"""Reparameterised sampling of q(z) = N(mean, diag(exp(log_var))); log_var is log sigma^2."""

from __future__ import annotations

import math

import pytest
import torch

from monai_probreg import VelocitySampler, sample_velocity


def _posterior(shape=(2, 3, 4, 5), seed=0):
    g = torch.Generator().manual_seed(seed)
    mean = torch.randn(shape, generator=g, dtype=torch.float64)
    log_var = torch.empty(shape, dtype=torch.float64).uniform_(-3.0, 1.0, generator=g)  # sigma in [0.22, 1.65]
    return mean, log_var


def test_samples_have_the_posterior_mean_and_std():
    mean, log_var = _posterior()
    n = 20000
    z = sample_velocity(mean, log_var, num_samples=n, generator=torch.Generator().manual_seed(1))
    assert z.shape == (n, *mean.shape)
    sigma = torch.exp(0.5 * log_var)  # exp(log_var / 2), not exp(log_var)
    # standard errors: of the sample mean sigma / sqrt(n), of the sample std ~ sigma / sqrt(2 n). Over 120
    # elements, a 5-standard-error bound fails with probability ~1e-4 for a random seed (fixed here anyway).
    mean_err = (z.mean(0) - mean).abs() / (sigma / math.sqrt(n))
    std_err = (z.std(0) - sigma).abs() / (sigma / math.sqrt(2 * n))
    assert mean_err.max() < 5.0
    assert std_err.max() < 5.0


def test_reparameterisation_gradients():
    mean, log_var = _posterior()
    mean.requires_grad_()
    log_var.requires_grad_()
    k = 3
    gen = torch.Generator().manual_seed(2)
    z = sample_velocity(mean, log_var, num_samples=k, generator=gen)
    z.sum().backward()
    eps = torch.randn((k, *mean.shape), dtype=mean.dtype, generator=torch.Generator().manual_seed(2))
    # z = mean + exp(log_var / 2) * eps: dz/dmean = 1 per sample, dz/dlog_var = exp(log_var / 2) * eps / 2.
    # 1e-12: float64, the same eps (same generator seed), only rounding differs
    torch.testing.assert_close(mean.grad, torch.full_like(mean, float(k)), atol=1e-12, rtol=0)
    expected = (0.5 * torch.exp(0.5 * log_var.detach()) * eps).sum(0)
    torch.testing.assert_close(log_var.grad, expected, atol=1e-12, rtol=0)


def test_samples_are_mean_plus_scaled_noise():
    mean, log_var = _posterior()
    z = sample_velocity(mean, log_var, num_samples=2, generator=torch.Generator().manual_seed(5))
    eps = torch.randn((2, *mean.shape), dtype=mean.dtype, generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(z, mean + torch.exp(0.5 * log_var) * eps, atol=1e-12, rtol=0)  # float64 rounding


def test_generator_makes_sampling_reproducible():
    mean, log_var = _posterior()
    a = sample_velocity(mean, log_var, 4, generator=torch.Generator().manual_seed(7))
    b = sample_velocity(mean, log_var, 4, generator=torch.Generator().manual_seed(7))
    c = sample_velocity(mean, log_var, 4, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    assert not torch.equal(a[0], a[1])  # samples within one call are independent draws


def test_sampler_eval_returns_the_mean_exactly():
    mean, log_var = _posterior()
    sampler = VelocitySampler().eval()
    assert sampler(mean, log_var) is mean


def test_sampler_train_returns_one_sample():
    mean, log_var = _posterior()
    sampler = VelocitySampler().train()
    z = sampler(mean, log_var)
    assert z.shape == mean.shape  # one sample, no leading sample axis
    assert not torch.equal(z, mean)
    assert not torch.equal(z, sampler(mean, log_var))


def test_sampler_train_uses_log_var():
    torch.manual_seed(0)  # VelocitySampler draws from the global generator
    mean = torch.zeros(1, 2, 64, 64)
    z = VelocitySampler().train()(mean, torch.full_like(mean, math.log(4.0)))  # sigma = 2
    # 8192 draws: the std of the sample std is ~2 / sqrt(2 * 8192) = 0.016; 0.1 is > 6 of those
    assert abs(z.std().item() - 2.0) < 0.1


@pytest.mark.parametrize("num_samples", [0, -2])
def test_num_samples_below_one_raises(num_samples):
    mean, log_var = _posterior()
    with pytest.raises(ValueError, match="num_samples"):
        sample_velocity(mean, log_var, num_samples=num_samples)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match=r"\(1, 2, 4, 4\).*\(1, 2, 4, 5\)"):
        sample_velocity(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 5))
    with pytest.raises(ValueError):
        VelocitySampler().train()(torch.zeros(1, 2, 4, 4), torch.zeros(1, 3, 4, 4))


def test_scales_multiply_each_samples_deviation_from_the_same_draws():
    mean, log_var = _posterior()
    scales = torch.tensor([2.0, 0.5, 1.0], dtype=torch.float64)
    plain = sample_velocity(mean, log_var, 3, torch.Generator().manual_seed(4))
    scaled = sample_velocity(mean, log_var, 3, torch.Generator().manual_seed(4), scales)
    torch.testing.assert_close(scaled - mean, (plain - mean) * scales.view(3, 1, 1, 1, 1))


def test_scales_of_another_count_are_refused():
    mean, log_var = _posterior()
    with pytest.raises(ValueError, match=r"expected one scale per sample, shape \(3,\)"):
        sample_velocity(mean, log_var, 3, scales=torch.ones(4))
