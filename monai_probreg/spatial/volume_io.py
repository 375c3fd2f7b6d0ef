"""Read the scans and label maps given to ``monai-probreg`` with their physical geometry, and validate them.

Conventions (the physical-space conventions of the package; :mod:`monai_probreg.spatial.physical` states them in full):

- A :class:`Volume` holds ``array`` in **index order** ``(i, j, k)``: ITK's index order, which is also nibabel's
  array order. ``itk.GetArrayFromImage`` returns the reverse order ``(k, j, i)``; this module transposes once,
  on reading and on writing, and nowhere else does.
- ``index_to_lps`` (4, 4) maps a voxel index ``(i, j, k, 1)`` to a physical point in ITK's LPS millimetres:
  ``origin + direction @ diag(spacing) @ (i, j, k)``. nibabel's RAS affine is ``diag(-1, -1, 1, 1) @ index_to_lps``.
- ITK reads the geometry (direction, spacing, origin); images are read as float32, label maps as float64 and
  checked to hold non-negative integers, then stored as int32. NIfTI voxels are also checked as stored, with
  nibabel: ITK's NIfTI reader zero-fills a truncated file and turns NaN into 0 without a warning. A NIfTI file whose
  header leaves ITK no choice of geometry is read without ITK, placed exactly as ITK places it
  (:mod:`monai_probreg.spatial.nifti_read`: one decompression instead of three, no ITK IO modules to load).

Every problem with an input raises :class:`InputError` with one line naming the file and the problem, before any
output is written: missing, unreadable, truncated or corrupt file, a header whose size disagrees with the data, not a
3-D scalar volume (2-D, 4-D with more than one volume, an axis of one voxel, vector/RGB pixels), more voxels than
:func:`~monai_probreg.spatial.checks.max_voxels` (checked before the voxels are read), a degenerate geometry, NaN/Inf
voxels, a constant image, a non-integer or negative label map, and label maps on a grid other than their image's
(:func:`check_same_grid`). The checks themselves live in :mod:`monai_probreg.spatial.checks`, shared with the bundle.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import itk
import nibabel as nib
import numpy as np

from monai_probreg.spatial.checks import (
    check_finite,
    check_image_values,
    check_label_values,
    check_nifti_header,
    check_nifti_voxels,
    check_size,
    corrupt_file_error,
    is_nifti,
    load_nifti,
)
from monai_probreg.spatial.nifti_read import itk_geometry
from monai_probreg.utils.errors import InputError

__all__ = [
    "Volume",
    "LPS_TO_RAS",
    "read_image",
    "read_label",
    "read_volume",
    "read_field",
    "check_same_grid",
    "volume_to_itk",
    "volume_from_itk",
    "geometry_of",
]

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse: RAS affine = LPS_TO_RAS @ index_to_lps

# Two headers describe the same grid when they agree to these tolerances. NIfTI stores the affine in float32 and
# the qform as a quaternion (~1e-7 relative); other tools round origins to 1e-4 mm or so. A real grid mismatch
# (a resampled or cropped label map) is at least a fraction of a voxel.
_ORIGIN_TOL_MM = 1e-3
_RELATIVE_TOL = 1e-4


@dataclass(frozen=True)
class Volume:
    """A 3-D volume and its geometry. ``array``: (I, J, K) in index order, or (I, J, K, C) for a vector field
    (C components per voxel, e.g. a displacement in LPS mm); ``index_to_lps``: (4, 4); ``shape``: the grid's
    (I, J, K)."""

    array: np.ndarray
    index_to_lps: np.ndarray
    path: str = ""

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.array.shape[:3])  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.index_to_lps[:3, :3], axis=0)

    @property
    def direction(self) -> np.ndarray:
        return self.index_to_lps[:3, :3] / self.spacing

    @property
    def origin(self) -> np.ndarray:
        return self.index_to_lps[:3, 3].copy()

    @property
    def ras_affine(self) -> np.ndarray:
        """nibabel's affine of this volume (index -> RAS mm)."""
        return LPS_TO_RAS @ self.index_to_lps

    @property
    def axcodes(self) -> str:
        """Orientation code in nibabel's (RAS) convention, e.g. ``"RAS"`` for LPBA40 and MNI files, ``"LPS"`` for DICOM-ordered ones."""
        return "".join(nib.aff2axcodes(self.ras_affine))

    def with_array(self, array: np.ndarray) -> Volume:
        """The same grid holding another array of the same shape."""
        if tuple(array.shape[:3]) != self.shape:
            raise ValueError(f"array shape {tuple(array.shape)} does not match the grid {self.shape}")
        return Volume(array, self.index_to_lps, self.path)


def geometry_of(image: itk.Image) -> np.ndarray:
    """``index_to_lps`` (4, 4) of an ITK image."""
    direction = itk.array_from_matrix(image.GetDirection()).astype(np.float64)
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
    affine = np.eye(4)
    affine[:3, :3] = direction * spacing  # column k = direction[:, k] * spacing[k]
    affine[:3, 3] = np.asarray(image.GetOrigin(), dtype=np.float64)
    return affine


