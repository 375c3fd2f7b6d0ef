"""A displacement resized onto a box of a finer grid only, by one small matrix per axis.

:func:`~monai_probreg.blocks.integration.resize_displacement` resizes a whole field (``F.interpolate``, linear,
``align_corners=True``); the test-time refinement then needs only the box of the finer grid where its image term can
change (:func:`~monai_probreg.losses.lncc.support_box`), and cropping a resized whole grid pays for the voxels outside
the box twice (the interpolation, and the zeros its slice's backward pass fills). :func:`resize_displacement_box`
gives the same values on the box alone (float rounding apart): linear interpolation with ``align_corners=True`` is
separable, so along each axis it is a matrix of two nonzero weights per row (:func:`interpolation_matrix`), and the
three products are matrix multiplications whose backward pass autograd takes as the transposed products.
Written by hand: torch and MONAI resize whole grids only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["interpolation_matrix", "resize_displacement_box"]


def interpolation_matrix(source: int, target: int, start: int, stop: int, dtype: torch.dtype) -> Tensor:
    """(stop - start, source) weights of linear interpolation with ``align_corners=True`` from a grid of ``source``
    voxels to voxels ``start .. stop - 1`` of a grid of ``target`` voxels over the same extent: row i holds the two
    weights of target voxel ``start + i`` at position ``(start + i) (source - 1) / (target - 1)`` of the source grid
    (one weight of 1 where it falls on a source voxel). The positions are computed in float64, then cast."""
    if source < 2 or target < 2:
        raise ValueError(f"both grids need at least 2 voxels; got {source} -> {target}")
    if not 0 <= start < stop <= target:
        raise ValueError(f"expected 0 <= start < stop <= {target} (the target grid); got {start}, {stop}")
    position = torch.arange(start, stop, dtype=torch.float64) * ((source - 1) / (target - 1))
    lower = position.floor().clamp(max=source - 2).long()  # the last voxel interpolates from its left neighbour
    upper_weight = position - lower
    weights = torch.zeros(stop - start, source, dtype=torch.float64)
    weights.scatter_(1, lower[:, None], (1.0 - upper_weight)[:, None])
    weights.scatter_add_(1, (lower + 1)[:, None], upper_weight[:, None])
    return weights.to(dtype)


def resize_displacement_box(
    ddf: Tensor, spatial_size: Sequence[int], region: tuple[Sequence[int], Sequence[int]]
) -> Tensor:
    """:func:`~monai_probreg.blocks.integration.resize_displacement` of ``ddf`` (B, D, *n) onto the grid
    ``spatial_size`` (*m, same extent), only inside ``region`` = (starts, stops) of that grid: (B, D, *(stops -
    starts)), in voxels of the target grid (component k times ``(m_k - 1) / (n_k - 1)``). Differentiable in ``ddf``;
    2-d and 3-d."""
    spatial_dims = ddf.ndim - 2
    size = [int(s) for s in spatial_size]
    starts, stops = ([int(i) for i in r] for r in region)
    if spatial_dims not in (2, 3) or ddf.shape[1] != spatial_dims:
        raise ValueError(f"expected a (B, D, *S) field with D = 2 or 3 spatial dims; got {tuple(ddf.shape)}")
    if not len(size) == len(starts) == len(stops) == spatial_dims:
        raise ValueError(f"expected {spatial_dims} target sizes, starts and stops; got {size}, {starts} and {stops}")
    source = [int(n) for n in ddf.shape[2:]]
    scale = torch.tensor([(m - 1) / (n - 1) for n, m in zip(source, size)], dtype=ddf.dtype, device=ddf.device)
    field = ddf * scale.view([1, spatial_dims] + [1] * spatial_dims)  # linear: scale the small field first
    matrices = [
        interpolation_matrix(n, m, a, b, ddf.dtype).to(ddf.device) for n, m, a, b in zip(source, size, starts, stops)
    ]
    # one axis at a time, the last first (it is contiguous): each product keeps the other axes as batch dimensions
    field = field @ matrices[-1].T
    if spatial_dims == 3:
        field = torch.matmul(matrices[1], field)  # (b1, n1) @ (..., n1, b2), broadcast over (B, D, n0)
    batch, channels, rest = field.shape[0], field.shape[1], list(field.shape[3:])
    flat = field.reshape(batch * channels, source[0], -1)
    return (matrices[0] @ flat).view(batch, channels, stops[0] - starts[0], *rest)
