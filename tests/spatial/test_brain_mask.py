"""monai_probreg.spatial.brain_mask: the fixed image's dilated support, and hiding the moving scan outside it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monai_probreg.spatial.brain_mask import fixed_brain_mask, hide_outside


def _box_image() -> np.ndarray:
    image = np.zeros((20, 24, 30), np.float32)
    image[5:10, 6:12, 10:14] = np.linspace(1.0, 2.0, 5 * 6 * 4).reshape(5, 6, 4)  # no constant inside
    return image


def test_mask_is_the_support_dilated_by_the_margin_per_axis():
    """Spacing (1, 2, 0.5) mm and a 2 mm margin: 2, 1 and 4 voxels along the three axes (an anisotropic box)."""
    mask = fixed_brain_mask(_box_image(), (1.0, 2.0, 0.5), margin_mm=2.0)
    expected = np.zeros_like(mask)
    expected[3:12, 5:13, 6:18] = True
    np.testing.assert_array_equal(mask, expected)


def test_zero_margin_gives_the_support_itself():
    image = _box_image()
    np.testing.assert_array_equal(fixed_brain_mask(image, (1.0, 1.0, 1.0), margin_mm=0.0), image > 0)


def test_no_background_means_no_mask():
    image = _box_image() + np.random.default_rng(0).random((20, 24, 30)).astype(np.float32)  # noise everywhere
    image[0, 0, 0] = -1.0  # one voxel at the minimum: its 3 mm neighbourhood is covered by the dilation
    assert fixed_brain_mask(image, (1.0, 1.0, 1.0)) is None


@pytest.mark.parametrize(
    ("array", "spacing", "margin", "match"),
    [
        (np.zeros((4, 4)), (1.0, 1.0), 1.0, "3-d image"),
        (np.zeros((4, 4, 4)), (1.0, 1.0), 1.0, "3 spacings"),
        (np.zeros((4, 4, 4)), (1.0, 1.0, 1.0), -1.0, "margin_mm must be >= 0"),
        (np.zeros((4, 4, 4)), (1.0, 1.0, 1.0), float("nan"), "margin_mm must be >= 0"),
    ],
)
def test_bad_arguments(array, spacing, margin, match):
    with pytest.raises(ValueError, match=match):
        fixed_brain_mask(array, spacing, margin)


def test_hide_outside_sets_the_fill_and_keeps_the_inside():
    image = np.arange(8, dtype=np.float32).reshape(2, 2, 2) + 10
    mask = np.zeros((2, 2, 2), bool)
    mask[0] = True
    hidden = hide_outside(image, mask, fill=-3.0)
    np.testing.assert_array_equal(hidden[0], image[0])
    assert (hidden[1] == -3.0).all() and hidden.dtype == image.dtype
    assert hide_outside(image, None, fill=0.0) is image
    with pytest.raises(ValueError, match="does not match"):
        hide_outside(image, mask[:1], fill=0.0)


def test_separable_dilation_equals_the_box_brute_force():
    """Random support, anisotropic spacing: the three 1-d max-pools give exactly the box of radius
    ceil(margin / spacing) voxels per axis, checked voxel by voxel."""
    rng = np.random.default_rng(0)
    array = np.zeros((14, 11, 9), np.float32)
    array[3:11, 2:9, 2:7] = rng.random((8, 7, 5)) > 0.85
    spacing, margin = (1.0, 1.5, 0.7), 2.0
    radius = [math.ceil(margin / s - 1e-9) for s in spacing]
    support = array > array.min()
    expected = np.zeros_like(support)
    for i, j, k in zip(*np.nonzero(support)):
        expected[
            max(i - radius[0], 0) : i + radius[0] + 1,
            max(j - radius[1], 0) : j + radius[1] + 1,
            max(k - radius[2], 0) : k + radius[2] + 1,
        ] = True
    np.testing.assert_array_equal(fixed_brain_mask(array, spacing, margin), expected)
