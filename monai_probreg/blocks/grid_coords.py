"""The one rule from voxel indices to ``torch.nn.functional.grid_sample``'s normalised coordinates.

``grid_sample(..., align_corners=True)`` reads a grid whose last axis holds normalised coordinates in [-1, 1]:
-1 and +1 are the centres of the first and last voxel, so index ``i`` of an axis of ``n`` voxels maps to
``i * 2 / (n - 1) - 1`` (a singleton axis, ``n = 1``, uses ``max(n - 1, 1)``: its voxel maps to -1, as in MONAI).
The grid's last axis is in **reversed** axis order (x, y, z) = (tensor axis -1, ..., tensor axis 2): the package's
fields and indices are in tensor-axis order (channel k along tensor axis 2 + k), so this is the only place
coordinates flip to xyz order.

Two forms of the same rule, both used by the package:

- :func:`index_to_grid` for index tensors (warps, point sampling);
- :func:`index_to_grid_matrix`, the same map as a homogeneous matrix, to fold into an affine chain (the affine
  stage, physical-space resampling).

:func:`normalise_index` (one axis, MONAI's order of operations, so identity grids are bit-identical to MONAI's
``Warp``) and :func:`index_scale` (its slope) are the pieces the one-pass sampling grid of
:mod:`monai_probreg.blocks.warp` is built from. All functions compile with ``torch.jit.script``.

Two orders of operations, on purpose: :func:`normalise_index` computes ``(i * 2) / (n - 1) - 1`` (MONAI's), while
:func:`index_to_grid` and the matrix multiply by the slope first, ``i * (2 / (n - 1)) - 1`` (what a matrix product
does). The two differ by rounding only (an ulp or so); each caller keeps the order it always had, so moving the rule
here changed no caller's result by a bit (``tests/blocks/test_grid_coords.py``).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["index_scale", "normalise_index", "index_to_grid", "index_to_grid_matrix"]


def index_scale(size: int) -> float:
    """Slope of the rule on an axis of ``size`` voxels: one voxel is ``2 / max(size - 1, 1)`` normalised units."""
    return 2.0 / max(size - 1, 1)


def normalise_index(index: Tensor, size: int) -> Tensor:
    """Indices along one axis of ``size`` voxels -> normalised coordinates (no flip: one axis)."""
    return index * 2 / max(size - 1, 1) - 1


def index_to_grid(index: Tensor, spatial_shape: list[int]) -> Tensor:
    """Continuous voxel indices (..., D), last axis in tensor-axis order, on a grid of ``spatial_shape`` (D sizes)
    -> ``grid_sample`` coordinates (..., D), last axis in xyz (reversed) order."""
    dims = len(spatial_shape)
    if index.shape[-1] != dims:
        raise ValueError("index must end in an axis of " + str(dims) + " coordinates; got " + str(index.shape[-1]))
    # grid channel k (x, y, z) is tensor axis dims - 1 - k: the flip to grid_sample's order; slope first, then -1
    # (the matrix form's arithmetic, see the module docstring)
    return torch.stack(
        [index[..., dims - 1 - k] * index_scale(spatial_shape[dims - 1 - k]) - 1 for k in range(dims)], dim=-1
    )


def index_to_grid_matrix(spatial_shape: list[int], dtype: torch.dtype = torch.float64) -> Tensor:
    """:func:`index_to_grid` as a homogeneous ``(D + 1, D + 1)`` matrix: ``M @ [i, 1] = [grid(i), 1]``, the rows of
    the coordinates reversed (xyz order), to compose with affine maps that end in voxel indices."""
    dims = len(spatial_shape)
    matrix = torch.zeros((dims + 1, dims + 1), dtype=dtype)
    for k in range(dims):
        axis = dims - 1 - k  # the flip, as in index_to_grid
        matrix[k, axis] = index_scale(spatial_shape[axis])
        matrix[k, dims] = -1.0
    matrix[dims, dims] = 1.0
    return matrix
