"""monai_probreg.spatial.volume_io: geometry as ITK reads it, the index-order convention, one clear error per bad input."""

from __future__ import annotations

import gzip

import itk
import nibabel as nib
import numpy as np
import pytest
from conftest import save_lps

from monai_probreg.spatial.volume_io import LPS_TO_RAS, Volume, check_same_grid, read_image, read_label, volume_to_itk
from monai_probreg.utils.errors import InputError


def _oblique() -> np.ndarray:
    """index -> LPS with anisotropic spacing, an axis permutation and a flip, and an offset origin."""
    affine = np.eye(4)
    affine[:3, :3] = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) * [0.9, 1.5, 1.2]
    affine[:3, 3] = [10.0, -20.0, 30.0]
    return affine


def test_geometry_and_index_order_match_itk(tmp_path):
    data = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    path = save_lps(tmp_path / "a.nii.gz", data, _oblique())
    volume = read_image(path)
    np.testing.assert_array_equal(volume.array, data)  # index order = nibabel's array order
    np.testing.assert_allclose(volume.index_to_lps, _oblique(), atol=1e-5)  # NIfTI stores float32
    np.testing.assert_allclose(volume.ras_affine, nib.load(path).affine, atol=1e-5)
    assert volume.axcodes == "".join(nib.aff2axcodes(nib.load(path).affine))
    image = itk.imread(str(path), itk.F)
    # ITK's own index (i, j, k) is our array[i, j, k]; its numpy view is the reverse (k, j, i)
    assert image.GetPixel([1, 2, 3]) == volume.array[1, 2, 3]
    assert itk.array_from_image(image)[3, 2, 1] == volume.array[1, 2, 3]
    point = image.TransformIndexToPhysicalPoint([1, 2, 3])
    np.testing.assert_allclose(np.asarray(point), (volume.index_to_lps @ [1, 2, 3, 1])[:3], atol=1e-4)


def test_volume_to_itk_round_trip():
    volume = Volume(np.random.default_rng(0).random((4, 5, 6)).astype(np.float32), _oblique())
    image = volume_to_itk(volume)
    assert tuple(image.GetLargestPossibleRegion().GetSize()) == (4, 5, 6)
    np.testing.assert_allclose(
        np.asarray(image.TransformIndexToPhysicalPoint([3, 1, 2])), (_oblique() @ [3, 1, 2, 1])[:3], atol=1e-12
    )
    assert image.GetPixel([3, 1, 2]) == volume.array[3, 1, 2]


def test_trailing_singleton_axis_is_one_3d_volume(tmp_path):
    data = np.random.default_rng(0).random((4, 5, 6, 1)).astype(np.float32)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "a.nii.gz")
    assert read_image(tmp_path / "a.nii.gz").shape == (4, 5, 6)


def test_labels_are_read_as_int32(tmp_path):
    labels = np.zeros((4, 5, 6), np.uint8)
    labels[1:3, 1:3, 1:3] = 182
    volume = read_label(save_lps(tmp_path / "l.nii.gz", labels, np.eye(4)))
    assert volume.array.dtype == np.int32 and volume.array.max() == 182


# ------------------------------------------------------------------------------------------------ bad inputs
def _error(call, *args) -> str:
    with pytest.raises(InputError) as info:
        call(*args)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_missing_file(tmp_path):
    message = _error(read_image, tmp_path / "nope.nii.gz", "--moving")
    assert "--moving" in message and "nope.nii.gz" in message and "no such file" in message


def test_unreadable_file(tmp_path):
    path = tmp_path / "broken.nii.gz"
    path.write_bytes(gzip.compress(b"this is not a NIfTI header" * 20))
    message = _error(read_image, path, "--moving")
    assert "broken.nii.gz" in message


def test_truncated_file(tmp_path):
    full = save_lps(tmp_path / "full.nii", np.random.default_rng(0).random((20, 20, 20)).astype(np.float32), np.eye(4))
    path = tmp_path / "truncated.nii"
    path.write_bytes(full.read_bytes()[:1000])
    message = _error(read_image, path, "--moving")  # ITK alone would zero-fill the missing voxels
    assert "truncated.nii" in message and "truncated" in message


def test_two_dimensional_image(tmp_path):
    nib.save(
        nib.Nifti1Image(np.random.default_rng(0).random((8, 9)).astype(np.float32), np.eye(4)), tmp_path / "flat.nii.gz"
    )
    message = _error(read_image, tmp_path / "flat.nii.gz", "--moving")
    assert "flat.nii.gz" in message and "2-D" in message


