"""benchmarks/identity_cases.py: the rigid motion it applies by header and the error it scores against it."""

from __future__ import annotations

import math

import itk
import nibabel as nib
import numpy as np
import pytest
from bench_helpers import load_benchmark

from monai_probreg.spatial.physical import field_to_itk

identity_cases = load_benchmark("identity_cases")


def test_the_motion_is_a_turn_about_the_centre_and_a_shift():
    centre = np.array([10.0, -20.0, 5.0])
    motion = identity_cases.rigid_motion_ras(4.0, 4.0, centre)
    rotation = motion[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert math.degrees(math.acos((np.trace(rotation) - 1) / 2)) == pytest.approx(4.0)
    axis = np.asarray(identity_cases.TURN_AXIS_RAS) / np.linalg.norm(identity_cases.TURN_AXIS_RAS)
    np.testing.assert_allclose(rotation @ axis, axis, atol=1e-12)  # the turn's axis stays
    assert np.linalg.norm(motion[:3] @ np.r_[centre, 1.0] - centre) == pytest.approx(4.0)  # the centre: the shift


def test_a_header_motion_moves_every_voxel_and_the_true_field_scores_zero(tmp_path):
    """moved_header changes the affine only; a warp.nii.gz holding the motion (LPS, on the fixed grid) scores 0 mm,
    the identity field scores the motion's displacement."""
    rng = np.random.default_rng(0)
    affine = np.diag([1.2, 1.0, 0.9, 1.0])
    affine[:3, 3] = [-10.0, 4.0, 7.0]
    scan = tmp_path / "scan.nii.gz"
    nib.save(nib.Nifti1Image(rng.random((9, 8, 7)).astype(np.float32), affine), scan)
    motion = identity_cases.rigid_motion_ras(4.0, 4.0, identity_cases.grid_centre_ras(scan))
    moved = nib.load(identity_cases.moved_header(scan, motion, tmp_path / "moved.nii.gz"))
    np.testing.assert_allclose(moved.affine, motion @ affine, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(moved.dataobj), np.asarray(nib.load(scan).dataobj))
    lps = identity_cases.LPS_FROM_RAS @ affine  # the fixed grid's index -> LPS
    index = np.stack(np.meshgrid(*[np.arange(n) for n in (9, 8, 7)], indexing="ij"), -1).reshape(-1, 3)
    points = index @ lps[:3, :3].T + lps[:3, 3]
    moved_lps = identity_cases.LPS_FROM_RAS @ motion @ identity_cases.LPS_FROM_RAS
    truth = (points @ moved_lps[:3, :3].T + moved_lps[:3, 3] - points).reshape(9, 8, 7, 3)
    mask = np.ones((9, 8, 7), bool)
    for field, expected in ((truth, 0.0), (np.zeros_like(truth), float(np.median(np.linalg.norm(truth, axis=-1))))):
        path = tmp_path / "warp.nii.gz"
        itk.imwrite(field_to_itk(field, lps), str(path))
        median, p95 = identity_cases.warp_error_mm(path, motion, mask)
        assert median == pytest.approx(expected, abs=1e-4) and p95 >= median
