"""Transforms given as files, and any image resampled through one as ``antsApplyTransforms`` resamples it.

Conventions (:mod:`monai_probreg.spatial.physical` states them in full): a transform ``T`` maps a point ``p`` of
the output (reference) grid, LPS mm, to the point of the input (moving) image that the output voxel shows:
``out(p) = moving(T(p))``, the pull-back of ITK's ``ResampleImageFilter``.

- **displacement field** (an ITK vector image, :func:`~monai_probreg.spatial.volume_io.read_field`; ``warp.nii.gz``,
  ``inverse_warp.nii.gz``, ANTs' ``*Warp.nii.gz``): ``T(p) = p + D(p)``. On the reference grid itself (every voxel
  within :data:`SAME_GRID_VOXELS` of its field voxel: header rounding) ``D`` is the file's value at that voxel,
  exactly what ``monai-probreg register`` samples through, so its outputs come back to the bit. On another grid ``D``
  is interpolated linearly at ``p`` and is 0 (``T(p) = p``) where ``p`` lies outside the field's grid extended by
  half a voxel: ITK's ``DisplacementFieldTransform``, which ANTs uses.
- **affine file**: ITK's text format (``.tfm``, ``.txt``) or its MATLAB form (``.mat``: ANTs' ``*GenericAffine.mat``),
  one transform, ``T(p) = M (p - c) + c + t``, ``Parameters`` = M row by row then t, ``FixedParameters`` = c.
  ``AffineTransform_*_3_3`` and ``MatrixOffsetTransformBase_*_3_3`` (what ANTs and most converters write, and a
  type ITK's Python wrapping cannot create) are read here; other linear ITK types (``Euler3DTransform``,
  ``VersorRigid3DTransform``, ...) through ``itk.transformread``, which loads ITK's transform modules (seconds).
  The same reader serves ``monai-probreg register --initial-transform`` (:func:`read_initial_transform`: an affine
  file only, invertible), whose transform is ``affine.tfm``'s: fixed point -> moving point.
- **sampling** (:mod:`monai_probreg.spatial.point_sampling`): linear, or nearest neighbour with ITK's rounding
  (half up); 0 outside the moving image.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path
from typing import NamedTuple

import numpy as np

from monai_probreg.spatial.physical import mapped_index
from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
from monai_probreg.spatial.volume_io import Volume, itk_error_message, read_field
from monai_probreg.utils.errors import InputError, first_line

__all__ = [
    "AFFINE_SUFFIXES",
    "SAME_GRID_VOXELS",
    "AffineFile",
    "FileTransform",
    "Resampled",
    "read_transform",
    "read_affine",
    "read_affine_file",
    "read_initial_transform",
    "field_on_grid",
    "resample_through",
]

AFFINE_SUFFIXES = (".tfm", ".txt", ".mat")
SAME_GRID_VOXELS = 1e-3  # a reference voxel this close to a field voxel reads that voxel (NIfTI's float32 headers)
_MATRIX_OFFSET = re.compile(r"(AffineTransform|MatrixOffsetTransformBase)_(double|float)_3_3")
_DIMENSIONS = re.compile(r"_(\d+)_(\d+)$")  # ITK's type names end in _<input dimension>_<output dimension>
LINEAR = "one linear 3-D transform (matrix and offset)"  # what an affine file must hold
_MATLAB_TYPES = {0: "f8", 1: "f4", 2: "i4", 3: "i2", 4: "u2", 5: "u1"}  # MATLAB v4 "P" digit -> numpy


class FileTransform(NamedTuple):
    """A transform read from ``path``: ``field`` (I, J, K, 3) LPS mm on its grid, or ``matrix`` (4, 4) LPS."""

    path: str
    field: Volume | None = None
    matrix: np.ndarray | None = None


class AffineFile(NamedTuple):
    """One linear transform read from a file: ``matrix`` (4, 4) LPS, output point -> input point; ``center``: its
    ITK centre (``FixedParameters``, LPS mm; the map does not depend on it, but writing it back keeps the file's
    parameters)."""

    matrix: np.ndarray
    center: np.ndarray


class Resampled(NamedTuple):
    """``array``: the moving image on the reference grid, float64 (linear) or the moving array's dtype (nearest);
    ``field_coverage``: the fraction of reference voxels inside the field's grid (1.0 for an affine)."""

    array: np.ndarray
    field_coverage: float


def read_transform(path: str | os.PathLike, role: str = "transform") -> FileTransform:
    """An affine file (:data:`AFFINE_SUFFIXES`) or a displacement field (any image format ITK reads)."""
    if Path(path).name.lower().endswith(AFFINE_SUFFIXES):
        return FileTransform(str(path), matrix=read_affine(path, role, f"a displacement field or {LINEAR}").matrix)
    return FileTransform(str(path), field=read_field(path, role))


def read_affine_file(path: str | os.PathLike, role: str = "transform") -> np.ndarray:
    """One linear transform from an ITK text (``.tfm``, ``.txt``) or MATLAB (``.mat``) file -> (4, 4) LPS matrix,
    output point -> input point (module docstring). InputError (one line) for anything else."""
    return read_affine(path, role).matrix


