"""Checks of input files, shared by both loading paths: the command line's ITK reader (:mod:`monai_probreg.spatial.volume_io`)
and the bundle's MONAI loader (:class:`monai_probreg.data.transforms.LoadCheckedd`).

Every problem raises :class:`InputError` with one line ``<role> '<path>': expected ..., got ...``:

- **size** (from the header, before any voxel is read): a 3-D volume (trailing axes of length 1 are dropped, so
  (X, Y, Z, 1) is 3-D) with at least 2 voxels along every axis and at most :func:`max_voxels` voxels in all
  (default ``512**3``; environment variable ``MONAI_PROBREG_MAX_VOXELS`` or ``monai-probreg --max-voxels``). A scan
  over the limit is refused with that message rather than killed by the operating system for lack of memory.
- **NIfTI header** (nibabel): scalar voxels (no complex or RGB), a finite voxel-to-world affine with non-zero
  spacing, and a file that holds exactly the bytes its header's size needs: fewer = truncated, more = the header's
  dimensions disagree with the data. A ``.nii.gz`` is decompressed to its end for this, which also checks its CRC
  (nibabel alone reads only the bytes it needs and loads a corrupted stream as silently wrong voxels).
- **voxels**: finite (float64 values beyond float32's range are refused too: they would become Inf when read);
  an image is not constant; a label map holds integers in [0, 2^31).
"""

from __future__ import annotations

import gzip
import io
import os
import zlib
from collections.abc import Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
from isal import igzip
from isal.igzip_lib import IsalError

from monai_probreg.utils.errors import InputError, first_line

__all__ = [
    "MAX_VOXELS_ENV",
    "DEFAULT_MAX_VOXELS",
    "max_voxels",
    "is_nifti",
    "check_size",
    "corrupt_file_error",
    "check_nifti_header",
    "load_nifti",
    "check_finite",
    "check_nifti_voxels",
    "check_image_values",
    "check_label_values",
]


MAX_VOXELS_ENV = "MONAI_PROBREG_MAX_VOXELS"


DEFAULT_MAX_VOXELS = 512**3  # 134M voxels (0.5 GiB per float32 copy): a 0.5 mm whole head fits, 0.25 mm does not
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_NIFTI1_HEADER_BYTES = 348


_READ_ERRORS = (EOFError, OSError, ValueError, zlib.error, gzip.BadGzipFile, OverflowError)


def max_voxels() -> int:
    """The voxel limit: ``$MONAI_PROBREG_MAX_VOXELS`` if set (a positive integer), else :data:`DEFAULT_MAX_VOXELS`."""
    value = os.environ.get(MAX_VOXELS_ENV, "").strip()
    if not value:
        return DEFAULT_MAX_VOXELS
    try:
        limit = int(value.replace("_", ""))
    except ValueError:
        limit = 0
    if limit < 1:
        raise InputError(f"environment variable {MAX_VOXELS_ENV}: expected a positive integer (voxels), got {value!r}")
    return limit


def is_nifti(path: str | os.PathLike) -> bool:
    return Path(path).name.lower().endswith((".nii", ".nii.gz"))


def check_size(sizes: Sequence[int], path: str | os.PathLike, role: str, limit: int | None = None) -> tuple[int, ...]:
    """The 3-D size of a volume whose header gives ``sizes`` (trailing 1s dropped); InputError otherwise."""
    sizes = [int(n) for n in sizes]
    while len(sizes) > 3 and sizes[-1] == 1:  # (X, Y, Z, 1) is one 3-D volume
        sizes.pop()
    where = f"{role} {str(path)!r}"
    if len(sizes) != 3:
        hint = "; pass a single 3-D volume (e.g. extract one with fslroi)" if len(sizes) > 3 else ""
        raise InputError(f"{where}: expected a 3-D volume, got a {len(sizes)}-D one of size {tuple(sizes)}{hint}")
    if min(sizes) < 2:
        raise InputError(
            f"{where}: expected at least 2 voxels along every axis of a 3-D volume, got size "
            f"{tuple(sizes)} (an axis of {min(sizes)} voxel{'s' if min(sizes) != 1 else ''})"
        )
    limit = max_voxels() if limit is None else limit
    count = int(np.prod(sizes, dtype=np.int64))
    if count > limit:
        raise InputError(
            f"{where}: expected at most {limit:,} voxels, got {count:,} (size {tuple(sizes)}); downsample "
            f"the scan (e.g. to 1 mm) or raise the limit ({MAX_VOXELS_ENV} or --max-voxels) if this "
            "machine has the memory"
        )
    return tuple(sizes)


