"""benchmarks/end_to_end.py helpers on synthetic files (the real-data run is the benchmark itself)."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
from bench_helpers import load_benchmark

end_to_end = load_benchmark("end_to_end")


def _save(path, array):
    nib.save(nib.Nifti1Image(array, np.eye(4)), path)
    return path


def test_native_scans_pairs_each_scan_with_its_labels(tmp_path):
    volume = np.zeros((4, 4, 4), np.int16)
    for name in ("S20.nii.gz", "S20_labels.nii.gz", "S01.nii.gz"):  # S01 has no labels: not scored
        _save(tmp_path / name, volume)
    assert end_to_end.native_scans(tmp_path) == [("S20", tmp_path / "S20.nii.gz", tmp_path / "S20_labels.nii.gz")]


def test_shared_dice_scores_only_the_labels_of_both_maps():
    fixed = np.zeros((6, 6, 6), np.int16)
    fixed[:3], fixed[3:, :3], fixed[3:, 3:] = 1, 2, 3
    warped = fixed.copy()
    warped[:3, :1] = 0  # label 1 (108 voxels) loses 18: Dice 2 * 90 / (90 + 108) = 10 / 11
    result = end_to_end.shared_dice(warped.astype(np.float32), fixed, moving_ids={1, 2})  # label 3: fixed only
    assert result["num_labels"] == 2 and set(result["per_label"]) == {"1", "2"}
    assert result["per_label"]["1"] == pytest.approx(10 / 11) and result["per_label"]["2"] == pytest.approx(1.0)
    assert result["mean"] == pytest.approx((10 / 11 + 1) / 2)
