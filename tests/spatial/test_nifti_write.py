"""monai_probreg.spatial.nifti_write: files that ITK reads back exactly (geometry and voxels), with the header
``itk.imwrite`` writes, for scalar volumes, label maps and displacement fields, on a rotated anisotropic grid."""

from __future__ import annotations

import gzip

import itk
import nibabel as nib
import numpy as np
import pytest
from isal import igzip
from scipy.spatial.transform import Rotation

from monai_probreg.spatial import nifti_write
from monai_probreg.spatial.nifti_write import GZIP_LEVEL, nifti_buffer, nifti_bytes, write_nifti
from monai_probreg.spatial.physical import field_from_itk, field_to_itk
from monai_probreg.spatial.volume_io import Volume, geometry_of, volume_from_itk, volume_to_itk

# an oblique grid (a rotation about three axes, one improper axis flip, anisotropic voxels, an offset origin)
_ROTATION = Rotation.from_euler("xyz", [12.0, -7.0, 25.0], degrees=True).as_matrix() @ np.diag([1.0, -1.0, 1.0])
GRID = np.eye(4)
GRID[:3, :3] = _ROTATION * np.array([0.9, 1.5, 1.2])
GRID[:3, 3] = [-31.5, 17.25, 4.0]
SHAPE = (7, 5, 6)  # asymmetric: an axis swap or flip would show


def _header_fields(path) -> dict:
    header = nib.load(path).header
    keys = (
        "dim",
        "pixdim",
        "intent_code",
        "qform_code",
        "sform_code",
        "xyzt_units",
        "datatype",
        "quatern_b",
        "quatern_c",
        "quatern_d",
        "qoffset_x",
        "qoffset_y",
        "qoffset_z",
        "srow_x",
        "srow_y",
        "srow_z",
    )
    return {key: np.asarray(header[key]) for key in keys}


def _assert_same_header(ours, theirs) -> None:
    a, b = _header_fields(ours), _header_fields(theirs)
    for key in a:
        np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-6, err_msg=key)


@pytest.mark.parametrize("dtype", [np.float32, np.uint8, np.int16])
def test_scalar_volume_matches_itk(tmp_path, dtype):
    array = (np.arange(np.prod(SHAPE)).reshape(SHAPE) % 97).astype(dtype)
    ours = write_nifti(tmp_path / "ours.nii.gz", array, GRID)
    itk.imwrite(volume_to_itk(Volume(array, GRID), dtype), str(tmp_path / "itk.nii.gz"), compression=True)
    _assert_same_header(ours, tmp_path / "itk.nii.gz")
    back = volume_from_itk(itk.imread(str(ours)))
    np.testing.assert_array_equal(back.array, array)
    np.testing.assert_allclose(back.index_to_lps, GRID, atol=1e-5)  # NIfTI stores the affine in float32


def test_displacement_field_matches_itk(tmp_path):
    field = np.random.default_rng(0).normal(size=(*SHAPE, 3)).astype(np.float32)
    ours = write_nifti(tmp_path / "ours.nii.gz", field, GRID, vector=True)
    itk.imwrite(field_to_itk(field, GRID), str(tmp_path / "itk.nii.gz"), compression=True)
    _assert_same_header(ours, tmp_path / "itk.nii.gz")
    assert nib.load(ours).header.get_intent()[0] == "vector"
    back = field_from_itk(itk.imread(str(ours)))
    np.testing.assert_array_equal(back.array, field)  # components as stored: LPS, no sign change
    np.testing.assert_allclose(back.index_to_lps, GRID, atol=1e-5)
    assert back.array.shape == (*SHAPE, 3)


def test_uncompressed_nii_and_gzip_stream(tmp_path):
    array = np.arange(np.prod(SHAPE), dtype=np.float32).reshape(SHAPE)
    plain = write_nifti(tmp_path / "v.nii", array, GRID)
    packed = write_nifti(tmp_path / "v.nii.gz", array, GRID)
    assert plain.read_bytes() == nifti_bytes(array, GRID)
    assert gzip.decompress(packed.read_bytes()) == plain.read_bytes()  # a standard gzip stream
    np.testing.assert_allclose(geometry_of(itk.imread(str(plain))), GRID, atol=1e-5)