def corrupt_file_error(path: str | os.PathLike, role: str, err: BaseException) -> InputError:
    """The InputError for a file whose bytes cannot be decoded."""
    where = f"{role} {str(path)!r}"
    if Path(path).is_file() and Path(path).stat().st_size == 0:
        return InputError(f"{where}: expected an image file, got an empty file (0 bytes)")
    return InputError(
        f"{where}: expected a complete image file, got a truncated or corrupt one ({first_line(err)}); "
        "was a download or copy interrupted?"
    )


def _stream_length(path: Path) -> int:
    """Bytes of the NIfTI stream: the file size, or for ``.nii.gz`` the length of the whole decompressed stream.
    Decompressing to the end makes gzip verify its CRC: nibabel reads only the bytes the header asks for, so a
    flipped byte in the middle would otherwise load as silently wrong voxels."""
    if not path.name.lower().endswith(".gz"):
        return path.stat().st_size
    total = 0
    with gzip.open(path, "rb") as stream:
        while chunk := stream.read(1 << 24):
            total += len(chunk)
    return total


def check_nifti_header(
    path: str | os.PathLike, role: str, limit: int | None = None, vector: bool = False
) -> nib.Nifti1Image:
    """Open a NIfTI file with nibabel and check its header: size and voxel limit first (nothing else is read for a
    refused size), then voxel type, affine and byte count (a ``.nii.gz`` is streamed through once for this; no voxel
    array is built). ``vector``: a vector image (a displacement field), whose grid is its first three axes."""
    path = Path(path)
    try:
        image = nib.load(str(path))
    except _READ_ERRORS + (nib.filebasedimages.ImageFileError,) as err:
        raise corrupt_file_error(path, role, err) from None
    check_size(image.shape[:3] if vector else image.shape, path, role, limit)
    try:
        stored = _stream_length(path)
    except _READ_ERRORS as err:
        raise corrupt_file_error(path, role, err) from None
    return _check_loaded_header(image, stored, path, role)


def load_nifti(
    path: str | os.PathLike, role: str, limit: int | None = None
) -> tuple[nib.Nifti1Image, np.ndarray] | None:
    """:func:`check_nifti_header` and :func:`check_nifti_voxels` in one pass over the bytes: the size checked from the
    header alone (nothing more is decompressed for a refused size), then the whole file decompressed once by ISA-L's
    igzip (which checks the CRC) and held in memory, the same header checks, and the voxels as stored (scaled).
    Returns (image, voxels), or None for a file that is not a single-file NIfTI-1 (``.nii``/``.nii.gz`` with a
    NIfTI-2 or Analyze header): :func:`check_nifti_header` handles those."""
    path = Path(path)
    gz = path.name.lower().endswith(".gz")
    errors = _READ_ERRORS + (IsalError, nib.filebasedimages.ImageFileError, nib.spatialimages.HeaderDataError)
    try:
        with igzip.open(path, "rb") if gz else open(path, "rb") as stream:
            head = stream.read(_NIFTI1_HEADER_BYTES)
        header = nib.Nifti1Header.from_fileobj(io.BytesIO(head), check=False)
    except errors as err:
        raise corrupt_file_error(path, role, err) from None
    if int(header["sizeof_hdr"]) != _NIFTI1_HEADER_BYTES or header["magic"] != b"n+1":
        return None
    check_size(header.get_data_shape(), path, role, limit)
    try:
        data = igzip.decompress(path.read_bytes()) if gz else path.read_bytes()
        image = nib.Nifti1Image.from_bytes(data)
    except errors as err:
        raise corrupt_file_error(path, role, err) from None
    _check_loaded_header(image, len(data), path, role)
    return image, check_nifti_voxels(image, path, role)


