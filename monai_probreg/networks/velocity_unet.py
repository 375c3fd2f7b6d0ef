"""The paper's ``def_psi(x, y)``: a UNet from (moving, fixed) to the velocity posterior's mean and log-variance.

Architecture (the published VoxelMorph-diff code, defaults shown):

- input: moving and fixed concatenated, 2 channels, spatial size a multiple of 2**len(enc_channels);
- encoder: one stride-2 3x3(x3) conv per level, ``enc_channels = (16, 32, 32, 32)`` -> 1/16 resolution;
- decoder: ``dec_channels[0]`` conv at the bottom, then one stage per ``dec_channels[1 : 1 + n_up]`` of
  (upsample x2, concatenate the encoder skip, conv) up to the velocity grid, then the remaining
  ``dec_channels`` as plain convs there. With ``int_downsize = 2`` that is 3 stages and one 16-filter conv;
- LeakyReLU(0.2) after every conv (MONAI ``Convolution`` blocks);
- two 3x3(x3) heads (written here, MONAI has no variational head): mean (weights N(0, 1e-5), bias 0) and
  log-variance (weights N(0, 1e-10), bias -10), both on the velocity grid of size ``S / int_downsize``;
- the log-variance is softly bounded to (:data:`LOG_VAR_MIN`, :data:`LOG_VAR_MAX`) = (-30, 10) by
  :func:`bound_log_var`, so ``exp(log_var)`` (KL, sampling) cannot overflow (e^10 ~ 2.2e4, under float16's 6.5e4)
  and ``-log_var`` in the KL stays finite. It is exactly the identity on [-25, 5] (the initial -10 and trained values,
  about -7 to -3 on LPBA40, are untouched) and saturates smoothly outside, with a positive gradient.

Shapes: moving, fixed (B, 1, *S) -> VelocityPosterior(mean, log_var), each (B, spatial_dims, *S / int_downsize).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from monai.networks.blocks import Convolution
from torch import Tensor, nn

from monai_probreg.utils.tensors import shape_str

__all__ = ["VelocityPosterior", "VelocityUNet", "LOG_VAR_MIN", "LOG_VAR_MAX", "LOG_VAR_MARGIN", "bound_log_var"]

# Bounds of the log-variance (velocity-grid voxels^2): sigma from 3e-7 to 150 voxels, far beyond both ends of what a
# registration posterior needs; exp(LOG_VAR_MAX) ~ 2.2e4 is finite even in float16 (max 6.5e4).
LOG_VAR_MIN = -30.0
LOG_VAR_MAX = 10.0
LOG_VAR_MARGIN = 5.0  # width of the smooth saturation inside each bound; identity between them


class VelocityPosterior(NamedTuple):
    """Parameters of ``q(z | moving, fixed)``, both (B, spatial_dims, *velocity_grid), in velocity-grid voxels."""

    mean: Tensor
    log_var: Tensor  # log sigma^2, not log sigma


def bound_log_var(
    raw: Tensor, low: float = LOG_VAR_MIN, high: float = LOG_VAR_MAX, margin: float = LOG_VAR_MARGIN
) -> Tensor:
    """Soft clamp of ``raw`` into (low, high): the identity on [low + margin, high - margin]; beyond, a tanh of width
    ``margin`` that continues it with value and slope 1 at the joint and tends to the bound (+-inf map onto it).
    The gradient is 1 inside and sech^2 > 0 outside: never a hard clamp's exact 0 for finite values nearby."""
    if not (margin > 0 and low + 2 * margin <= high):
        raise ValueError(
            f"expected margin > 0 and low + 2 * margin <= high, got low={low}, high={high}, margin={margin}"
        )
    top, bottom = high - margin, low + margin
    upper = top + margin * torch.tanh((raw - top) / margin)
    lower = bottom + margin * torch.tanh((raw - bottom) / margin)
    return torch.where(raw > top, upper, torch.where(raw < bottom, lower, raw))


