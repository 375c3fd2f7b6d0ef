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


def test_ants_syn_as_a_whole_process_carries_the_labels_onto_the_atlas(tmp_path):
    """The ANTs whole-process row (needs antspyx, the bench extra): a shifted copy of an asymmetric labelled volume
    comes back onto the atlas grid, its labels closer to the atlas' than before the registration."""
    pytest.importorskip("ants")
    grid = np.stack(np.meshgrid(*[np.arange(32)] * 3, indexing="ij"))
    atlas = np.exp(-(((grid - np.array([14, 17, 15])[:, None, None, None]) / 6.0) ** 2).sum(0)).astype(np.float32)
    atlas += 0.5 * np.exp(-(((grid - np.array([22, 10, 18])[:, None, None, None]) / 3.0) ** 2).sum(0))
    labels = (atlas > 0.3).astype(np.int16) + (grid[0] > 16) * (atlas > 0.3)
    shifted, shifted_labels = np.roll(atlas, 2, axis=0), np.roll(labels, 2, axis=0)
    warped, seconds = end_to_end.run_ants_whole(
        _save(tmp_path / "scan.nii.gz", shifted),
        _save(tmp_path / "labels.nii.gz", shifted_labels.astype(np.int16)),
        _save(tmp_path / "atlas.nii.gz", atlas),
        threads=1,
    )
    assert warped.shape == atlas.shape and seconds > 0
    before = end_to_end.shared_dice(shifted_labels.astype(np.float32), labels, moving_ids={1, 2})["mean"]
    after = end_to_end.shared_dice(warped.astype(np.float32), labels, moving_ids={1, 2})["mean"]
    assert after > before + 0.05