def volume_from_itk(image: itk.Image, path: str = "") -> Volume:
    """ITK image -> :class:`Volume` (a copy, index order)."""
    return Volume(np.ascontiguousarray(itk.array_from_image(image).transpose(2, 1, 0)), geometry_of(image), path)


def volume_to_itk(volume: Volume, dtype: type = np.float32) -> itk.Image:
    """:class:`Volume` -> ITK image of pixel type ``dtype`` (float32, float64, int16, uint8, ...) with its geometry."""
    image = itk.image_from_array(np.ascontiguousarray(volume.array.astype(dtype, copy=False).transpose(2, 1, 0)))
    spacing = volume.spacing
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(o) for o in volume.origin])
    image.SetDirection(itk.matrix_from_array(np.ascontiguousarray(volume.direction)))
    return image


def _check_file(path: Path, role: str) -> None:
    if not path.exists():
        raise InputError(f"{role} {str(path)!r}: no such file")
    if not path.is_file():
        raise InputError(f"{role} {str(path)!r}: is a folder, not an image file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{role} {str(path)!r}: file is not readable (permissions)")
    if path.stat().st_size == 0:
        raise corrupt_file_error(path, role, EOFError())


def _header(path: Path, role: str) -> tuple[list[int], int]:
    """(size per dimension, components per voxel) from the file header; InputError if it cannot be read."""
    _check_file(path, role)
    image_io = itk.ImageIOFactory.CreateImageIO(str(path), itk.CommonEnums.IOFileMode_ReadMode)
    if image_io is None:
        if is_nifti(path):  # ITK cannot even identify a damaged .nii.gz; nibabel says what is wrong
            check_nifti_voxels(check_nifti_header(path, role), path, role)
        raise InputError(
            f"{role} {str(path)!r}: not an image format ITK can read (use NIfTI .nii/.nii.gz, .nrrd, .mha, ...)"
        )
    try:
        image_io.SetFileName(str(path))
        image_io.ReadImageInformation()
    except RuntimeError as err:
        if is_nifti(path):
            check_nifti_header(path, role)
        raise InputError(f"{role} {str(path)!r}: unreadable header ({itk_error_message(err)})") from None
    sizes = [int(image_io.GetDimensions(d)) for d in range(image_io.GetNumberOfDimensions())]
    return sizes, int(image_io.GetNumberOfComponents())


def itk_error_message(err: BaseException) -> str:
    """The message of an ITK exception without its source location (``.../itkNiftiImageIO.cxx:2135:``)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    located = [line for line in lines if not re.fullmatch(r"\S+\.(cxx|hxx|txx|h)(:\d+)?:?", line)]
    useful = [line for line in lines if "Description:" in line] or located or lines or [type(err).__name__]
    text = re.sub(r"^(itk::ERROR:|ITK ERROR:)\s*", "", useful[0]).replace("Description:", "").strip()
    if "orthonormal" in text:
        text += " The header's voxel axes are sheared (not at right angles); resample the image first"
    return text[:200]


def _read_nifti(path: Path, role: str, dtype: type) -> Volume | None:
    """The NIfTI fast path (:mod:`monai_probreg.spatial.nifti_read`): the checks of the ITK path on one decompressed
    copy, voxels by nibabel, geometry by ITK's rule; None when ITK must read the file (that module's docstring)."""
    _check_file(path, role)
    loaded = load_nifti(path, role)
    if loaded is None:
        return None
    image, values = loaded
    index_to_lps = itk_geometry(image.header)
    if index_to_lps is None:
        return None
    return Volume(np.asarray(values, dtype=dtype).reshape(image.shape[:3]), index_to_lps, str(path))


def _read(path: str | os.PathLike, role: str, dtype: type) -> Volume:
    """``dtype``: np.float32 (images) or np.float64 (label maps, checked for integers afterwards)."""
    path = Path(path)
    if is_nifti(path):
        volume = _read_nifti(path, role, dtype)
        if volume is not None:
            return volume
    pixel = itk.F if dtype == np.float32 else itk.D
    sizes, components = _header(path, role)
    nifti = check_nifti_header(path, role) if is_nifti(path) else None  # before any voxel is read
    if components != 1:
        raise InputError(
            f"{role} {str(path)!r}: has {components} values per voxel (vector or RGB image); need a scalar 3-D volume"
        )
    check_size(sizes, path, role)
    image = _itk_read(path, role, itk.Image[pixel, 3])
    if nifti is not None:
        check_nifti_voxels(nifti, path, role)
    return volume_from_itk(image, str(path))


def _itk_read(path: Path, role: str, image_type: type) -> itk.Image:
    """The voxels by ITK's reader, and a non-degenerate geometry."""
    try:
        reader = itk.ImageFileReader[image_type].New(FileName=str(path))
        reader.Update()
    except RuntimeError as err:
        raise InputError(f"{role} {str(path)!r}: could not read the voxels ({itk_error_message(err)})") from None
    index_to_lps = geometry_of(reader.GetOutput())
    if not np.all(np.isfinite(index_to_lps)) or abs(np.linalg.det(index_to_lps[:3, :3])) < 1e-12:
        raise InputError(f"{role} {str(path)!r}: the header's geometry is degenerate (spacing/direction)")
    return reader.GetOutput()