class VelocityUNet(nn.Module):
    """UNet producing the posterior over a stationary velocity field.

    Args:
        spatial_dims: 2 or 3.
        in_channels: channels of moving + fixed together (2 for single-channel images).
        enc_channels: filters of the stride-2 encoder convs; its length is the depth.
        dec_channels: bottom conv, then one per upsampling stage, then extra convs at the velocity grid.
        int_downsize: velocity grid = input grid / int_downsize; a power of two, at most 2**depth.
        negative_slope: LeakyReLU slope.
        mean_init_std, log_var_init_std, log_var_init_bias: head initialisation (paper code: 1e-5, 1e-10, -10).
    """

    def __init__(
        self,
        spatial_dims: int = 3,
        in_channels: int = 2,
        enc_channels: Sequence[int] = (16, 32, 32, 32),
        dec_channels: Sequence[int] = (32, 32, 32, 32, 16),
        int_downsize: int = 2,
        negative_slope: float = 0.2,
        mean_init_std: float = 1e-5,
        log_var_init_std: float = 1e-10,
        log_var_init_bias: float = -10.0,
    ) -> None:
        super().__init__()
        if spatial_dims not in (2, 3):
            raise ValueError(f"spatial_dims must be 2 or 3; got {spatial_dims}")
        depth = len(enc_channels)
        if depth < 1:
            raise ValueError("enc_channels must have at least one level")
        if int_downsize < 1 or (int_downsize & (int_downsize - 1)) or int_downsize > 2**depth:
            raise ValueError(f"int_downsize must be a power of two in [1, {2**depth}]; got {int_downsize}")
        num_up = depth - int(math.log2(int_downsize))
        if len(dec_channels) < 1 + num_up:
            raise ValueError(
                f"dec_channels needs at least {1 + num_up} entries (bottom conv + {num_up} upsampling stages) "
                f"for depth {depth} and int_downsize {int_downsize}; got {len(dec_channels)}"
            )
        self.spatial_dims = spatial_dims
        self.int_downsize = int_downsize
        self.divisor = 2**depth

        act = ("leakyrelu", {"negative_slope": negative_slope})

        def conv(cin: int, cout: int, stride: int = 1) -> Convolution:
            return Convolution(spatial_dims, cin, cout, strides=stride, kernel_size=3, act=act, norm=None)

        self.encoder = nn.ModuleList()
        skip_channels = [in_channels]
        cin = in_channels
        for cout in enc_channels:
            self.encoder.append(conv(cin, cout, stride=2))
            skip_channels.append(cout)
            cin = cout
        self.bottom = conv(cin, dec_channels[0])
        cin = dec_channels[0]
        self.up_convs = nn.ModuleList()
        for i in range(num_up):
            skip = skip_channels[depth - 1 - i]  # encoder output one level above the current one
            self.up_convs.append(conv(cin + skip, dec_channels[1 + i]))
            cin = dec_channels[1 + i]
        self.extra_convs = nn.Sequential(
            *[
                conv(c_in, c_out)
                for c_in, c_out in zip([cin, *dec_channels[1 + num_up : -1]], dec_channels[1 + num_up :])
            ]
        )
        if len(dec_channels) > 1 + num_up:
            cin = dec_channels[-1]
        conv_type = nn.Conv3d if spatial_dims == 3 else nn.Conv2d
        self.mean_head = conv_type(cin, spatial_dims, kernel_size=3, padding=1)
        self.log_var_head = conv_type(cin, spatial_dims, kernel_size=3, padding=1)
        with torch.no_grad():
            nn.init.normal_(self.mean_head.weight, 0.0, mean_init_std)
            nn.init.zeros_(self.mean_head.bias)
            nn.init.normal_(self.log_var_head.weight, 0.0, log_var_init_std)
            nn.init.constant_(self.log_var_head.bias, log_var_init_bias)

    def forward(self, moving: Tensor, fixed: Tensor) -> VelocityPosterior:
        # written for torch.jit.script as well as eager (bundle ckpt_export): no comprehension with an ``if``, no
        # ``tuple(shape)``; the messages are the same either way (:func:`_shape_str`)
        if moving.shape != fixed.shape:
            raise ValueError(
                "moving and fixed must have the same shape; got "
                + shape_str(moving.shape)
                + " and "
                + shape_str(fixed.shape)
            )
        if moving.ndim != self.spatial_dims + 2:
            raise ValueError(
                "expected (B, C, *S) inputs with "
                + str(self.spatial_dims)
                + " spatial dims; got shape "
                + shape_str(moving.shape)
            )
        for s in moving.shape[2:]:
            if s % self.divisor:
                raise ValueError(
                    "spatial size must be a multiple of "
                    + str(self.divisor)
                    + " (2**depth); got "
                    + shape_str(moving.shape[2:])
                )
        x = torch.cat([moving, fixed], dim=1)
        skips = [x]
        for layer in self.encoder:
            x = layer(x)
            skips.append(x)
        x = self.bottom(x)
        for i, layer in enumerate(self.up_convs):
            skip = skips[len(self.encoder) - 1 - i]
            x = F.interpolate(x, scale_factor=2.0, mode="nearest")
            x = layer(torch.cat([x, skip], dim=1))
        x = self.extra_convs(x)
        return VelocityPosterior(mean=self.mean_head(x), log_var=bound_log_var(self.log_var_head(x)))
