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

Memory: a ``.nii.gz`` is compressed in one call (ISA-L's output depends on how its input is split, so the file's bytes
stay those of one call only when it gets the whole file at once), and what that call needs is held once: nibabel
writes the uncompressed file straight into one buffer of its final size (:class:`_FileBuffer`, not a growing
``BytesIO`` copied out at the end), the buffer goes as soon as it is compressed, and the gzip header and the
compressed stream are written one after the other instead of joined into a third copy.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import nibabel as nib
import numpy as np
from isal import igzip, igzip_lib

from monai_probreg.spatial.checks import is_nifti
from monai_probreg.spatial.volume_io import LPS_TO_RAS
from monai_probreg.utils.files import atomic_write

__all__ = ["GZIP_LEVEL", "nifti_buffer", "nifti_bytes", "write_nifti"]

GZIP_LEVEL = 1  # ISA-L levels are 0-3; 1 gives zlib-level-1 sizes, far faster (module docstring)
_SCANNER = 1  # NIfTI xform code "scanner", what ITK writes for both qform and sform


def _image(array: np.ndarray, index_to_lps: np.ndarray, vector: bool) -> nib.Nifti1Image:
    """nibabel's image of ``array`` with ITK's header (module docstring), the array not copied."""
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
    return image


class _FileBuffer(io.RawIOBase):
    """A file of known ``size`` in memory that nibabel writes into (seeks and writes, as into a file): one buffer,
    filled in place."""

    def __init__(self, size: int):
        super().__init__()
        self.buffer = np.empty(size, np.uint8)  # every byte is written by nibabel (checked by nifti_buffer)
        self.position = 0
        self.end = 0  # one past the last byte written

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.position, io.SEEK_END: self.end}[whence]
        self.position = base + offset
        return self.position

    def tell(self) -> int:
        return self.position

    def write(self, data) -> int:
        chunk = np.frombuffer(data, np.uint8)
        if self.position + chunk.size > self.buffer.size:
            raise ValueError(f"nibabel wrote past the expected {self.buffer.size} bytes of the file")
        self.buffer[self.position : self.position + chunk.size] = chunk
        self.position += chunk.size
        self.end = max(self.end, self.position)
        return chunk.size


def nifti_buffer(array: np.ndarray, index_to_lps: np.ndarray, vector: bool = False) -> np.ndarray:
    """The uncompressed NIfTI-1 file of ``array`` (I, J, K) in index order, or (I, J, K, C) with ``vector``, on the
    grid ``index_to_lps`` (4, 4, LPS mm), with ITK's header (module docstring): its bytes (uint8), in one buffer."""
    image = _image(array, index_to_lps, vector)
    # one file: the header (and its empty extension flag), then the voxels from nibabel's single-file offset
    out = _FileBuffer(int(image.header.single_vox_offset) + array.nbytes)
    image.to_stream(out)
    if out.end != out.buffer.size:
        raise ValueError(f"nibabel wrote {out.end} bytes; expected {out.buffer.size}")
    return out.buffer


def nifti_bytes(array: np.ndarray, index_to_lps: np.ndarray, vector: bool = False) -> bytes:
    """:func:`nifti_buffer` as ``bytes`` (a copy: for small files and tests)."""
    return nifti_buffer(array, index_to_lps, vector).tobytes()


def _gzip_header(level: int) -> bytes:
    """The gzip header (RFC 1952) igzip's one-shot ``compress`` puts before its stream at ``level``, time stamp 0."""
    return igzip.compress(b"", level, mtime=0)[:_GZIP_HEADER_BYTES]


_GZIP_HEADER_BYTES = 10  # RFC 1952: the fixed header, no optional fields (igzip writes none)


def write_nifti(path: str | os.PathLike, array: np.ndarray, index_to_lps: np.ndarray, vector: bool = False) -> Path:
    """Write ``array`` as ``path`` (``.nii.gz``: gzip by ISA-L; ``.nii``: as is), atomically; the same bytes as
    ``igzip.compress(file, GZIP_LEVEL, mtime=0)`` (no time stamp: the same voxels give the same bytes)."""
    if not is_nifti(path):
        raise ValueError(f"expected a .nii or .nii.gz path; got {str(path)!r}")
    data = nifti_buffer(array, index_to_lps, vector)
    if str(path).lower().endswith(".gz"):
        # igzip.compress's stream, its header written before it rather than joined to it (module docstring, "Memory")
        parts = (_gzip_header(GZIP_LEVEL), igzip_lib.compress(data, GZIP_LEVEL, flag=igzip_lib.COMP_GZIP_NO_HDR))
        del data  # the uncompressed file goes before the compressed one is written
    else:
        parts = (data,)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as file:
            for part in parts:
                file.write(part)

    return atomic_write(path, write)