def test_four_dimensional_image(tmp_path):
    nib.save(
        nib.Nifti1Image(np.random.default_rng(0).random((6, 7, 8, 3)).astype(np.float32), np.eye(4)),
        tmp_path / "series.nii.gz",
    )
    message = _error(read_image, tmp_path / "series.nii.gz", "--moving")
    assert "series.nii.gz" in message and "4-D" in message and "single 3-D volume" in message


def test_nan_voxels(tmp_path):
    data = np.random.default_rng(0).random((6, 7, 8)).astype(np.float32)
    data[1, 2, 3] = np.nan
    message = _error(read_image, save_lps(tmp_path / "nan.nii.gz", data, np.eye(4)), "--fixed")
    assert "--fixed" in message and "nan.nii.gz" in message and "1 NaN" in message  # ITK alone would read 0


def test_nan_voxels_in_another_format(tmp_path):
    data = np.random.default_rng(0).random((6, 7, 8)).astype(np.float32)
    data[1, 2, 3] = np.nan
    itk.imwrite(itk.image_from_array(data), str(tmp_path / "nan.mha"))
    assert "1 NaN" in _error(read_image, tmp_path / "nan.mha", "--moving")


def test_inf_voxels(tmp_path):
    data = np.random.default_rng(0).random((6, 7, 8)).astype(np.float32)
    data[0, 0, :2] = np.inf
    message = _error(read_image, save_lps(tmp_path / "inf.nii.gz", data, np.eye(4)), "--moving")
    assert "inf.nii.gz" in message and "2 Inf" in message


def test_constant_image(tmp_path):
    message = _error(
        read_image, save_lps(tmp_path / "empty.nii.gz", np.full((6, 7, 8), 3.0, np.float32), np.eye(4)), "--moving"
    )
    assert "empty.nii.gz" in message and "constant" in message


def test_non_integer_labels(tmp_path):
    labels = np.zeros((6, 7, 8), np.float32)
    labels[2:4, 2:4, 2:4] = 1.5
    message = _error(read_label, save_lps(tmp_path / "prob.nii.gz", labels, np.eye(4)), "--moving-label")
    assert "--moving-label" in message and "prob.nii.gz" in message and "non-integer" in message


def test_negative_labels(tmp_path):
    labels = np.zeros((6, 7, 8), np.int16)
    labels[0, 0, 0] = -1
    message = _error(read_label, save_lps(tmp_path / "neg.nii.gz", labels, np.eye(4)), "--fixed-label")
    assert "neg.nii.gz" in message


@pytest.mark.parametrize(
    "change, expected",
    [("shape", "size"), ("spacing", "spacing"), ("origin", "origins differ"), ("direction", "orientation")],
)
def test_labels_on_another_grid(tmp_path, change, expected):
    image = Volume(np.zeros((6, 7, 8), np.float32), np.eye(4), "img.nii.gz")
    affine, shape = np.eye(4), (6, 7, 8)
    if change == "shape":
        shape = (6, 7, 9)
    elif change == "spacing":
        affine = np.diag([1.0, 1.0, 2.0, 1.0])
    elif change == "origin":
        affine[:3, 3] = [0.0, 0.5, 0.0]
    else:
        affine = np.diag([-1.0, 1.0, 1.0, 1.0])
    label = Volume(np.zeros(shape, np.int32), affine, "lab.nii.gz")
    message = _error(check_same_grid, label, image, "--moving-label", "--moving")
    assert "lab.nii.gz" in message and "img.nii.gz" in message and expected in message


def test_header_rounding_is_the_same_grid():
    image = Volume(np.zeros((6, 7, 8), np.float32), _oblique())
    jitter = _oblique() + 1e-6  # float32 header storage
    check_same_grid(Volume(np.zeros((6, 7, 8), np.int32), jitter), image)


def test_lps_to_ras_is_its_own_inverse():
    np.testing.assert_array_equal(LPS_TO_RAS @ LPS_TO_RAS, np.eye(4))


def test_truncated_gzip_file(tmp_path):
    full = save_lps(
        tmp_path / "full.nii.gz", np.random.default_rng(0).random((20, 20, 20)).astype(np.float32), np.eye(4)
    )
    data = full.read_bytes()
    path = tmp_path / "cut.nii.gz"
    path.write_bytes(data[: len(data) // 2])
    message = _error(read_image, path, "--moving")
    assert "cut.nii.gz" in message and "truncated" in message
