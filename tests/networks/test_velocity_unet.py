"""VelocityUNet: (moving, fixed) -> posterior mean and log-variance of the velocity, on the velocity grid."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from monai_probreg import VelocityPosterior, VelocityUNet


@pytest.mark.parametrize("int_downsize", [1, 2, 4])
@pytest.mark.parametrize("spatial_dims, shape", [(2, (32, 48)), (3, (16, 16, 32))])
def test_output_shapes(spatial_dims, shape, int_downsize):
    net = VelocityUNet(spatial_dims=spatial_dims, int_downsize=int_downsize)
    moving, fixed = torch.rand(2, 1, *shape), torch.rand(2, 1, *shape)
    out = net(moving, fixed)
    assert isinstance(out, VelocityPosterior)
    expected = (2, spatial_dims, *[s // int_downsize for s in shape])
    assert out.mean.shape == expected
    assert out.log_var.shape == expected


def test_multichannel_inputs():
    net = VelocityUNet(spatial_dims=2, in_channels=4)  # two 2-channel images
    out = net(torch.rand(1, 2, 32, 32), torch.rand(1, 2, 32, 32))
    assert out.mean.shape == (1, 2, 16, 16)


def test_head_initialisation():
    torch.manual_seed(0)
    net = VelocityUNet(spatial_dims=3)
    # 16 * 3 * 27 = 1296 weights per head: the relative standard error of their std is 1/sqrt(2 * 1296) = 2%,
    # so 15% is > 7 standard errors
    assert net.mean_head.weight.std().item() == pytest.approx(1e-5, rel=0.15)
    assert torch.equal(net.mean_head.bias, torch.zeros(3))
    assert net.log_var_head.weight.std().item() == pytest.approx(1e-10, rel=0.15)
    assert torch.equal(net.log_var_head.bias, torch.full((3,), -10.0))

    x = torch.rand(1, 1, 32, 32, 32)
    with torch.no_grad():
        out = net(x, x.flip(2))
    # features are O(1) and the log_var weights 1e-10: log_var is -10 up to ~1e-8, below float32's ulp at 10
    # (9.5e-7); 1e-5 leaves room. The mean is a sum of 432 products of O(1) features and 1e-5 weights: < 1e-3.
    torch.testing.assert_close(out.log_var, torch.full_like(out.log_var, -10.0), atol=1e-5, rtol=0)
    assert out.mean.abs().max() < 1e-3
    assert out.mean.abs().max() > 0  # but not zero: the mean head is random, not zero-initialised


def test_custom_head_initialisation():
    net = VelocityUNet(spatial_dims=2, mean_init_std=0.1, log_var_init_std=0.0, log_var_init_bias=-3.0)
    assert net.mean_head.weight.std().item() == pytest.approx(0.1, rel=0.15)  # 16 * 2 * 9 = 288 weights: 4% SE
    assert torch.equal(net.log_var_head.weight, torch.zeros_like(net.log_var_head.weight))
    assert torch.equal(net.log_var_head.bias, torch.full((2,), -3.0))


def _conv_trace(net, x):
    """(in_channels, out_channels, stride, kernel, input spatial size) of every conv, in execution order."""
    trace = []
    hooks = [
        m.register_forward_hook(
            lambda m, inp, out: trace.append(
                (m.in_channels, m.out_channels, m.stride[0], m.kernel_size[0], tuple(inp[0].shape[2:]))
            )
        )
        for m in net.modules()
        if isinstance(m, (nn.Conv2d, nn.Conv3d))
    ]
    with torch.no_grad():
        net(x, x)
    for h in hooks:
        h.remove()
    return trace


def test_default_architecture_matches_the_paper():
    """VoxelMorph-diff: encoder 16, 32, 32, 32 (stride 2); 32 at 1/16; three (upsample, skip, 32) stages to
    1/2; a 16-filter conv at 1/2; mean and log-variance heads. 3x3x3 kernels, LeakyReLU(0.2) after each conv."""
    net = VelocityUNet(spatial_dims=3)
    n = 32
    trace = _conv_trace(net, torch.rand(1, 1, n, n, n))
    r = lambda f: (n // f,) * 3  # noqa: E731 - input size of a conv running at resolution 1 / f
    assert trace == [
        (2, 16, 2, 3, r(1)),  # encoder: moving + fixed -> 1/2
        (16, 32, 2, 3, r(2)),  # -> 1/4
        (32, 32, 2, 3, r(4)),  # -> 1/8
        (32, 32, 2, 3, r(8)),  # -> 1/16
        (32, 32, 1, 3, r(16)),  # decoder conv at 1/16
        (32 + 32, 32, 1, 3, r(8)),  # upsample to 1/8, concat encoder output at 1/8 (32 ch)
        (32 + 32, 32, 1, 3, r(4)),  # 1/4, skip 32
        (32 + 16, 32, 1, 3, r(2)),  # 1/2, skip 16
        (32, 16, 1, 3, r(2)),  # 16-filter conv at 1/2 (the velocity grid)
        (16, 3, 1, 3, r(2)),  # mean head
        (16, 3, 1, 3, r(2)),  # log-variance head
    ]
    acts = [m for m in net.modules() if isinstance(m, nn.LeakyReLU)]
    assert len(acts) == 9 and all(a.negative_slope == 0.2 for a in acts)  # every conv but the two heads
    assert not any(isinstance(m, nn.modules.batchnorm._NormBase) for m in net.modules())  # no normalisation


def test_full_resolution_velocity_uses_the_input_skip():
    net = VelocityUNet(spatial_dims=2, int_downsize=1)
    trace = _conv_trace(net, torch.rand(1, 1, 32, 32))
    assert trace[-3:] == [(32 + 2, 16, 1, 3, (32, 32)), (16, 2, 1, 3, (32, 32)), (16, 2, 1, 3, (32, 32))]


@pytest.mark.parametrize("shape", [(24, 32), (32, 40), (8, 16)])
def test_size_not_a_multiple_of_16_raises(shape):
    net = VelocityUNet(spatial_dims=2)
    x = torch.rand(1, 1, *shape)
    with pytest.raises(ValueError, match=r"multiple of 16\b"):
        net(x, x)


def test_depth_sets_the_divisor():
    net = VelocityUNet(spatial_dims=2, enc_channels=(8, 8), dec_channels=(8, 8, 8), int_downsize=2)
    x = torch.rand(1, 1, 12, 20)  # multiples of 4 = 2**2
    assert net(x, x).mean.shape == (1, 2, 6, 10)
    with pytest.raises(ValueError, match=r"multiple of 4\b"):
        net(torch.rand(1, 1, 14, 20), torch.rand(1, 1, 14, 20))


def test_mismatched_moving_fixed_shapes_raise():
    net = VelocityUNet(spatial_dims=2)
    with pytest.raises(ValueError, match="same shape"):
        net(torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 48))
    with pytest.raises(ValueError):
        net(torch.rand(1, 1, 32, 32), torch.rand(2, 1, 32, 32))


def test_wrong_number_of_spatial_dims_raises():
    net = VelocityUNet(spatial_dims=3)
    x = torch.rand(1, 1, 32, 32)
    with pytest.raises(ValueError, match="3 spatial dims"):
        net(x, x)


@pytest.mark.parametrize("int_downsize", [0, 3, 6, 32])
def test_invalid_int_downsize_raises(int_downsize):
    with pytest.raises(ValueError, match="int_downsize"):
        VelocityUNet(spatial_dims=2, int_downsize=int_downsize)  # default depth 4: powers of two up to 16


def test_int_downsize_up_to_two_to_the_depth():
    net = VelocityUNet(spatial_dims=2, int_downsize=16)
    x = torch.rand(1, 1, 32, 48)
    assert net(x, x).mean.shape == (1, 2, 2, 3)


@pytest.mark.parametrize(
    "int_downsize, dec_channels",
    [(2, (32, 32, 32)), (1, (32, 32, 32, 32)), (4, (32, 32))],  # need 1 + number of upsampling stages
)
def test_too_few_dec_channels_raises(int_downsize, dec_channels):
    with pytest.raises(ValueError, match="dec_channels"):
        VelocityUNet(spatial_dims=2, int_downsize=int_downsize, dec_channels=dec_channels)


def test_minimal_dec_channels_work():
    net = VelocityUNet(spatial_dims=2, int_downsize=2, dec_channels=(32, 32, 32, 8))  # no extra conv
    x = torch.rand(1, 1, 32, 32)
    assert net(x, x).mean.shape == (1, 2, 16, 16)
    assert net.mean_head.in_channels == 8


def test_invalid_spatial_dims_raises():
    with pytest.raises(ValueError, match="spatial_dims"):
        VelocityUNet(spatial_dims=1)