def read_image(path: str | os.PathLike, role: str = "image") -> Volume:
    """Read a 3-D scalar image as float32 with its geometry; ``role`` names it in errors (e.g. ``"--moving"``).

    Raises :class:`InputError` for the problems listed in the module docstring, including a constant image
    (nothing to register).
    """
    volume = _read(path, role, np.float32)
    check_image_values(volume.array, path, role)
    return volume


def read_label(path: str | os.PathLike, role: str = "label map") -> Volume:
    """Read a 3-D label map (non-negative integers, 0 = background) as int32 with its geometry."""
    volume = _read(path, role, np.float64)
    check_label_values(volume.array, path, role)
    return Volume(volume.array.astype(np.int32), volume.index_to_lps, volume.path)


def read_volume(path: str | os.PathLike, role: str = "image", dtype: type = np.float32) -> Volume:
    """Any 3-D scalar volume (an image, a label map, a mask, a reference grid) with its geometry, as ``dtype``
    (np.float32, or np.float64, which keeps integers up to 2^53 exact): :func:`read_image`'s checks and its reading
    path, but a constant volume is accepted."""
    volume = _read(path, role, dtype)
    check_finite(volume.array, path, role)
    return volume


def read_field(path: str | os.PathLike, role: str = "displacement field") -> Volume:
    """A displacement field file, read as ITK reads it (so as ANTs does) -> :class:`Volume` of (I, J, K, 3) float32.

    A field is an ITK vector image with 3 components per voxel, in LPS mm: ``warp.nii.gz``, ANTs' ``*Warp.nii.gz``.
    In NIfTI the vector is dimension 5 with the intent "vector" (1007: LPS components, what ITK, ANTs and this
    package write) or "displacement vector" (1006: ITK 5.4 reads RAS components and turns them into LPS). Refused,
    with one line naming the file: what :func:`read_image` refuses, and a file that is not a 3-D field of
    3-vectors (a scalar image, another vector length, a NIfTI vector without an intent, which ITK reads as 5-D)."""
    path = Path(path)
    sizes, components = _header(path, role)
    if components != 3 or len(sizes) != 3:
        got = f"{components} value{'s' if components != 1 else ''} per voxel on a {len(sizes)}-D grid {tuple(sizes)}"
        hint = ""
        if components == 1 and len(sizes) > 3 and is_nifti(path):
            hint = "; a NIfTI field holds its vectors in dimension 5 with the intent 'vector' (1007), as ANTs writes"
        raise InputError(
            f"{role} {str(path)!r}: not a displacement field: expected 3 values per voxel (a vector in LPS mm) on "
            f"a 3-D grid, got {got}{hint}"
        )
    check_size(sizes, path, role)
    nifti = check_nifti_header(path, role, vector=True) if is_nifti(path) else None
    image = _itk_read(path, role, itk.Image[itk.Vector[itk.F, 3], 3])
    if nifti is not None:
        check_nifti_voxels(nifti, path, role)  # truncation, NaN, which ITK's reader hides
    array = np.ascontiguousarray(itk.array_from_image(image).transpose(2, 1, 0, 3), dtype=np.float32)
    check_finite(array, path, role)
    return Volume(array, geometry_of(image), str(path))


def check_same_grid(
    label: Volume,
    image: Volume,
    label_role: str = "label map",
    image_role: str = "image",
    advice: str = "resample the labels onto their image first (nearest neighbour)",
) -> None:
    """InputError unless ``label`` lies on ``image``'s grid (same shape, spacing, direction and origin, to
    1e-4 relative and 1e-3 mm: header rounding, not a resampling); ``advice`` ends the message (a mask's differs)."""

    def fail(difference: str) -> None:
        raise InputError(
            f"{label_role} {label.path!r} is not on the grid of {image_role} {image.path!r}: {difference}; {advice}"
        )

    if label.shape != image.shape:
        fail(f"size {label.shape} vs {image.shape}")
    if not np.allclose(label.spacing, image.spacing, rtol=_RELATIVE_TOL, atol=0):
        fail(f"spacing {np.round(label.spacing, 4).tolist()} vs {np.round(image.spacing, 4).tolist()} mm")
    if not np.allclose(label.direction, image.direction, rtol=0, atol=_RELATIVE_TOL):
        fail(f"orientation {label.axcodes} vs {image.axcodes} (direction matrices differ)")
    offset = float(np.abs(label.origin - image.origin).max())
    if offset > _ORIGIN_TOL_MM:
        fail(f"origins differ by {offset:.3g} mm")
