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

import numpy as np
import torch
import torch.nn.functional as F

from monai_probreg.spatial.volume_io import Volume

__all__ = ["continuous_index", "sample_linear", "sample_nearest"]


def continuous_index(points: np.ndarray, index_to_lps: np.ndarray) -> np.ndarray:
    """LPS points (..., 3) -> continuous voxel indices (..., 3) of the grid ``index_to_lps``."""
    lps_to_index = np.linalg.inv(np.asarray(index_to_lps, dtype=np.float64))
    return points @ lps_to_index[:3, :3].T + lps_to_index[:3, 3]


def _index(points: np.ndarray, volume: Volume, index: np.ndarray | None) -> np.ndarray:
    if index is not None:
        if index.shape != np.shape(points):
            raise ValueError(f"expected an index of the points' shape {np.shape(points)}; got {index.shape}")
        return index.reshape(-1, 3)
    return continuous_index(np.asarray(points, dtype=np.float64).reshape(-1, 3), volume.index_to_lps)


def _inside(index: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    upper = np.asarray(shape, dtype=np.float64) - 0.5
    return np.all((index >= -0.5) & (index < upper), axis=-1)


def sample_linear(volume: Volume, points: np.ndarray, fill: float = 0.0, outside: str = "fill",
                  chunk: int = 2_000_000, index: np.ndarray | None = None) -> np.ndarray:
    """Trilinear samples of ``volume.array`` (I, J, K[, C]) at ``points`` (..., 3) -> (...[, C]) float64.

    ``outside``: ``"fill"`` (ITK: ``fill`` outside the half-voxel-extended grid) or ``"border"`` (clamp).
    ``chunk``: points per ``grid_sample`` call (bounds memory on large grids). ``index``: the points'
    :func:`continuous_index` in ``volume``'s grid when the caller has it already (several volumes on one grid).
    """
    if outside not in ("fill", "border"):
        raise ValueError(f"outside must be 'fill' or 'border'; got {outside!r}")
    data = np.asarray(volume.array, dtype=np.float64)
    channels = data.shape[3:]
    source = torch.from_numpy(np.ascontiguousarray(data.reshape(*data.shape[:3], -1).transpose(3, 0, 1, 2)))[None]
    index = _index(points, volume, index)
    sizes = np.asarray(data.shape[:3], dtype=np.float64)
    # align_corners=True: normalised -1 / +1 are the centres of the first / last voxel; grid order is (x, y, z) =
    # (axis 2, axis 1, axis 0) of the (N, C, D, H, W) input, hence the flip.
    normalised = 2.0 * index / np.maximum(sizes - 1.0, 1.0) - 1.0
    out = np.empty((index.shape[0], source.shape[1]), dtype=np.float64)
    for start in range(0, index.shape[0], chunk):
        grid = torch.from_numpy(np.ascontiguousarray(normalised[start:start + chunk, ::-1])).view(1, -1, 1, 1, 3)
        values = F.grid_sample(source, grid, mode="bilinear", padding_mode="border", align_corners=True)
        out[start:start + chunk] = values[0, :, :, 0, 0].T.numpy()
    if outside == "fill":
        out[~_inside(index, data.shape[:3])] = fill
    return out.reshape(*np.shape(points)[:-1], *channels)


def sample_nearest(volume: Volume, points: np.ndarray, fill: int = 0, index: np.ndarray | None = None) -> np.ndarray:
    """Nearest-neighbour samples (ITK rounding, half up) at ``points`` (..., 3); ``fill`` outside; input dtype.
    ``index``: as :func:`sample_linear`'s."""
    index = _index(points, volume, index)
    inside = _inside(index, volume.shape)
    nearest = np.floor(index + 0.5).astype(np.int64)
    out = np.full(index.shape[0], fill, dtype=volume.array.dtype)
    i, j, k = nearest[inside].T
    out[inside] = volume.array[i, j, k]
    return out.reshape(np.shape(points)[:-1])
