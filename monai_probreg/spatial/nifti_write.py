"""Write volumes and displacement fields as NIfTI-1 (``.nii`` / ``.nii.gz``), fast, with the header ITK writes.

Why not ``itk.imwrite``: ITK compresses with zlib at its default level, slowly, and a registration's outputs are
hundreds of MB of float32 (the inverse field on a native scan's grid is the largest), which barely compress at any
level: the time is spent for nothing. Here nibabel builds the file and ISA-L's igzip (``isal``, Python bindings of
Intel's ISA-L) compresses it at level 1: the same gzip format (read by ITK, ANTs, nibabel, FSL, Slicer), about the
same size, an order of magnitude faster, and it releases the GIL, so several files compress in parallel
(:func:`monai_probreg.utils.files.parallel_writes`). The time against zlib: ``experiments/command_levers.py``.

The header is the one ITK writes (checked by ``tests/spatial/test_nifti_write.py`` against ``itk.imwrite``, and read
back by ITK): qform and sform from the grid (code 1, "scanner"), units mm and s, nibabel's RAS affine
``LPS_TO_RAS @ index_to_lps`` (:mod:`monai_probreg.spatial.volume_io`); a vector image (a displacement field in LPS
mm, :mod:`monai_probreg.spatial.physical`) is 5-D ``(I, J, K, 1, C)`` with intent "vector", its components stored as
they are (LPS), exactly as ITK stores a ``DisplacementFieldTransform``'s field and ANTs reads it.

Only NIfTI is written here (:func:`monai_probreg.spatial.checks.is_nifti`); other formats (``.nrrd``, ``.mha``) keep ITK's writer.
"""

from __future__ import annotations

import os
from pathlib import Path

import nibabel as nib
import numpy as np
from isal import igzip

from monai_probreg.spatial.checks import is_nifti
from monai_probreg.spatial.volume_io import LPS_TO_RAS
from monai_probreg.utils.files import atomic_write

__all__ = ["GZIP_LEVEL", "nifti_bytes", "write_nifti"]

GZIP_LEVEL = 1  # ISA-L levels are 0-3; 1 gives zlib-level-1 sizes, far faster (module docstring)
_SCANNER = 1  # NIfTI xform code "scanner", what ITK writes for both qform and sform


def nifti_bytes(array: np.ndarray, index_to_lps: np.ndarray, vector: bool = False) -> bytes:
    """The uncompressed NIfTI-1 file of ``array`` (I, J, K) in index order, or (I, J, K, C) with ``vector``, on the
    grid ``index_to_lps`` (4, 4, LPS mm), with ITK's header (module docstring)."""
    if vector:
        if array.ndim != 4:
            raise ValueError(f"expected a vector image (I, J, K, C); got shape {array.shape}")
        array = array[:, :, :, None, :]  # NIfTI: components on the 5th axis, a time axis of 1 before them
    elif array.ndim != 3:
        raise ValueError(f"expected a 3-D volume (I, J, K); got shape {array.shape}")
    affine = LPS_TO_RAS @ np.asarray(index_to_lps, dtype=np.float64)
    image = nib.Nifti1Image(np.asanyarray(array), affine)
    image.set_qform(affine, code=_SCANNER)
    image.set_sform(affine, code=_SCANNER)
    image.header.set_xyzt_units("mm", "sec")
    image.header["pixdim"][4:] = 0.0  # as ITK: no spacing along the time and component axes (nibabel writes 1)
    if vector:
        image.header.set_intent("vector")
    return image.to_bytes()


def write_nifti(path: str | os.PathLike, array: np.ndarray, index_to_lps: np.ndarray, vector: bool = False) -> Path:
    """Write ``array`` as ``path`` (``.nii.gz``: gzip by ISA-L; ``.nii``: as is), atomically."""
    if not is_nifti(path):
        raise ValueError(f"expected a .nii or .nii.gz path; got {str(path)!r}")
    data = nifti_bytes(array, index_to_lps, vector)
    if str(path).lower().endswith(".gz"):
        data = igzip.compress(data, GZIP_LEVEL, mtime=0)  # no time stamp: the same voxels give the same bytes
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
