"""Read a NIfTI scan without ITK, placed in space exactly as ITK places it, when the header leaves ITK no choice.

Why: ITK is the reference for where a voxel lies (ANTs and Slicer read through it), but on the command line loading
ITK's NIfTI modules is slow, and ITK, the header check and the voxel check each decompressed a ``.nii.gz``
(three passes of zlib over the same bytes). Here the file is decompressed once (ISA-L's igzip, which also checks the
CRC), checked (:func:`monai_probreg.spatial.checks.load_nifti`) and read by nibabel.

Which headers (:func:`itk_geometry`): ITK 5.4's ``NiftiImageIO::SetImageIOOrientationFromNIfTI`` takes the **sform**
when its code is set, its columns are orthogonal once their lengths are removed, and the qform is unset or agrees
with it; the voxel size then comes from ``pixdim``, not from the sform's column lengths, and the direction cosines
from the sform's normalised columns. This module only accepts headers where that rule applies and nothing else can
differ between ITK and nibabel: the sform set and orthonormal (to 1e-6), the qform unset or equal to it (to 1e-4 mm,
the float32 storage of a quaternion), ``pixdim`` equal to the column lengths (relative 1e-4), spatial units mm or
unknown, a scalar 3-D volume (a fourth axis of one), no intent. Any other header returns ``None`` and the caller
reads the file with ITK, which then decides (a qform-only file, forms that disagree, a sheared sform, vectors).
The voxels are nibabel's, with ``scl_slope``/``scl_inter`` applied as ITK applies them. Pinned by
``tests/spatial/test_nifti_read.py``: the same geometry and voxels as ITK's reader on rotated, flipped and
anisotropic grids, and ``None`` for each header this rule leaves to ITK.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np

__all__ = ["itk_geometry"]

_ORTHONORMAL_TOL = 1e-6  # sform columns, once normalised: |c_i . c_j - delta_ij|
_FORMS_AGREE_MM = 1e-4  # qform vs sform, element by element (a quaternion in float32 is good to ~1e-7)
_SPACING_RTOL = 1e-4  # pixdim vs the sform's column lengths
_MM_UNITS = ("mm", "unknown")
_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def itk_geometry(header: nib.Nifti1Header) -> np.ndarray | None:
    """``index_to_lps`` (4, 4) of a scalar 3-D NIfTI volume as ITK 5.4 would place it, or ``None`` when the header is
    one this module leaves to ITK (module docstring)."""
    dims = [int(d) for d in header["dim"][: int(header["dim"][0]) + 1]]
    if dims[0] not in (3, 4) or (dims[0] == 4 and dims[4] != 1) or int(header["intent_code"]) != 0:
        return None
    if header.get_xyzt_units()[0] not in _MM_UNITS or int(header["sform_code"]) <= 0:
        return None
    sform = np.asarray(header.get_sform(), dtype=np.float64)
    columns = sform[:3, :3]
    lengths = np.linalg.norm(columns, axis=0)
    if not np.all(np.isfinite(sform)) or lengths.min() <= 0:
        return None
    direction = columns / lengths
    if np.abs(direction.T @ direction - np.eye(3)).max() > _ORTHONORMAL_TOL:
        return None
    if int(header["qform_code"]) > 0:
        qform = np.asarray(header.get_qform(), dtype=np.float64)
        if not np.all(np.isfinite(qform)) or np.abs(qform - sform).max() > _FORMS_AGREE_MM:
            return None
    spacing = np.asarray(header["pixdim"][1:4], dtype=np.float64)
    if spacing.min() <= 0 or np.abs(spacing - lengths).max() > _SPACING_RTOL * lengths.max():
        return None
    ras = np.eye(4)
    ras[:3, :3] = direction * spacing  # column k: direction k times ITK's spacing (pixdim)
    ras[:3, 3] = sform[:3, 3]
    return _RAS_TO_LPS @ ras
