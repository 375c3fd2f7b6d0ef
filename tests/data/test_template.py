"""The default fixed image: the MNI152 template inside nilearn's package."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
from conftest import FAST_AFFINE, make_tiny_dataset, run_cli, save_lps, tiny_bundle

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.template import mni152_template_path

pytest.importorskip("nilearn")


def test_the_template_is_the_skull_stripped_1mm_ras_mni152():
    image = nib.load(mni152_template_path())
    assert image.shape == (197, 233, 189)
    assert nib.aff2axcodes(image.affine) == ("R", "A", "S")
    np.testing.assert_allclose(np.abs(np.diag(image.affine)[:3]), 1.0)
    brain = np.asarray(image.dataobj) > 0
    assert 0.15 < brain.mean() < 0.3  # skull-stripped: about a fifth of the box is brain
    assert not brain[0].any() and not brain[-1].any()


def test_a_dataset_without_atlas_folder_uses_the_default_atlas(tmp_path):
    root = make_tiny_dataset(tmp_path / "d", num_subjects=2, shape=(16, 16, 16))
    for f in (root / "atlas").iterdir():
        f.unlink()
    (root / "atlas").rmdir()
    with pytest.raises(ValueError, match="atlas"):
        index_dataset(root)
    index = index_dataset(root, default_atlas=mni152_template_path)
    assert index.atlas_image == mni152_template_path() and index.atlas_label is None and index.ids == ["T01", "T02"]


def test_register_without_fixed_goes_to_the_template(tmp_path, monkeypatch):
    """The command's wiring: no --fixed means the template's file (here a small stand-in, so the test is fast; the
    real template's header is checked above)."""
    from conftest import BUNDLE_DIR, FIXED_LPS, asymmetric_phantom

    import monai_probreg.data.template as template

    image, _ = asymmetric_phantom()
    stand_in = save_lps(tmp_path / "template.nii.gz", image, FIXED_LPS)
    monkeypatch.setattr(template, "mni152_template_path", lambda: stand_in)
    moving = save_lps(tmp_path / "scan.nii.gz", image, FIXED_LPS)
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    out = tmp_path / "out"
    result = run_cli("register", "--moving", str(moving), "--out", str(out), "--bundle-root", str(bundle), *FAST_AFFINE)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fixed"]["path"] == str(stand_in.resolve())


def test_fixed_label_needs_fixed(tmp_path):
    result = run_cli(
        "register",
        "--moving",
        str(tmp_path / "m.nii.gz"),
        "--fixed-label",
        str(tmp_path / "l.nii.gz"),
        "--out",
        str(tmp_path / "o"),
    )
    assert result.rc == 1 and "expected --fixed too" in result.err