def read_initial_transform(path: str | os.PathLike, role: str = "--initial-transform") -> AffineFile:
    """The affine of an earlier registration, fixed LPS -> moving LPS (ITK's and ANTs' convention, ``affine.tfm``'s):
    an affine file (:data:`AFFINE_SUFFIXES`) holding one invertible linear 3-D transform. InputError (one line)
    otherwise: a displacement field is refused by its name before it is read (the affine stage takes a matrix)."""
    where = f"{role} {str(path)!r}"
    _check_file(Path(path), where)
    if not Path(path).name.lower().endswith(AFFINE_SUFFIXES):
        raise InputError(
            f"{where}: expected an affine transform file ({', '.join(AFFINE_SUFFIXES)}), got another kind of file "
            "(an image such as a displacement field cannot start or replace the affine stage)"
        )
    affine = read_affine(path, role)
    linear = affine.matrix[:3, :3]
    # numpy's rank tolerance (the largest singular value x 3 x float64's epsilon): singular to working precision
    if np.linalg.matrix_rank(linear) < len(linear):
        raise InputError(
            f"{where}: expected an invertible matrix, got a singular one (determinant {np.linalg.det(linear):.3g}: "
            "it maps the fixed image onto a plane, a line or a point)"
        )
    return affine


def _check_file(path: Path, where: str) -> None:
    if not path.exists():
        raise InputError(f"{where}: no such file")
    if not path.is_file():
        raise InputError(f"{where}: is a folder, not a transform file")


def read_affine(path: str | os.PathLike, role: str = "transform", expected: str = LINEAR) -> AffineFile:
    """One linear transform from an ITK text (``.tfm``, ``.txt``) or MATLAB (``.mat``) file, with its centre
    (module docstring). InputError (one line) for anything else, saying the file should hold ``expected``."""
    path = Path(path)
    where = f"{role} {str(path)!r}"
    _check_file(path, where)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(f"{where}: cannot read the file ({first_line(err)})") from None
    try:
        name, parameters, fixed = _matlab_transform(data) if path.suffix.lower() == ".mat" else _text_transform(data)
    except ValueError as err:
        raise InputError(f"{where}: not an ITK/ANTs transform file: {err}") from None
    dimensions = _DIMENSIONS.search(name)
    if dimensions is not None and dimensions.groups() != ("3", "3"):  # refused here, without loading ITK (seconds)
        source, target = dimensions.groups()
        kind = f"{source}-D" if source == target else f"{source}-D to {target}-D"
        raise InputError(f"{where}: expected {expected}, got a {kind} transform ({name})")
    if not _MATRIX_OFFSET.fullmatch(name):
        return _itk_affine(path, where, name, expected)
    if parameters.size != 12 or fixed.size != 3:
        raise InputError(
            f"{where}: expected 12 parameters and 3 fixed parameters (the centre) for {name}, got "
            f"{parameters.size} and {fixed.size}"
        )
    if not np.all(np.isfinite(parameters)) or not np.all(np.isfinite(fixed)):
        raise InputError(f"{where}: expected finite parameters, got {parameters.tolist()} and {fixed.tolist()}")
    linear, translation = parameters[:9].reshape(3, 3), parameters[9:]
    matrix = np.eye(4)
    matrix[:3, :3] = linear
    matrix[:3, 3] = translation + fixed - linear @ fixed  # M (p - c) + c + t
    return AffineFile(matrix, fixed.copy())


def _text_transform(data: bytes) -> tuple[str, np.ndarray, np.ndarray]:
    """(type name, parameters, fixed parameters) of ITK's ``#Insight Transform File`` holding one transform."""
    try:
        lines = [line.strip() for line in data.decode("ascii").splitlines()]
    except UnicodeDecodeError:
        raise ValueError("expected ITK's text transform format, got a binary file") from None
    fields: dict[str, list[str]] = {}
    for line in lines:
        key, colon, value = line.partition(":")
        if colon and key in ("Transform", "Parameters", "FixedParameters"):
            fields.setdefault(key, []).append(value.strip())
    names = fields.get("Transform", [])
    if len(names) != 1:
        raise ValueError(
            f"expected one 'Transform:' line (one transform), got {len(names)}"
            + ("; compose them into one field first (e.g. antsApplyTransforms -o [warp.nii.gz,1])" if names else "")
        )
    if len(fields.get("Parameters", [])) != 1:
        raise ValueError("expected one 'Parameters:' line")
    try:
        parameters = np.array(fields["Parameters"][0].split(), dtype=np.float64)
        fixed = np.array(" ".join(fields.get("FixedParameters", [])).split(), dtype=np.float64)
    except ValueError as err:
        raise ValueError(f"parameters that are not numbers ({first_line(err)})") from None
    return names[0], parameters, fixed


