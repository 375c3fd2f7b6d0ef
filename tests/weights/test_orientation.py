"""Tests of the weight mirroring (the network that sees its inputs mirrored along array axes)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from monai_probreg import ProbRegNet
from monai_probreg.utils.errors import InputError
from monai_probreg.weights.orientation import mirror_state_dict, mirror_weight_file
from monai_probreg.weights.settings import settings_path


def _network(spatial_dims=3, seed=0):
    torch.manual_seed(seed)
    net = ProbRegNet(spatial_dims=spatial_dims, enc_channels=(4, 8), dec_channels=(8, 8, 4), int_downsize=1).eval()
    with torch.no_grad():  # heads far from their near-zero initialisation, so the outputs mean something
        torch.nn.init.normal_(net.unet.mean_head.weight, 0.0, 0.05)
        torch.nn.init.normal_(net.unet.mean_head.bias, 0.0, 0.1)
        torch.nn.init.normal_(net.unet.log_var_head.weight, 0.0, 0.05)
    return net


@pytest.mark.parametrize("spatial_dims, axes", [(2, [0]), (2, [0, 1]), (3, [0, 1]), (3, [2])])
def test_a_stride_one_convolution_is_exactly_equivariant(spatial_dims, axes):
    conv = getattr(torch.nn, f"Conv{spatial_dims}d")(2, spatial_dims, 3, padding=1).double()
    state = {f"unet.mean_head.{k}": v for k, v in conv.state_dict().items()}
    mirrored = mirror_state_dict(state, axes, spatial_dims)
    x = torch.randn(1, 2, *([7, 9, 6][:spatial_dims]), dtype=torch.float64)
    dims = [2 + a for a in axes]
    conv_fn = F.conv3d if spatial_dims == 3 else F.conv2d
    out = conv_fn(torch.flip(x, dims), mirrored["unet.mean_head.weight"], mirrored["unet.mean_head.bias"], padding=1)
    expected = torch.flip(conv(x), dims)
    expected[:, axes] = -expected[:, axes]  # the velocity component along a mirrored axis changes sign
    torch.testing.assert_close(out, expected)


def test_mirroring_twice_gives_the_original_back():
    state = _network().state_dict()
    twice = mirror_state_dict(mirror_state_dict(state, [0, 1]), [0, 1])
    assert twice.keys() == state.keys()
    for name in state:
        torch.testing.assert_close(twice[name], state[name], rtol=0, atol=0)


def test_the_mirrored_network_registers_the_mirrored_pair_like_the_original():
    """The whole UNet (stride-2 convolutions on even sizes sample the mirrored grid one voxel off) is equivariant
    only approximately: the mirrored network's velocity on the mirrored pair, mirrored back, must match the original's
    far better than the original's own velocity on the mirrored pair (what unconverted weights would give)."""
    net = _network()
    mirrored = _network(seed=1)
    mirrored.load_state_dict(mirror_state_dict(net.state_dict(), [0, 1]))
    torch.manual_seed(3)
    moving, fixed = (F.avg_pool3d(torch.rand(1, 1, 20, 24, 16), 5, 1, 2) for _ in range(2))
    dims = [2, 3]
    with torch.no_grad():
        reference = net(moving, fixed).velocity_mean
        converted = mirrored(torch.flip(moving, dims), torch.flip(fixed, dims)).velocity_mean
        unconverted = net(torch.flip(moving, dims), torch.flip(fixed, dims)).velocity_mean
    back = torch.flip(converted, dims)
    back[:, :2] = -back[:, :2]
    naive = torch.flip(unconverted, dims)
    naive[:, :2] = -naive[:, :2]
    err, naive_err = (back - reference).norm() / reference.norm(), (naive - reference).norm() / reference.norm()
    assert err < 0.1 and err < naive_err / 10, (float(err), float(naive_err))  # measured: 0.013 and 1.50


def test_the_weight_file_and_its_settings_are_written(tmp_path):
    net = _network()
    source = tmp_path / "model.pt"
    torch.save(net.state_dict(), source)
    settings_path(source).write_text("{}")
    target = mirror_weight_file(source, tmp_path / "mirrored.pt", [0, 1])
    state = torch.load(target, weights_only=True)
    torch.testing.assert_close(state["unet.mean_head.bias"][:2], -net.state_dict()["unet.mean_head.bias"][:2])
    assert settings_path(target).read_text() == "{}"
    with pytest.raises(InputError, match="other than the source"):
        mirror_weight_file(source, source, [0])


@pytest.mark.parametrize("axes", [[], [3], [-1]])
def test_bad_axes_are_refused(axes):
    with pytest.raises(ValueError, match="axes"):
        mirror_state_dict(_network().state_dict(), axes)


def test_a_state_dict_without_the_velocity_head_is_refused():
    with pytest.raises(KeyError, match="mean_head"):
        mirror_state_dict({"w": torch.zeros(1, 1, 3, 3, 3)}, [0])
