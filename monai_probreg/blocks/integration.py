"""Scaling-and-squaring integration of stationary velocity fields, and field resizing.

``exp(v)`` is computed as in Arsigny et al. (2006) and the paper (Sec. 2, T = 7): start from
``u = v / 2**T`` and square ``T`` times, ``u <- u + u o (id + u)``. We build on MONAI's
:class:`~monai.networks.blocks.DVF2DDF` and only swap its warp layer:

- MONAI pads with zeros, so a field sampled just outside the grid reads 0 and the integrated
  displacement shrinks towards the borders (a constant velocity is not integrated to a
  translation near the faces). We pad with ``"border"`` (nearest extrapolation, as the published
  VoxelMorph code does), which makes a constant field an exact fixed point of every squaring.
- MONAI's grid cache never hits; :class:`~monai_probreg.blocks.warp.CachedWarp` fixes that, and with
  ``fast=True`` (default) also builds each squaring's sampling grid in one pass and spreads a single field over
  the CPU threads (see :mod:`monai_probreg.blocks.warp`).

Fields are (B, spatial_dims, *S), in voxels of their own grid, channel k along tensor axis 2 + k.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import List

import torch
import torch.nn.functional as F
from monai.networks.blocks import DVF2DDF
from torch import Tensor, nn

from monai_probreg.blocks.warp import CachedWarp
from monai_probreg.utils.tensors import shape_str

__all__ = ["ScalingAndSquaring", "integrate_velocity", "resize_displacement", "DisplacementResize"]


class ScalingAndSquaring(DVF2DDF):
    """Velocity (B, D, *S) in voxels -> displacement of ``exp(v)``, same shape and units.

    Args:
        num_steps: number of squarings T (the velocity is divided by 2**T first). The paper uses 7.
        padding_mode: how the field is extrapolated outside the grid during composition.
        fast: :class:`~monai_probreg.blocks.warp.CachedWarp`'s fast path (same result up to float32 rounding).

    ``forward(-v)`` gives the displacement of the inverse transform ``exp(-v) = exp(v)^-1``.
    """

    def __init__(self, num_steps: int = 7, padding_mode: str = "border", fast: bool = True) -> None:
        if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
            raise ValueError(f"num_steps must be a positive integer; got {num_steps!r}")
        with warnings.catch_warnings():  # DVF2DDF builds a MONAI Warp we replace below; silence its notice
            warnings.filterwarnings("ignore", message=".*Using PyTorch native grid_sample.*")
            super().__init__(num_steps=num_steps, mode="bilinear", padding_mode=padding_mode)
        # Deviation from DVF2DDF: border padding and a working grid cache (see the module docstring).
        self.warp_layer = CachedWarp(mode="bilinear", padding_mode=padding_mode, fast=fast)

    def forward(self, dvf: Tensor) -> Tensor:
        spatial_dims = dvf.ndim - 2
        if spatial_dims not in (2, 3) or dvf.shape[1] != spatial_dims:
            raise ValueError(
                "velocity must have shape (B, spatial_dims, *S) with spatial_dims in (2, 3); got "
                + shape_str(dvf.shape)
            )
        # DVF2DDF.forward, written out (torch.jit.script has no super()): same operations in the same order
        ddf = dvf / (2**self.num_steps)
        for _ in range(self.num_steps):
            ddf = ddf + self.warp_layer(image=ddf, ddf=ddf)
        return ddf


def integrate_velocity(velocity: Tensor, num_steps: int = 7, padding_mode: str = "border") -> Tensor:
    """Functional form of :class:`ScalingAndSquaring`: displacement of ``exp(velocity)``."""
    return ScalingAndSquaring(num_steps=num_steps, padding_mode=padding_mode)(velocity)


def resize_displacement(ddf: Tensor, spatial_size: List[int]) -> Tensor:
    """Resample a displacement field to another grid over the same extent, rescaling its values.

    With ``align_corners=True`` the first and last voxel centres of both grids coincide, so a voxel
    step on the source grid along axis k is ``(m_k - 1) / (n_k - 1)`` voxels of the target grid
    (n_k source size, m_k target size). Each component is multiplied by that factor; a plain "x2"
    would be off by (n_k - 1) / n_k. Shapes: (B, D, *n) -> (B, D, *m).
    """
    # written for torch.jit.script as well as eager (ProbRegNet's forward); the messages are the same either way
    spatial_dims = ddf.ndim - 2
    size = [int(s) for s in spatial_size]
    if len(size) != spatial_dims or ddf.shape[1] != spatial_dims:
        raise ValueError(
            "expected a (B, "
            + str(len(size))
            + ", *S) field for a "
            + str(len(size))
            + "-d target size; got "
            + shape_str(ddf.shape)
        )
    source = list(ddf.shape[2:])
    if size == source:
        return ddf
    for n in source + size:
        if n < 2:
            raise ValueError(
                "both grids need at least 2 voxels per axis; got " + shape_str(source) + " -> " + shape_str(size)
            )
    mode = "bilinear" if spatial_dims == 2 else "trilinear"
    scale = [(size[k] - 1) / (source[k] - 1) for k in range(spatial_dims)]
    scale_t = torch.tensor(scale, dtype=ddf.dtype, device=ddf.device).view([1, spatial_dims] + [1] * spatial_dims)
    # interpolation is linear: scaling the small field first saves a pass over the large one
    return F.interpolate(ddf * scale_t, size=size, mode=mode, align_corners=True)


class DisplacementResize(nn.Module):
    """``nn.Module`` form of :func:`resize_displacement` to a fixed ``spatial_size``."""

    def __init__(self, spatial_size: Sequence[int]) -> None:
        super().__init__()
        self.spatial_size = tuple(int(s) for s in spatial_size)

    def forward(self, ddf: Tensor) -> Tensor:
        return resize_displacement(ddf, self.spatial_size)