def _matlab_transform(data: bytes) -> tuple[str, np.ndarray, np.ndarray]:
    """(type name, parameters, fixed parameters) of ITK's MATLAB v4 transform file: a matrix named after the transform
    type holding its parameters, then one named ``fixed``."""
    records: dict[str, np.ndarray] = {}
    offset = 0
    while offset < len(data):
        if offset + 20 > len(data):
            raise ValueError("expected a MATLAB v4 matrix header, got the end of the file (truncated)")
        for endian in "<>":
            code, rows, cols, imaginary, name_length = struct.unpack_from(f"{endian}5i", data, offset)
            if 0 <= code < 2000 and "<>"[code // 1000] == endian:  # the "M" digit says which byte order
                break
        else:
            raise ValueError("expected a MATLAB v4 matrix (MOPT code), got other bytes")
        kind = (code // 10) % 10
        if (code // 100) % 10 or code % 10 or imaginary or kind not in _MATLAB_TYPES or min(rows, cols) < 0:
            raise ValueError(f"expected a real full numeric matrix, got MATLAB type code {code}")
        start = offset + 20 + name_length
        dtype = np.dtype(_MATLAB_TYPES[kind]).newbyteorder(endian)
        end = start + rows * cols * dtype.itemsize
        if name_length < 1 or end > len(data):
            raise ValueError("the file is truncated")
        name = data[offset + 20 : start].rstrip(b"\0").decode("ascii", errors="replace")
        records[name] = np.frombuffer(data[start:end], dtype=dtype).astype(np.float64)
        offset = end
    names = [name for name in records if name != "fixed"]
    if len(names) != 1:
        raise ValueError(f"expected one transform's parameters and 'fixed', got the matrices {list(records)}")
    return names[0], records[names[0]], records.get("fixed", np.zeros(0))


def _itk_affine(path: Path, where: str, name: str, expected: str) -> AffineFile:
    """A linear ITK transform of another type (Euler, versor, similarity...) read by ITK itself."""
    import itk

    from monai_probreg.spatial.physical import affine_from_itk

    try:
        transforms = itk.transformread(str(path))
    except RuntimeError as err:
        raise InputError(f"{where}: ITK cannot read the {name} transform ({itk_error_message(err)})") from None
    transform = transforms[0] if len(transforms) == 1 else None
    if (
        transform is None
        or not hasattr(transform, "GetMatrix")
        or transform.GetInputSpaceDimension() != 3
        or transform.GetOutputSpaceDimension() != 3
    ):
        raise InputError(f"{where}: expected {expected}, got {name}")
    center = np.asarray(transform.GetCenter(), dtype=np.float64) if hasattr(transform, "GetCenter") else np.zeros(3)
    return AffineFile(affine_from_itk(transform), center)


def _same_grid(field: Volume, shape: tuple[int, ...], index_to_lps: np.ndarray) -> bool:
    """Every voxel of the grid (``shape``, ``index_to_lps``) within :data:`SAME_GRID_VOXELS` of the field's voxel of
    the same index (checked at the 8 corners: the map between two grids is affine)."""
    if tuple(field.shape) != tuple(shape):
        return False
    to_field = np.linalg.inv(field.index_to_lps) @ np.asarray(index_to_lps, dtype=np.float64)
    corners = np.array(
        [[i, j, k, 1.0] for i in (0, shape[0] - 1) for j in (0, shape[1] - 1) for k in (0, shape[2] - 1)]
    )
    return float(np.abs(corners @ (to_field - np.eye(4)).T).max()) < SAME_GRID_VOXELS


def field_on_grid(field: Volume, shape: tuple[int, ...], index_to_lps: np.ndarray) -> tuple[np.ndarray, float]:
    """``D`` (I, J, K, 3) LPS mm at every voxel of the grid (``shape``, ``index_to_lps``) and the fraction of those
    voxels inside the field's grid (module docstring: the file's values on its own grid, else linear, 0 outside)."""
    if _same_grid(field, shape, index_to_lps):
        return field.array, 1.0
    index = mapped_index(shape, index_to_lps, field.index_to_lps)
    inside = np.all((index >= -0.5) & (index < np.asarray(field.shape) - 0.5), axis=-1)
    return sample_linear(field, None, index=index), float(inside.mean())


def resample_through(moving: Volume, reference: Volume, transform: FileTransform, nearest: bool = False) -> Resampled:
    """``moving`` on ``reference``'s grid through ``transform``: ``out(p) = moving(T(p))`` (module docstring), linear
    or nearest neighbour, 0 outside ``moving``; only the reference's grid is used."""
    coverage = 1.0
    if transform.matrix is not None:
        index = mapped_index(reference.shape, reference.index_to_lps, moving.index_to_lps, affine=transform.matrix)
    else:
        field, coverage = field_on_grid(transform.field, reference.shape, reference.index_to_lps)
        index = mapped_index(reference.shape, reference.index_to_lps, moving.index_to_lps, field=field)
    sample = sample_nearest if nearest else sample_linear
    return Resampled(sample(moving, None, index=index), coverage)
