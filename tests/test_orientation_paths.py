"""Orientation, pinned on both paths: the network sees anatomy as the header defines it.

One synthetic volume with a marker in the right-anterior-superior corner of the world is saved twice with correct
headers, as a RAS array and as an LPI array (every axis reversed in the file, its affine saying so). The bundle path
(MONAI ``Orientationd``) and the command line path (ITK reading, ``ModelGrid``) must both hand the network the same
array for both files, with the marker at the high end of every axis (RAS). A header that lies (the LPBA40 files once
stored LPS on RAS arrays) would put the marker at the other end: this test fails on it.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

from monai_probreg.data.transforms import registration_transforms
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.volume_io import read_image

SHAPE = (20, 24, 16)
SPACING = (1.2, 0.9, 1.5)


def _ras_volume() -> np.ndarray:
    """Smooth background and a bright block in the right-anterior-superior corner (RAS array: high indices)."""
    grid = np.meshgrid(*[np.linspace(0.0, 1.0, n) for n in SHAPE], indexing="ij")
    volume = (1.0 + 0.2 * grid[0] + 0.1 * grid[1] + 0.05 * grid[2]).astype(np.float32)
    volume[14:18, 17:22, 10:14] = 5.0
    return volume


def _save_both(tmp_path):
    volume = _ras_volume()
    ras_affine = np.diag([*SPACING, 1.0])
    ras_affine[:3, 3] = [-10.0, 20.0, 5.0]
    ras = tmp_path / "ras.nii.gz"
    nib.save(nib.Nifti1Image(volume, ras_affine), ras)
    # the same world content stored with every axis reversed: voxel i of the LPI file is voxel n-1-i of the RAS one
    lpi_affine = ras_affine @ np.array(
        [[-1, 0, 0, SHAPE[0] - 1], [0, -1, 0, SHAPE[1] - 1], [0, 0, -1, SHAPE[2] - 1], [0, 0, 0, 1]], dtype=float
    )
    lpi = tmp_path / "lpi.nii.gz"
    nib.save(nib.Nifti1Image(np.ascontiguousarray(volume[::-1, ::-1, ::-1]), lpi_affine), lpi)
    assert nib.aff2axcodes(lpi_affine) == ("L", "P", "I")
    return volume, ras, lpi


def _marker_at_high_end(array: np.ndarray) -> bool:
    peak = np.unravel_index(np.argmax(array), array.shape)
    return all(p > n / 2 for p, n in zip(peak, array.shape))


def test_bundle_path_gives_the_network_ras_anatomy_for_both_files(tmp_path):
    _, ras, lpi = _save_both(tmp_path)
    out = registration_transforms(with_labels=False, divisor=8)({"moving": str(lpi), "fixed": str(ras)})
    moving, fixed = out["moving"].numpy()[0], out["fixed"].numpy()[0]
    np.testing.assert_array_equal(moving, fixed)
    assert _marker_at_high_end(fixed)


def test_command_line_path_gives_the_network_ras_anatomy_for_both_files(tmp_path):
    _, ras, lpi = _save_both(tmp_path)
    arrays = []
    for path in (ras, lpi):
        volume = read_image(path)
        arrays.append(ModelGrid.for_volume(volume, divisor=8).to_model(volume.array))
    np.testing.assert_array_equal(arrays[0], arrays[1])
    assert _marker_at_high_end(arrays[0])


@pytest.mark.parametrize("lie", [np.diag([-1.0, -1.0, 1.0, 1.0]), np.diag([-1.0, 1.0, 1.0, 1.0])])
def test_a_header_that_lies_moves_the_marker(tmp_path, lie):
    volume = _ras_volume()
    path = tmp_path / "lying.nii.gz"
    nib.save(nib.Nifti1Image(volume, lie), path)  # a RAS array under an LPS (or LAS) header
    out = registration_transforms(with_labels=False, divisor=8)({"moving": str(path), "fixed": str(path)})
    assert not _marker_at_high_end(out["fixed"].numpy()[0])
