"""ProbRegNet: UNet posterior -> velocity (sample / mean) -> exp at the velocity grid -> resize -> warp moving."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from monai_probreg import (
    PosteriorSamples,
    ProbRegLoss,
    ProbRegNet,
    RegistrationOutput,
    VelocityPosterior,
    compose_displacements,
    integrate_velocity,
    resize_displacement,
    warp_image,
)

SHAPES = {2: (32, 32), 3: (16, 32, 32)}


def _pair(spatial_dims, batch=2, channels=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = SHAPES[spatial_dims]
    return torch.rand(batch, channels, *shape, generator=g), torch.rand(batch, channels, *shape, generator=g)


def _set_heads(net, mean_bias=None, log_var_bias=None):
    """Zero a head's weights and give it a constant bias: a spatially constant mean / log_var."""
    with torch.no_grad():
        if mean_bias is not None:
            net.unet.mean_head.weight.zero_()
            net.unet.mean_head.bias.copy_(torch.as_tensor(mean_bias))
        if log_var_bias is not None:
            net.unet.log_var_head.weight.zero_()
            net.unet.log_var_head.bias.fill_(log_var_bias)


@pytest.mark.parametrize("bidirectional", [False, True])
@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_output_structure_and_shapes(spatial_dims, bidirectional):
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=spatial_dims, bidirectional=bidirectional)
    moving, fixed = _pair(spatial_dims)
    out = net(moving, fixed)
    assert isinstance(out, RegistrationOutput)
    assert out._fields == (
        "warped",
        "displacement",
        "velocity",
        "velocity_mean",
        "velocity_log_var",
        "inverse_displacement",
        "warped_fixed",
    )  # same fields whatever the flags
    shape = SHAPES[spatial_dims]
    vel_shape = (2, spatial_dims, *[s // 2 for s in shape])  # default int_downsize = 2
    assert out.warped.shape == moving.shape
    assert out.displacement.shape == (2, spatial_dims, *shape)
    assert out.velocity.shape == vel_shape
    assert out.velocity_mean.shape == vel_shape
    assert out.velocity_log_var.shape == vel_shape
    if bidirectional:
        assert out.inverse_displacement.shape == (2, spatial_dims, *shape)
        assert out.warped_fixed.shape == fixed.shape
    else:
        assert out.inverse_displacement is None
        assert out.warped_fixed is None


def test_multichannel_images():
    net = ProbRegNet(spatial_dims=2, in_channels=2, bidirectional=True)
    moving, fixed = _pair(2, channels=2)
    out = net(moving, fixed)
    assert out.warped.shape == (2, 2, 32, 32)
    assert out.warped_fixed.shape == (2, 2, 32, 32)
    assert out.displacement.shape == (2, 2, 32, 32)


@pytest.mark.parametrize("int_downsize", [1, 4])
def test_int_downsize_sets_the_velocity_grid(int_downsize):
    net = ProbRegNet(spatial_dims=2, int_downsize=int_downsize)
    out = net(*_pair(2))
    assert out.velocity_mean.shape == (2, 2, 32 // int_downsize, 32 // int_downsize)
    assert out.displacement.shape == (2, 2, 32, 32)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_eval_is_deterministic_and_uses_the_mean(spatial_dims):
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=spatial_dims, bidirectional=True).eval()
    _set_heads(net, log_var_bias=0.0)  # sigma = 1: sampling would be obvious
    moving, fixed = _pair(spatial_dims)
    with torch.no_grad():
        a, b = net(moving, fixed), net(moving, fixed)
    assert torch.equal(a.velocity, a.velocity_mean)
    for name in ("warped", "displacement", "velocity", "inverse_displacement", "warped_fixed"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_train_mode_samples(spatial_dims):
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=spatial_dims).train()
    _set_heads(net, log_var_bias=0.0)  # log sigma^2 = 0: unit-variance noise around the mean
    moving, fixed = _pair(spatial_dims)
    a, b = net(moving, fixed), net(moving, fixed)
    assert not torch.equal(a.velocity, a.velocity_mean)
    assert not torch.equal(a.velocity, b.velocity)
    # thousands of unit-variance draws: the sample std of (velocity - mean) is 1 within a few percent
    assert (a.velocity - a.velocity_mean).std().item() == pytest.approx(1.0, abs=0.1)
    assert (a.velocity_log_var == 0).all()


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_zero_mean_head_gives_identity(spatial_dims):
    net = ProbRegNet(spatial_dims=spatial_dims, bidirectional=True).eval()
    _set_heads(net, mean_bias=torch.zeros(spatial_dims))
    moving, fixed = _pair(spatial_dims)
    with torch.no_grad():
        out = net(moving, fixed)
    assert torch.equal(out.displacement, torch.zeros_like(out.displacement))  # exact
    assert torch.equal(out.inverse_displacement, torch.zeros_like(out.displacement))
    # identity warp: exact up to MONAI's index normalisation round trip (sizes 16, 32 have n - 1 not a power
    # of two), i.e. a few float32 ulps on intensities in [0, 1]
    torch.testing.assert_close(out.warped, moving, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.warped_fixed, fixed, atol=1e-6, rtol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_sample_returns_k_different_displacements(spatial_dims):
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=spatial_dims).eval()  # sample() ignores the mode
    _set_heads(net, log_var_bias=-2.0)
    moving, fixed = _pair(spatial_dims)
    k = 3
    samples = net.sample(moving, fixed, num_samples=k, generator=torch.Generator().manual_seed(0))
    assert isinstance(samples, PosteriorSamples)
    assert samples.displacements.shape == (k, 2, spatial_dims, *SHAPES[spatial_dims])
    for i in range(k):
        for j in range(i + 1, k):
            assert not torch.equal(samples.displacements[i], samples.displacements[j])
    with torch.no_grad():
        out = net(moving, fixed)
    assert torch.equal(samples.velocity_mean, out.velocity_mean)
    assert torch.equal(samples.velocity_log_var, out.velocity_log_var)
    again = net.sample(moving, fixed, num_samples=k, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.displacements, samples.displacements)  # reproducible with a generator


def test_sample_is_sample_velocity_then_integrate():
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=2).eval()
    _set_heads(net, log_var_bias=-1.0)
    moving, fixed = _pair(2)
    samples = net.sample(moving, fixed, num_samples=2, generator=torch.Generator().manual_seed(3))
    eps = torch.randn((2, *samples.velocity_mean.shape), generator=torch.Generator().manual_seed(3))
    z = samples.velocity_mean + math.exp(-0.5) * eps
    for k in range(2):  # the batched (K * B) integration equals integrating each sample on its own
        expected = resize_displacement(integrate_velocity(z[k]), (32, 32))
        # 1e-5: same operations in a different batch layout; float32 rounding only
        torch.testing.assert_close(samples.displacements[k], expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_constant_velocity_is_a_translation_scaled_to_the_image_grid(spatial_dims):
    """Mean head weights 0, bias b: velocity = b on the half-resolution grid V = S / 2, which integrates to the
    translation b (border padding) and is resized to b (S - 1) / (V - 1) image voxels, not 2 b."""
    shape = SHAPES[spatial_dims]
    bias = torch.tensor([0.6, -0.9, 0.45][:spatial_dims])
    # fp32: a bf16 UNet (the default on CPUs with native bf16) rounds the bias to 8 bits of mantissa (0.6 -> 0.6016);
    # this test pins the geometry to 1e-5, the bf16 bounds are in test_acceleration.py
    net = ProbRegNet(spatial_dims=spatial_dims, bidirectional=True, unet_precision="fp32").eval()
    _set_heads(net, mean_bias=bias)
    moving, fixed = _pair(spatial_dims)
    with torch.no_grad():
        out = net(moving, fixed)
    scale = torch.tensor([(s - 1) / (s // 2 - 1) for s in shape])  # 31/15 and, in 3D, 15/7 along axis 0
    expected = (bias * scale).view(1, spatial_dims, *[1] * spatial_dims).expand_as(out.displacement)
    # 1e-5: a constant field is integrated and resized exactly up to float32 rounding (values ~1); the gap to
    # 2 b is (S - 1) / (V - 1) - 2 >= 0.067 * |b| > 0.03, far above the tolerance
    torch.testing.assert_close(out.displacement, expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.inverse_displacement, -expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(
        compose_displacements(out.displacement, out.inverse_displacement), torch.zeros_like(expected), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(out.warped, warp_image(moving, expected), atol=1e-5, rtol=0)
    torch.testing.assert_close(out.warped_fixed, warp_image(fixed, -expected), atol=1e-5, rtol=0)


class _FixedPosterior(nn.Module):
    """Stands in for the UNet: returns a given (smooth) posterior whatever the images."""

    def __init__(self, mean, log_var):
        super().__init__()
        self.mean, self.log_var = mean, log_var

    def forward(self, moving, fixed):
        return VelocityPosterior(self.mean, self.log_var)


def test_bidirectional_smooth_field_inverse():
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=2, bidirectional=True).eval()
    g = torch.Generator().manual_seed(0)
    mean = F.interpolate(torch.randn(1, 2, 4, 4, generator=g), size=(32, 32), mode="bilinear", align_corners=True)
    mean = mean * (1.0 / mean.abs().max())  # up to 1 velocity-grid voxel (~2 image voxels)
    net.unet = _FixedPosterior(mean, torch.full_like(mean, -10.0))
    moving, fixed = torch.rand(1, 1, 64, 64), torch.rand(1, 1, 64, 64)
    with torch.no_grad():
        out = net(moving, fixed)
    assert out.displacement.abs().max() > 1.5  # image voxels
    m = 8  # 4 velocity-grid voxels: keep away from the faces, where border extrapolation breaks invertibility
    for a, b in ((out.displacement, out.inverse_displacement), (out.inverse_displacement, out.displacement)):
        err = compose_displacements(a, b)[..., m:-m, m:-m].abs().max().item()
        # measured 0.036 / 0.028 image voxels: scaling-and-squaring interpolation error on the velocity grid,
        # plus the linear resize of two curved fields; 0.09 is ~2.5x the worst, while the field reaches 2 voxels
        assert err < 0.09


def _blob(shape, centre, radius=4.0):
    idx = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")
    d2 = sum((i - c) ** 2 for i, c in zip(idx, centre))
    return torch.exp(-d2 / (2 * radius**2))[None, None]


def test_training_reduces_the_loss_on_a_shifted_blob():
    # ~0.6 s on 2 idle CPU cores (30 Adam steps on 32x32); no wall-clock assert: that would be flaky under load
    torch.manual_seed(0)
    moving = _blob((32, 32), (16.0, 16.0))
    fixed = _blob((32, 32), (14.0, 16.0))  # fixed(x) = moving(x + 2 e_0): the ideal displacement is +2 on axis 0
    net = ProbRegNet(spatial_dims=2)
    loss_fn = ProbRegLoss(spatial_dims=2, image_sigma=0.05, prior_lambda=20.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)

    def evaluate():
        net.eval()
        with torch.no_grad():
            out = net(moving, fixed)
            terms = loss_fn(out, moving, fixed)
        net.train()
        return out, terms

    _, before = evaluate()
    for _ in range(30):
        terms = loss_fn(net(moving, fixed), moving, fixed)
        opt.zero_grad()
        terms.total.backward()
        opt.step()
    out, after = evaluate()
    # measured: total 11.19 -> 6.49, image term 1.19 -> 0.09. Bounds at about half the measured gains.
    assert after.total < 0.8 * before.total
    assert after.image < 0.3 * before.image  # it registers, not only fits log_var in the KL
    assert out.displacement[0, 0, 16, 16] > 0.5  # moving towards +2 along axis 0: the pull-back sign
    assert out.displacement[0, 1, 16, 16].abs() < 0.5


def test_network_size_registers_any_input_size_on_its_own_grid():
    """network_size: the UNet runs on a fixed grid; a constant velocity b there (V = network_size / 2) becomes
    b (S - 1) / (V - 1) voxels of the input grid S, whatever S is (here not even a multiple of 16)."""
    net = ProbRegNet(spatial_dims=2, network_size=(32, 32), unet_precision="fp32").eval()  # exact bias, see above
    bias = torch.tensor([0.5, -0.8])
    _set_heads(net, mean_bias=bias)
    moving, fixed = torch.rand(1, 1, 45, 38), torch.rand(1, 1, 45, 38)
    with torch.no_grad():
        out = net(moving, fixed)
    assert out.velocity_mean.shape == (1, 2, 16, 16)
    assert out.displacement.shape == (1, 2, 45, 38)
    expected = (bias * torch.tensor([44 / 15, 37 / 15])).view(1, 2, 1, 1).expand_as(out.displacement)
    torch.testing.assert_close(out.displacement, expected, atol=1e-5, rtol=0)  # constant field: float32 rounding
    with pytest.raises(ValueError, match="network_size"):
        ProbRegNet(spatial_dims=3, network_size=(32, 32))


@pytest.mark.parametrize("samples_per_batch", [1, 2, 3, 5])
def test_sample_batching_does_not_change_the_samples(samples_per_batch):
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=2).eval()
    _set_heads(net, log_var_bias=-1.0)
    moving, fixed = _pair(2)
    fused = net.sample(moving, fixed, 3, generator=torch.Generator().manual_seed(5), samples_per_batch=3)
    chunked = net.sample(
        moving, fixed, 3, generator=torch.Generator().manual_seed(5), samples_per_batch=samples_per_batch
    )
    assert chunked.displacements.shape == fused.displacements.shape
    # same draws, other batch layout: float32 rounding only
    torch.testing.assert_close(chunked.displacements, fused.displacements, atol=1e-5, rtol=0)
    default = net.sample(moving, fixed, 3, generator=torch.Generator().manual_seed(5))  # CPU: one at a time
    torch.testing.assert_close(default.displacements, fused.displacements, atol=1e-5, rtol=0)


@pytest.mark.parametrize("bad", [0, -1, True, 1.5])
def test_sample_rejects_bad_samples_per_batch(bad):
    net = ProbRegNet(spatial_dims=2).eval()
    moving, fixed = _pair(2)
    with pytest.raises((ValueError, TypeError), match="samples_per_batch"):
        net.sample(moving, fixed, 2, samples_per_batch=bad)