def _check_loaded_header(image: nib.Nifti1Image, stored: int, path: Path, role: str) -> nib.Nifti1Image:
    """Voxel type, affine, and ``stored`` (the bytes of the decompressed stream) against what the header needs."""
    where = f"{role} {str(path)!r}"
    dtype = image.header.get_data_dtype()
    if dtype.kind == "c" or dtype.fields is not None:
        raise InputError(f"{where}: expected one real value per voxel, got {dtype} voxels (complex or RGB)")
    affine = np.asarray(image.affine, dtype=np.float64)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if not np.all(np.isfinite(affine)) or spacing.min() <= 1e-6 or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise InputError(
            f"{where}: expected a header with a finite, invertible voxel-to-world affine, got spacing "
            f"{np.round(spacing, 6).tolist()} mm and affine {np.round(affine[:3], 4).tolist()}"
        )
    offset = getattr(image.dataobj, "offset", None)  # where the voxels start (the loaded header's is reset to 0)
    needed = (
        int(offset if offset is not None else image.header.get_data_offset())
        + int(np.prod(image.header.get_data_shape(), dtype=np.int64)) * dtype.itemsize
    )
    if stored < needed:
        raise InputError(
            f"{where}: expected {needed:,} bytes for the header's size {tuple(image.shape)} ({dtype}), "
            f"got {stored:,}: the file is truncated; was a download or copy interrupted?"
        )
    if stored > needed:
        raise InputError(
            f"{where}: expected the header's dimensions to match the data, got a header size "
            f"{tuple(image.shape)} ({dtype}) that accounts for {needed:,} bytes and {stored - needed:,} "
            "more in the file; was the header edited or the file appended to?"
        )
    return image


def check_finite(values: np.ndarray, path: str | os.PathLike, role: str) -> None:
    nan, inf = int(np.isnan(values).sum()), int(np.isinf(values).sum())
    if nan or inf:
        why = " (values beyond float32's +-3.4e38 read as Inf)" if inf else ""
        raise InputError(
            f"{role} {str(path)!r}: expected finite voxels, got {nan} NaN and {inf} Inf voxels{why}; "
            "replace them (e.g. with 0) first"
        )


def check_nifti_voxels(image: nib.Nifti1Image, path: str | os.PathLike, role: str) -> np.ndarray:
    """Read the voxels as stored (nibabel, scaled by ``scl_slope``/``scl_inter``): a truncated file, NaN/Inf, and
    float64 values beyond float32's range; returns them. ITK's NIfTI reader would zero-fill the first and turn NaN
    into 0 without a warning."""
    try:
        values = np.asanyarray(image.dataobj)
    except MemoryError:
        raise InputError(
            f"{role} {str(path)!r}: expected an image that fits in memory, got size {tuple(image.shape)} "
            f"({image.get_data_dtype()}) that does not; downsample it or lower {MAX_VOXELS_ENV}"
        ) from None
    except _READ_ERRORS as err:
        raise corrupt_file_error(path, role, err) from None
    if values.dtype.kind == "f":
        check_finite(values, path, role)
        peak = float(np.abs(values).max())
        if peak > _FLOAT32_MAX:
            raise InputError(
                f"{role} {str(path)!r}: expected intensities within float32's range (|v| <= 3.4e38), got "
                f"values up to {peak:.3g}; rescale the image"
            )
    return values


def check_image_values(values: np.ndarray, path: str | os.PathLike, role: str) -> None:
    """Finite and not constant (nothing to register in a constant image)."""
    check_finite(values, path, role)
    low, high = float(values.min()), float(values.max())
    if low == high:
        raise InputError(
            f"{role} {str(path)!r}: expected an image with contrast, got a constant one (every voxel = "
            f"{low:g}); nothing to register"
        )


def check_label_values(values: np.ndarray, path: str | os.PathLike, role: str) -> None:
    """Finite integers in [0, 2^31) (0 = background)."""
    check_finite(values, path, role)
    fractional = values != np.round(values)
    if fractional.any():
        example = float(values[fractional].flat[0])
        raise InputError(
            f"{role} {str(path)!r}: not a label map: expected integer labels, got {int(fractional.sum())} "
            f"voxels holding non-integer values (e.g. {example:g})"
        )
    low, high = float(values.min()), float(values.max())
    if low < 0 or high > np.iinfo(np.int32).max:
        raise InputError(
            f"{role} {str(path)!r}: expected label values that are integers in [0, 2^31), got [{low:g}, {high:g}]"
        )
