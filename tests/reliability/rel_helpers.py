"""Builders of damaged and odd image files for the reliability suite (byte-level edits of real NIfTI files)."""

from __future__ import annotations

import gzip
import struct
from pathlib import Path

import nibabel as nib
import numpy as np

# NIfTI-1 header byte offsets (the standard's layout): dim[0..7] int16 at 40, so dim[k] at 40 + 2k
_DIM_OFFSET = 40


def smooth(shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    """A smooth, non-constant float64 field in [0, 1] with a little noise (no two voxels equal)."""
    rng = np.random.default_rng(seed)
    grid = np.meshgrid(*[np.linspace(0.0, 1.0, n) for n in shape], indexing="ij")
    return 0.5 + 0.3 * np.sin(3 * sum(grid)) + 0.1 * grid[0] + 0.01 * rng.random(shape)


def save(
    path: Path,
    data: np.ndarray,
    affine: np.ndarray | None = None,
    dtype: type | None = None,
    slope: float | None = None,
    inter: float = 0.0,
) -> Path:
    """nibabel save with an explicit on-disk dtype (int64 needs it) and optional scl_slope/scl_inter."""
    image = nib.Nifti1Image(data, np.eye(4) if affine is None else affine, dtype=dtype or data.dtype)
    if slope is not None:
        image.header.set_slope_inter(slope, inter)
    nib.save(image, path)
    return path


def _read_bytes(path: Path) -> bytes:
    raw = path.read_bytes()
    return gzip.decompress(raw) if path.name.endswith(".gz") else raw


def _write_bytes(path: Path, raw: bytes) -> Path:
    path.write_bytes(gzip.compress(raw) if path.name.endswith(".gz") else raw)
    return path


def set_header_dim(path: Path, axis: int, size: int) -> Path:
    """Overwrite dim[axis] (1-based, as in the standard) of a NIfTI-1 header, leaving the voxel bytes alone."""
    raw = bytearray(_read_bytes(path))
    struct.pack_into("<h", raw, _DIM_OFFSET + 2 * axis, size)
    return _write_bytes(path, bytes(raw))


def truncate(path: Path, keep: float) -> Path:
    """Keep the first ``keep`` fraction of the file's bytes (as stored: compressed for .gz)."""
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])
    return path


def flip_byte(path: Path, where: float = 0.5) -> Path:
    """Invert one byte at relative position ``where`` of the file as stored."""
    raw = bytearray(path.read_bytes())
    raw[int(len(raw) * where)] ^= 0xFF
    path.write_bytes(bytes(raw))
    return path


def rotation(angles_deg: tuple[float, float, float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()


def affine_of(direction: np.ndarray, spacing: tuple[float, float, float], origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A RAS affine (nibabel's convention) with columns direction[:, k] * spacing[k]."""
    affine = np.eye(4)
    affine[:3, :3] = np.asarray(direction, dtype=np.float64) * np.asarray(spacing, dtype=np.float64)
    affine[:3, 3] = origin
    return affine
