"""Sample a volume at physical points with ITK's resampling semantics (so ITK and ANTs reproduce our outputs).

Points are LPS millimetres, shape (..., 3); the volume maps index -> LPS through ``index_to_lps``
(:mod:`monai_probreg.spatial.volume_io`). A point's continuous index is ``c = index_to_lps^-1 @ p``; as in ITK's
``ResampleImageFilter``:

- **inside** means ``-0.5 <= c_k < n_k - 0.5`` on every axis; outside points get ``fill`` (ITK's default pixel
  value, 0), or with ``outside="border"`` the value of the nearest border position (for extending a
  displacement field beyond its grid);
- **linear**: trilinear interpolation with the neighbours clamped to the grid (ITK's
  ``LinearInterpolateImageFunction``), computed with ``torch.nn.functional.grid_sample(align_corners=True,
  padding_mode="border")`` in float64;
- **nearest**: the voxel ``floor(c + 0.5)`` (ITK's ``NearestNeighborInterpolateImageFunction`` rounds half up;
  ``grid_sample(mode="nearest")`` rounds half to even, so it is not used for labels).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from monai_probreg.blocks.grid_coords import index_to_grid
from monai_probreg.blocks.warp import split_grid_sample
from monai_probreg.spatial.physical import apply_affine
from monai_probreg.spatial.volume_io import Volume

__all__ = ["LinearSampler", "continuous_index", "sample_linear", "sample_nearest"]


def continuous_index(points: np.ndarray, index_to_lps: np.ndarray) -> np.ndarray:
    """LPS points (..., 3) -> continuous voxel indices (..., 3) of the grid ``index_to_lps``."""
    return apply_affine(np.linalg.inv(np.asarray(index_to_lps, dtype=np.float64)), points)


_CHUNK = 1 << 20  # points per step: a step's temporaries stay small (no N x 3 array beyond the caller's own)


def _query_shape(points: np.ndarray | None, index: np.ndarray | None) -> tuple[int, ...]:
    """The shape (..., 3) of what is sampled: ``points``, or ``index`` alone (then ``points`` may be None)."""
    if points is None and index is None:
        raise ValueError("expected points or their index; got neither")
    if points is not None and index is not None and index.shape != np.shape(points):
        raise ValueError(f"expected an index of the points' shape {np.shape(points)}; got {index.shape}")
    return tuple(np.shape(points if points is not None else index))


def _index_chunks(
    points: np.ndarray | None, volume: Volume, index: np.ndarray | None, chunk: int
) -> Iterator[tuple[int, torch.Tensor]]:
    """(start, continuous indices (n, 3) float64) of ``points`` in ``volume``'s grid, ``chunk`` points at a time:
    ``index`` when the caller has it (the callers check both with :func:`_query_shape`), else
    :func:`continuous_index` per chunk."""
    source = (index if index is not None else np.asarray(points, dtype=np.float64)).reshape(-1, 3)
    for start in range(0, source.shape[0], chunk):
        part = np.asarray(source[start : start + chunk], dtype=np.float64)
        yield start, torch.from_numpy(part if index is not None else continuous_index(part, volume.index_to_lps))


def _inside(index: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """ITK's "inside" (module docstring) per point of ``index`` (n, 3)."""
    upper = torch.tensor(shape, dtype=index.dtype) - 0.5
    return ((index >= -0.5) & (index < upper)).all(dim=-1)


