"""Dataset discovery, splitting and the transform chain, on tiny synthetic NIfTI folders."""

from __future__ import annotations

import shutil

import nibabel as nib
import numpy as np
import pytest
import torch
from conftest import TINY_LABELS, make_tiny_dataset

from monai_probreg.data.dataset import atlas_label_values, index_dataset, pair_dicts, split_ids
from monai_probreg.data.transforms import NearestResizeAlignCornersd, registration_transforms


def test_index_reads_atlas_and_subjects_from_the_folder(tiny_dataset):
    index = index_dataset(tiny_dataset)
    assert index.atlas_image.name == "A01_image.nii.gz"
    assert index.atlas_label is not None and index.atlas_label.name == "A01_label.nii.gz"
    assert index.ids == ["T01", "T02", "T03"]
    assert sorted(index.labels) == ["T01", "T02", "T03"]
    assert atlas_label_values(index) == list(TINY_LABELS)


def test_missing_folder_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        index_dataset(tmp_path / "nowhere")


def test_two_atlases_are_refused(tmp_path, tiny_dataset):
    root = shutil.copytree(tiny_dataset, tmp_path / "ds")
    shutil.copy(root / "atlas" / "A01_image.nii.gz", root / "atlas" / "A02_image.nii.gz")
    with pytest.raises(ValueError, match="exactly one atlas image"):
        index_dataset(root)


def test_no_images_is_refused(tmp_path, tiny_dataset):
    root = shutil.copytree(tiny_dataset, tmp_path / "ds")
    shutil.rmtree(root / "images")
    with pytest.raises(ValueError, match="no NIfTI images"):
        index_dataset(root)


def test_unlabelled_subjects_are_kept_or_skipped_on_request(tmp_path):
    root = make_tiny_dataset(tmp_path / "ds", num_subjects=2, with_labels=False)
    index = index_dataset(root)
    assert index.labels == {}
    assert [p["id"] for p in pair_dicts(index)] == ["T01", "T02"]
    assert "moving_label" not in pair_dicts(index)[0]
    assert pair_dicts(index, require_labels=True) == []


def test_pairs_put_the_subject_as_moving_and_the_atlas_as_fixed(tiny_dataset):
    index = index_dataset(tiny_dataset)
    (pair,) = pair_dicts(index, ["T02"])
    assert pair["moving"].endswith("images/T02.nii.gz") and pair["fixed"] == str(index.atlas_image)
    assert pair["moving_label"].endswith("labels/T02.nii.gz") and pair["fixed_label"] == str(index.atlas_label)
    with pytest.raises(ValueError, match="T99"):
        pair_dicts(index, ["T99"])


def test_split_is_deterministic_disjoint_and_complete():
    ids = [f"S{i}" for i in range(11, 41)]
    train, val = split_ids(ids, 6, seed=3)
    assert (train, val) == split_ids(list(reversed(ids)), 6, seed=3)
    assert len(val) == 6 and not set(train) & set(val) and sorted(train + val) == sorted(ids)
    with pytest.raises(ValueError, match="num_val"):
        split_ids(ids, 30)


def test_transforms_scale_pad_and_keep_labels(tmp_path):
    root = make_tiny_dataset(tmp_path / "ds", num_subjects=1, shape=(30, 33, 32))
    item = registration_transforms()(pair_dicts(index_dataset(root))[0])
    for key in ("moving", "fixed"):
        assert tuple(item[key].shape) == (1, 32, 48, 32)  # padded to multiples of 16
        assert item[key].dtype == torch.float32
        assert float(item[key].min()) >= 0.0 and float(item[key].max()) == pytest.approx(1.0)
    raw = np.asanyarray(nib.load(str(root / "labels" / "T01.nii.gz")).dataobj)
    assert set(torch.unique(item["moving_label"]).tolist()) == {0, *np.unique(raw[raw > 0]).tolist()}


def test_network_size_resizes_images_and_optionally_labels(tiny_dataset):
    pair = pair_dicts(index_dataset(tiny_dataset))[0]
    item = registration_transforms(network_size=(16, 16, 16), resize_labels=True)(pair)
    assert tuple(item["moving"].shape) == (1, 16, 16, 16)
    assert tuple(item["moving_label"].shape) == (1, 16, 16, 16)
    assert set(torch.unique(item["moving_label"]).tolist()) <= {0, *TINY_LABELS}
    full = registration_transforms(network_size=(16, 16, 16))(pair)
    assert tuple(full["moving_label"].shape) == (1, 32, 32, 32)  # labels stay on the native grid by default


def test_nearest_resize_samples_at_align_corners_positions():
    # value = index along axis 0; 16 -> 6 voxels with align corners samples input i * 15 / 5 = 0, 3, ..., 15
    labels = torch.arange(16, dtype=torch.int16).view(1, 16, 1, 1).expand(1, 16, 4, 4).clone()
    out = NearestResizeAlignCornersd(["label"], (6, 4, 4))({"label": labels})["label"]
    assert out.dtype == torch.int16
    assert out[0, :, 0, 0].tolist() == [0, 3, 6, 9, 12, 15]
    assert torch.equal(out[0, :, 1:, 1:], out[0, :, :1, :1].expand(6, 3, 3))  # no mixing across other axes
