"""experiments/affine_levers.py: its Dice on a synthetic atlas (the real-data run is the benchmark itself)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIXED_LPS, asymmetric_phantom, load_script, save_lps

from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.spatial.volume_io import Volume

affine_levers = load_script("experiments", "affine_levers")


@pytest.fixture
def atlas(tmp_path):
    image, labels = asymmetric_phantom()
    return prepare_fixed(
        save_lps(tmp_path / "atlas.nii.gz", image.astype(np.float32), FIXED_LPS),
        save_lps(tmp_path / "atlas_label.nii.gz", labels.astype(np.int16), FIXED_LPS),
    ), labels


def test_affine_dice_is_one_for_the_atlas_itself_and_drops_when_shifted(atlas):
    fixed, labels = atlas
    moving_labels = Volume(labels.astype(np.int32), FIXED_LPS)
    assert affine_levers.affine_dice(fixed, np.eye(4), moving_labels) == pytest.approx(1.0)
    shifted = np.eye(4)
    shifted[:3, 3] = [3.0, 0.0, 0.0]  # 3 mm along L: every structure overlaps less
    assert affine_levers.affine_dice(fixed, shifted, moving_labels) < 0.9


def test_settings_compared_include_the_default_and_no_cap():
    settings = affine_levers.settings_to_compare()
    caps = [s.max_samples for s in settings.values()]
    assert affine_levers.AffineSettings().max_samples in caps and None in caps
