"""The template-space training folder (monai_probreg.cli.template_space): majority vote by brute force, and the
folder written through the command's code path on a tiny dataset whose subjects are the template moved in space."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
from conftest import BUNDLE_DIR, FAST_AFFINE_SETTINGS, FIXED_LPS, asymmetric_phantom, save_lps, tiny_bundle

from monai_probreg.cli.template_space import TEMPLATE_ATLAS_NAME, majority_vote, to_template_space
from monai_probreg.data.dataset import index_dataset


def test_majority_vote_is_the_most_frequent_value_per_voxel_ties_to_the_smaller():
    rng = np.random.default_rng(0)
    maps = [rng.integers(0, 4, size=(5, 6, 7)).astype(np.uint8) for _ in range(5)]
    fused = majority_vote(maps)
    stacked = np.stack(maps)
    for idx in np.ndindex(fused.shape):
        counts = np.bincount(stacked[(slice(None), *idx)], minlength=4)
        assert fused[idx] == int(np.argmax(counts))  # argmax: the first (smaller) value among ties
    assert majority_vote([np.array([1, 2]), np.array([2, 1])]).tolist() == [1, 1]


@pytest.mark.parametrize("maps, words", [([], "at least one"), ([np.zeros((2, 2)), np.zeros((2, 3))], "one shape")])
def test_majority_vote_rejects_bad_input(maps, words):
    with pytest.raises(ValueError, match=words):
        majority_vote(maps)


def test_the_folder_holds_the_subjects_on_the_template_grid_after_the_affine_stage(tmp_path):
    """Each subject is the template's anatomy on another grid, shifted by a known translation: after the affine
    stage its image and labels land back on the template's (the translation recovered, not the header copied)."""
    image, labels = asymmetric_phantom((40, 44, 36))
    image = np.where(labels > 0, np.clip(image, 0.05, None), 0).astype(np.float32)
    template = save_lps(tmp_path / "template.nii.gz", image * 100, FIXED_LPS)
    data = tmp_path / "data"
    for sub in ("atlas", "images", "labels"):
        (data / sub).mkdir(parents=True)
    save_lps(data / "atlas" / "A_image.nii.gz", image, FIXED_LPS)
    save_lps(data / "atlas" / "A_label.nii.gz", labels, FIXED_LPS)
    for sid, shift in (("S1", (3.0, -2.0, 0.0)), ("S2", (-2.0, 0.0, 3.0))):
        moved = FIXED_LPS.copy()
        moved[:3, 3] += shift  # the same voxels, 3 mm elsewhere in space: the affine stage must undo the shift
        save_lps(data / "images" / f"{sid}.nii.gz", image * 50, moved)
        save_lps(data / "labels" / f"{sid}.nii.gz", labels, moved)
    fast = FAST_AFFINE_SETTINGS
    out = to_template_space(
        data,
        tmp_path / "out",
        ["S1", "S2"],
        template=template,
        bundle_root=tiny_bundle(tmp_path / "bundle", BUNDLE_DIR),
        affine=fast,
    )
    index = index_dataset(out)
    assert index.ids == ["S1", "S2"] and sorted(index.labels) == ["S1", "S2"]
    assert index.atlas_image.name == f"{TEMPLATE_ATLAS_NAME}_image.nii.gz" and index.atlas_label is not None
    reference = nib.load(template)
    for sid in ("S1", "S2"):
        moved_image, moved_label = nib.load(index.images[sid]), nib.load(index.labels[sid])
        assert moved_image.shape == reference.shape and np.allclose(moved_image.affine, reference.affine)
        agree = np.asarray(moved_label.dataobj) == labels
        assert agree.mean() > 0.97, f"{sid}: labels back on the template at {agree.mean():.3f}"
    fused = np.asarray(nib.load(index.atlas_label).dataobj)
    assert fused.shape == labels.shape and (fused == labels).mean() > 0.9
