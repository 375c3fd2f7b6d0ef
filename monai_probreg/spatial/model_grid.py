"""The model grid: the fixed image as the network saw it in training, and the exact way back to the fixed grid.

The bundle's preprocessing (:func:`monai_probreg.data.transforms.registration_transforms`) reorients every image to RAS
(nibabel's ``io_orientation``, as MONAI's ``Orientation``) and pads it symmetrically with zeros to a multiple of
``divisor`` (MONAI's ``DivisiblePad``); the network was trained on such arrays, with the subject already on the
atlas grid. :class:`ModelGrid` reproduces that geometry from any fixed :class:`~monai_probreg.spatial.volume_io.Volume`:

- ``to_model(array)``: an array on the fixed grid (index order, any trailing channel axes) -> the model grid
  (axes permuted/flipped to RAS, then zero-padded). Only voxels are re-indexed: no interpolation.
- ``to_fixed(array)``: the exact inverse (crop, then undo the permutation/flips).
- ``index_to_lps``: the model grid's voxel index -> LPS mm. Its voxel centres are the fixed grid's voxel centres
  (plus the padding), so a field in millimetres moves between the two grids by re-indexing alone, while a field
  in **voxels** must first be converted to mm on the grid it was computed on
  (:func:`monai_probreg.spatial.physical.voxel_to_mm`), because the axes are permuted and flipped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from nibabel.orientations import apply_orientation, axcodes2ornt, inv_ornt_aff, io_orientation, ornt_transform

from monai_probreg.spatial.volume_io import LPS_TO_RAS, Volume

__all__ = ["ModelGrid"]


class ModelGrid:
    """Geometry of the network's input grid for a fixed image.

    Args:
        fixed_shape: (I, J, K) of the fixed image.
        fixed_index_to_lps: its (4, 4) index -> LPS mm matrix.
        divisor: pad every axis to a multiple of this (the bundle's ``divisor``); 1 = no padding.
        axcodes: orientation of the model grid, in nibabel's convention (the bundle's is ``"RAS"``).
    """

    def __init__(
        self, fixed_shape: Sequence[int], fixed_index_to_lps: np.ndarray, divisor: int = 16, axcodes: str = "RAS"
    ) -> None:
        if divisor < 1:
            raise ValueError(f"divisor must be >= 1; got {divisor}")
        self.fixed_shape = tuple(int(n) for n in fixed_shape)
        self.fixed_index_to_lps = np.asarray(fixed_index_to_lps, dtype=np.float64)
        fixed_ras = LPS_TO_RAS @ self.fixed_index_to_lps
        self.ornt = ornt_transform(io_orientation(fixed_ras), axcodes2ornt(axcodes))
        self.inverse_ornt = ornt_transform(axcodes2ornt(axcodes), io_orientation(fixed_ras))
        reoriented_ras = fixed_ras @ inv_ornt_aff(self.ornt, self.fixed_shape)
        self.reoriented_shape = tuple(int(self.fixed_shape[int(a)]) for a in self.ornt[:, 0].argsort())
        sizes = [-(-n // divisor) * divisor for n in self.reoriented_shape]
        self.pad_before = tuple((m - n) // 2 for m, n in zip(sizes, self.reoriented_shape))  # MONAI "symmetric"
        self.shape = tuple(sizes)
        shift = np.eye(4)
        shift[:3, 3] = -np.asarray(self.pad_before, dtype=np.float64)
        self.index_to_lps = LPS_TO_RAS @ reoriented_ras @ shift

    @classmethod
    def for_volume(cls, fixed: Volume, divisor: int = 16, axcodes: str = "RAS") -> ModelGrid:
        return cls(fixed.shape, fixed.index_to_lps, divisor, axcodes)

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.index_to_lps[:3, :3], axis=0)

    @property
    def ras_affine(self) -> np.ndarray:
        return LPS_TO_RAS @ self.index_to_lps

    def _crop(self) -> tuple[slice, ...]:
        return tuple(slice(b, b + n) for b, n in zip(self.pad_before, self.reoriented_shape))

    def to_model(self, array: np.ndarray, pad_value: float = 0.0) -> np.ndarray:
        """(I, J, K, ...) on the fixed grid -> (*self.shape, ...) on the model grid (re-indexing + padding)."""
        if tuple(array.shape[:3]) != self.fixed_shape:
            raise ValueError(f"expected an array on the fixed grid {self.fixed_shape}; got {tuple(array.shape)}")
        out = np.full((*self.shape, *array.shape[3:]), pad_value, dtype=array.dtype)
        out[self._crop()] = self._reorient(array, self.ornt)
        return out

    def to_fixed(self, array: np.ndarray) -> np.ndarray:
        """(*self.shape, ...) on the model grid -> (I, J, K, ...) on the fixed grid (the exact inverse)."""
        if tuple(array.shape[:3]) != self.shape:
            raise ValueError(f"expected an array on the model grid {self.shape}; got {tuple(array.shape)}")
        return self.block_to_fixed(array[self._crop()])

    def block_of_rows(self, rows: slice) -> tuple[slice, slice, slice]:
        """The model grid's block (a slice per axis) that holds the fixed grid's rows ``rows`` of its first axis (a
        slab of :func:`~monai_probreg.spatial.physical.row_slabs`, step 1): a per-voxel computation on that block
        then :meth:`block_to_fixed` give those rows of ``to_fixed`` of the computation on the whole model grid."""
        start, stop, step = rows.indices(self.fixed_shape[0])
        if step != 1:
            raise ValueError(f"expected a slice of consecutive rows; got step {step}")
        axis, flipped = int(self.ornt[0, 0]), self.ornt[0, 1] < 0  # where the fixed grid's first axis went
        if flipped:
            start, stop = self.fixed_shape[0] - stop, self.fixed_shape[0] - start
        block = list(self._crop())
        block[axis] = slice(self.pad_before[axis] + start, self.pad_before[axis] + stop)
        return tuple(block)

    def block_to_fixed(self, block: np.ndarray) -> np.ndarray:
        """A block of the model grid cut by :meth:`block_of_rows` (or the whole cropped grid; any trailing channel
        axes) -> the same voxels in the fixed grid's orientation (re-indexing only)."""
        return np.ascontiguousarray(self._reorient(block, self.inverse_ornt))

    @staticmethod
    def _reorient(array: np.ndarray, ornt: np.ndarray) -> np.ndarray:
        # nibabel's apply_orientation handles the first len(ornt) axes and keeps trailing (channel) axes.
        return np.ascontiguousarray(apply_orientation(array, ornt))