def test_same_voxels_same_bytes(tmp_path):
    """No time stamp in the gzip header (bytes 4-7, RFC 1952): two runs' outputs are byte-identical whenever they
    run (issue "Same input, same output")."""
    array = np.arange(np.prod(SHAPE), dtype=np.float32).reshape(SHAPE)
    first = write_nifti(tmp_path / "a.nii.gz", array, GRID).read_bytes()
    assert first[:2] == b"\x1f\x8b" and first[4:8] == b"\x00\x00\x00\x00"
    assert write_nifti(tmp_path / "b.nii.gz", array, GRID).read_bytes() == first


def test_bad_path_and_shapes(tmp_path):
    array = np.zeros(SHAPE, dtype=np.float32)
    with pytest.raises(ValueError, match=r"expected a \.nii or \.nii\.gz path; got .*v\.nrrd"):
        write_nifti(tmp_path / "v.nrrd", array, GRID)
    with pytest.raises(ValueError, match=r"expected a vector image \(I, J, K, C\); got shape \(7, 5, 6\)"):
        nifti_bytes(array, GRID, vector=True)
    with pytest.raises(ValueError, match=r"expected a 3-D volume \(I, J, K\); got shape \(7, 5, 6, 3\)"):
        nifti_bytes(np.zeros((*SHAPE, 3), np.float32), GRID)
    assert not list(tmp_path.iterdir())  # nothing half-written


@pytest.mark.parametrize(
    ("shape", "vector", "dtype"),
    [(SHAPE, False, np.float32), (SHAPE, False, np.uint8), ((*SHAPE, 3), True, np.float32)],
)
def test_one_buffer_and_one_gzip_call_give_the_files_of_before(tmp_path, shape, vector, dtype):
    """The file is built in one buffer of its size and its gzip header written before the stream, not joined to it:
    the bytes are nibabel's ``to_bytes`` and igzip's one-shot ``compress`` of them (what was written before)."""
    array = (np.random.default_rng(1).random(shape) * 200).astype(dtype)
    image = nib.load(write_nifti(tmp_path / "v.nii", array, GRID, vector=vector))
    assert nifti_bytes(array, GRID, vector) == image.to_bytes() == (tmp_path / "v.nii").read_bytes()
    packed = write_nifti(tmp_path / "v.nii.gz", array, GRID, vector=vector).read_bytes()
    assert packed == igzip.compress(nifti_bytes(array, GRID, vector), GZIP_LEVEL, mtime=0)
    buffer = nifti_buffer(array, GRID, vector)
    assert buffer.dtype == np.uint8 and buffer.tobytes() == nifti_bytes(array, GRID, vector)


def test_a_file_of_another_size_than_expected_is_refused(monkeypatch):
    """nibabel writing past (or short of) the file's expected size is an error, not a silently wrong file."""
    array = np.zeros(SHAPE, np.float32)
    to_stream = nib.Nifti1Image.to_stream

    def longer(image, stream):
        to_stream(image, stream)
        stream.write(b"x")

    monkeypatch.setattr(nib.Nifti1Image, "to_stream", longer)
    with pytest.raises(ValueError, match="wrote past the expected 1192 bytes"):
        nifti_buffer(array, GRID)
    monkeypatch.setattr(nib.Nifti1Image, "to_stream", lambda image, stream: stream.write(b"header"))
    with pytest.raises(ValueError, match="nibabel wrote 6 bytes; expected 1192"):
        nifti_buffer(array, GRID)


def test_a_failed_compression_leaves_no_file(tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise MemoryError("no room")

    monkeypatch.setattr(nifti_write.igzip_lib, "compress", fail)
    with pytest.raises(MemoryError):
        write_nifti(tmp_path / "v.nii.gz", np.zeros(SHAPE, np.float32), GRID)
    assert not list(tmp_path.iterdir())
