"""monai_probreg.registration.inputs: label maps are held in the smallest integer type that holds them."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.registration.inputs import compact_label, label_dtype, prepare_fixed, read_moving
from monai_probreg.spatial.volume_io import Volume


@pytest.mark.parametrize(("top", "dtype"), [(0, np.uint8), (255, np.uint8), (256, np.int16), (32768, np.int32)])
def test_compact_label_keeps_the_values_in_the_smallest_type(top, dtype):
    array = np.zeros((4, 3, 2), np.int32)
    array[1, 2, 1], array[3, 0, 0] = top, 7
    label = Volume(array, FIXED_LPS, "labels.nii.gz")
    compact = compact_label(label)
    assert compact.array.dtype == dtype == label_dtype(array)
    assert np.array_equal(compact.array, array) and compact.path == label.path
    assert np.array_equal(compact.index_to_lps, label.index_to_lps)
    assert (compact is label) == (dtype == np.int32)  # already in its type: not copied


def test_the_registration_reads_label_maps_compact(tmp_path):
    image, labels = asymmetric_phantom()
    image_path = save_lps(tmp_path / "image.nii.gz", image.astype(np.float32), FIXED_LPS)
    label_path = save_lps(tmp_path / "labels.nii.gz", labels.astype(np.int32), FIXED_LPS)
    fixed = prepare_fixed(image_path, label_path)
    moving = read_moving(image_path, label_path)
    for label in (fixed.label, moving.label):
        assert label.array.dtype == np.uint8 and np.array_equal(label.array, labels)
