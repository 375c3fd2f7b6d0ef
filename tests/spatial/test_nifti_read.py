"""monai_probreg.spatial.nifti_read and volume_io's NIfTI fast path: the same geometry and voxels as ITK's reader for
the headers it accepts (rotated, flipped, anisotropic grids; sform with or without an agreeing qform; scaled voxels; a
fourth axis of one), ITK itself for every header it leaves to ITK."""

from __future__ import annotations

import itk
import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from monai_probreg.spatial import volume_io
from monai_probreg.spatial.nifti_read import itk_geometry
from monai_probreg.spatial.volume_io import read_image, read_label, volume_from_itk

SHAPE = (9, 7, 8)  # asymmetric: an axis swap shows
_DIRECTION = Rotation.from_euler("xyz", [14.0, -9.0, 31.0], degrees=True).as_matrix() @ np.diag([1.0, 1.0, -1.0])
RAS = np.eye(4)
RAS[:3, :3] = _DIRECTION * np.array([0.86, 1.5, 1.2])
RAS[:3, 3] = [41.25, -17.5, 8.0]


def _data(dtype=np.float32) -> np.ndarray:
    return (np.arange(np.prod(SHAPE)).reshape(SHAPE) % 251 + 3).astype(dtype)


def _save(path, data, qform_code=1, sform_code=1, qform=RAS, sform=RAS, edit=None):
    image = nib.Nifti1Image(data, None)
    image.set_qform(qform, code=qform_code)
    image.set_sform(sform, code=sform_code)
    image.header.set_xyzt_units("mm", "sec")
    if edit is not None:
        edit(image.header)
    nib.save(image, path)
    return path


def _itk(path, pixel=itk.F):
    return volume_from_itk(itk.imread(str(path), pixel))


def _same_as_itk(path, read=read_image, pixel=itk.F):
    ours, theirs = read(path), _itk(path, pixel)
    np.testing.assert_allclose(ours.index_to_lps, theirs.index_to_lps, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(ours.array, theirs.array.astype(ours.array.dtype))
    return ours


@pytest.fixture
def no_itk_reader(monkeypatch):
    """Reading through ITK fails: what passes with this fixture was read without ITK."""

    def refuse(*args, **kwargs):
        raise AssertionError("ITK was asked to read")

    monkeypatch.setattr(volume_io, "_header", refuse)


@pytest.mark.parametrize("qform_code, sform_code", [(1, 1), (0, 2), (2, 1), (0, 1)])
def test_accepted_headers_match_itk_without_itk(tmp_path, qform_code, sform_code, no_itk_reader):
    path = _save(tmp_path / "scan.nii.gz", _data(np.int16), qform_code, sform_code)
    ours = read_image(path)
    theirs = _itk(path)
    np.testing.assert_allclose(ours.index_to_lps, theirs.index_to_lps, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(ours.array, theirs.array)
    assert ours.array.dtype == np.float32 and ours.shape == SHAPE


def test_scaled_voxels_and_a_fourth_axis_of_one_match_itk(tmp_path, no_itk_reader):
    def scale(header):
        header.set_slope_inter(2.5, -7.0)

    path = _save(tmp_path / "scaled.nii", _data(np.int16)[..., None], edit=scale)
    ours = read_image(path)
    theirs = _itk(path)
    np.testing.assert_allclose(ours.index_to_lps, theirs.index_to_lps, rtol=0, atol=1e-5)
    np.testing.assert_allclose(ours.array, theirs.array, rtol=1e-6)
    assert ours.array.min() == pytest.approx(3 * 2.5 - 7.0)


def test_labels_match_itk_without_itk(tmp_path, no_itk_reader):
    path = _save(tmp_path / "labels.nii.gz", (_data(np.uint8) % 5))
    ours = read_label(path)
    np.testing.assert_array_equal(ours.array, _itk(path, itk.D).array.astype(np.int32))
    assert ours.array.dtype == np.int32


def _sheared():
    sheared = RAS.copy()
    sheared[0, 1] += 0.3
    return sheared


def _moved():
    moved = RAS.copy()
    moved[:3, 3] += [2.0, 0.0, 0.0]
    return moved


@pytest.mark.parametrize("case", ["qform only", "forms disagree", "sheared sform", "metres", "pixdim differs"])
def test_headers_left_to_itk_are_read_by_itk(tmp_path, case):
    """For each header this rule does not cover, ``itk_geometry`` says None and the file is read by ITK as before."""
    kwargs = {
        "qform only": {"sform_code": 0},
        "forms disagree": {"sform": _moved(), "sform_code": 2},
        "sheared sform": {"sform": _sheared(), "sform_code": 2},
        "metres": {"edit": lambda header: header.set_xyzt_units("meter", "sec")},
        "pixdim differs": {"edit": lambda header: header["pixdim"].__setitem__(1, 0.9)},
    }[case]
    path = _save(tmp_path / "odd.nii.gz", _data(), **kwargs)
    assert itk_geometry(nib.load(path).header) is None
    _same_as_itk(path)


def test_both_paths_refuse_the_same_truncated_file(tmp_path):
    path = _save(tmp_path / "cut.nii", _data())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 40])
    with pytest.raises(volume_io.InputError, match="truncated"):
        read_image(path)