class LinearSampler:
    """:func:`sample_linear` of one volume at many sets of points: the volume is made float64 (and channels first)
    once, so a grid sampled slab by slab (:func:`~monai_probreg.spatial.physical.row_slabs`) pays for that copy once.
    Calling it gives exactly :func:`sample_linear`'s values (each point is sampled on its own)."""

    def __init__(self, volume: Volume, fill: float = 0.0, outside: str = "fill", chunk: int = _CHUNK) -> None:
        if outside not in ("fill", "border"):
            raise ValueError(f"outside must be 'fill' or 'border'; got {outside!r}")
        self.volume, self.fill, self.outside, self.chunk = volume, fill, outside, chunk
        data = np.asarray(volume.array, dtype=np.float64)
        self.shape, self.channels = data.shape[:3], data.shape[3:]
        self.source = torch.from_numpy(np.ascontiguousarray(data.reshape(*data.shape[:3], -1).transpose(3, 0, 1, 2)))[
            None
        ]

    def __call__(self, points: np.ndarray | None, index: np.ndarray | None = None) -> np.ndarray:
        """Samples at ``points`` (..., 3) or their continuous ``index`` -> (...[, C]) float64."""
        sizes = [int(n) for n in self.shape]
        query_shape = _query_shape(points, index)
        out = torch.empty((int(np.prod(query_shape[:-1])), self.source.shape[1]), dtype=torch.float64)
        for start, index_part in _index_chunks(points, self.volume, index, self.chunk):
            grid = index_to_grid(index_part, sizes).view(1, -1, 1, 1, 3)  # blocks.grid_coords: normalised, xyz order
            values = split_grid_sample(self.source, grid, mode="bilinear", padding_mode="border")  # on all threads
            out[start : start + len(index_part)] = values[0, :, :, 0, 0].T
            if self.outside == "fill":
                out[start : start + len(index_part)][~_inside(index_part, self.shape)] = self.fill
        return out.numpy().reshape(*query_shape[:-1], *self.channels)


def sample_linear(
    volume: Volume,
    points: np.ndarray | None,
    fill: float = 0.0,
    outside: str = "fill",
    chunk: int = _CHUNK,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Trilinear samples of ``volume.array`` (I, J, K[, C]) at ``points`` (..., 3) -> (...[, C]) float64.

    ``outside``: ``"fill"`` (ITK: ``fill`` outside the half-voxel-extended grid) or ``"border"`` (clamp).
    ``chunk``: points per ``grid_sample`` call (bounds memory on large grids). ``index``: the points'
    :func:`continuous_index` in ``volume``'s grid when the caller has it already (several volumes on one grid, or
    :func:`~monai_probreg.spatial.physical.mapped_index` of a whole grid); ``points`` may then be None.
    """
    return LinearSampler(volume, fill, outside, chunk)(points, index)


def _flat_view(array: np.ndarray) -> tuple[torch.Tensor, tuple[int, ...]]:
    """``array`` (I, J, K) as one flat tensor and the step in it of each axis (in elements): a view of a C- or
    Fortran-ordered array (nibabel reads NIfTI in Fortran order), so that sampling a grid slab by slab copies the
    volume never, not once per slab; a copy for any other layout."""
    if not (array.flags.c_contiguous or array.flags.f_contiguous):
        array = np.ascontiguousarray(array)
    steps = tuple(int(s) // array.itemsize for s in array.strides)
    return torch.from_numpy(array.ravel(order="K")), steps


def sample_nearest(
    volume: Volume, points: np.ndarray | None, fill: int = 0, index: np.ndarray | None = None, chunk: int = _CHUNK
) -> np.ndarray:
    """Nearest-neighbour samples (ITK rounding, half up) at ``points`` (..., 3); ``fill`` outside; input dtype.
    ``index``, ``chunk``: as :func:`sample_linear`'s (no copy of the volume is made, so slabs need no sampler)."""
    flat, steps = _flat_view(volume.array)
    query_shape = _query_shape(points, index)
    out = torch.empty(int(np.prod(query_shape[:-1])), dtype=flat.dtype)
    for start, index_part in _index_chunks(points, volume, index, chunk):
        inside = _inside(index_part, volume.shape)
        nearest = torch.floor(index_part + 0.5).to(torch.int64)  # ITK: half up
        nearest[~inside] = 0  # any voxel: overwritten by ``fill`` below
        values = flat[nearest[:, 0] * steps[0] + nearest[:, 1] * steps[1] + nearest[:, 2] * steps[2]]
        values[~inside] = fill
        out[start : start + len(values)] = values
    return out.numpy().reshape(query_shape[:-1])
