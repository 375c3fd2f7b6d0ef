"""monai_probreg.spatial.contrast: a second contrast mapped onto the first by the joint histogram's conditional mean."""

from __future__ import annotations

import numpy as np
import pytest

from monai_probreg.registration.affine_stage import matched_input
from monai_probreg.spatial.contrast import CONTRAST_MATCH_MIN_COUNT, check_contrast_match_bins, match_contrast
from monai_probreg.utils.errors import InputError


def _pair(relation, n: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    moving = np.random.default_rng(seed).uniform(0.02, 1.0, n).astype(np.float32)
    return moving, relation(moving).astype(np.float32)


def _conditional_means(moving, fixed, num_bins, counted):
    """Brute force: the mean fixed intensity of each moving bin, one bin at a time (NaN where a bin is empty)."""
    means = np.full(num_bins, np.nan)
    for b in range(num_bins):
        low, high = b / num_bins, (b + 1) / num_bins
        members = counted & (moving >= low) & ((moving < high) if b < num_bins - 1 else (moving <= high))
        if members.any():
            means[b] = fixed[members].mean()
    return means


@pytest.mark.parametrize(
    "relation",
    [lambda m: 1.0 - m, lambda m: 4.0 * m * (1.0 - m), lambda m: 0.3 + 0.5 * m**2],
    ids=["inverted", "non-monotone", "monotone"],
)
def test_an_intensity_function_of_the_moving_image_is_found_back(relation):
    """fixed = f(moving) exactly: the map is f up to its piecewise-linear reading between bin centres, away from the
    first and last bins (the moving intensities start at 0.02: the second bin's mean lies off its centre)."""
    moving, fixed = _pair(relation)
    matched = match_contrast(moving, fixed, 64)
    interior = (moving > 3 / 64) & (moving < 1 - 3 / 64)
    assert np.abs(matched - fixed)[interior].max() < 1e-3
    assert matched.dtype == np.float32 and matched.shape == moving.shape


def test_the_map_is_each_bins_conditional_mean_read_linearly_between_centres():
    """Against a brute-force mean per bin, with noise in the fixed image: at each bin's centre the map is that mean."""
    rng = np.random.default_rng(1)
    moving = np.round(rng.uniform(0, 1, 100_000) * 32 - 0.5).clip(0, 31).astype(np.float32) / 32 + 1 / 64  # centres
    fixed = (np.sin(6 * moving) ** 2 + 0.1 * rng.standard_normal(moving.shape)).astype(np.float32)
    matched = match_contrast(moving, fixed, 32)
    expected = _conditional_means(moving, fixed, 32, np.ones(moving.shape, bool))
    bins = np.clip((moving * 32).astype(int), 0, 31)
    np.testing.assert_allclose(matched, expected[bins], atol=1e-5)


def test_the_shared_background_does_not_count_and_the_moving_background_stays_zero():
    moving, fixed = _pair(lambda m: 1.0 - m)
    alone = match_contrast(moving, fixed, 16)
    padded = match_contrast(np.r_[moving, np.zeros(10**6, np.float32)], np.r_[fixed, np.zeros(10**6, np.float32)], 16)
    np.testing.assert_array_equal(padded[: moving.size], alone)
    assert not padded[moving.size :].any()
    # moving background against fixed tissue (a misaligned edge) counts, but the moving 0 is not mapped
    edge = match_contrast(np.r_[moving, np.zeros(500, np.float32)], np.r_[fixed, np.ones(500, np.float32)], 16)
    assert not edge[moving.size :].any()


def test_only_the_voxels_inside_count():
    moving, fixed = _pair(lambda m: 1.0 - m)
    damaged = fixed.copy()
    damaged[: moving.size // 3] = 1.0  # a lesion or artefact the mask leaves out
    inside = np.ones(moving.shape, bool)
    inside[: moving.size // 3] = False
    np.testing.assert_array_equal(
        match_contrast(moving, damaged, 16, inside), match_contrast(moving, fixed, 16, inside)
    )
    assert np.abs(match_contrast(moving, damaged, 16) - fixed).max() > 0.1  # without the mask it would count


def test_a_bin_with_too_few_voxels_is_read_from_its_neighbours():
    moving, fixed = _pair(lambda m: m)
    moving[(moving >= 0.5) & (moving < 0.5 + 1 / 8)] = 0.45  # empty bin 4 of 8
    moving[:5] = 0.5625  # ... but for 5 voxels at its centre, of another fixed intensity
    fixed[:5] = 1.0
    matched = match_contrast(moving, fixed, 8)
    means = _conditional_means(moving, fixed, 8, np.ones(moving.shape, bool))
    assert CONTRAST_MATCH_MIN_COUNT > 5
    assert matched[0] == pytest.approx(0.5 * (means[3] + means[5]), abs=1e-6)  # halfway between bins 3 and 5


def test_on_a_3d_grid_the_shape_and_values_are_kept_voxel_by_voxel():
    moving = np.random.default_rng(2).uniform(0, 1, (20, 24, 16)).astype(np.float32)
    fixed = 1.0 - moving
    matched = match_contrast(moving, fixed, 32)
    assert matched.shape == moving.shape
    assert np.abs(matched - fixed)[(moving > 0.05) & (moving < 0.95)].max() < 5e-3


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"fixed": np.zeros(5)}, r"one grid.*\(10,\).*\(5,\)"),
        ({"num_bins": 1}, r"num_bins must be an integer >= 2; got 1"),
        ({"num_bins": 2.5}, r"num_bins must be an integer >= 2; got 2.5"),
        ({"inside": np.ones(3, bool)}, r"inside must have the images' shape \(10,\); got \(3,\)"),
    ],
)
def test_bad_arguments_say_what_was_expected(kwargs, message):
    arguments = {"moving": np.linspace(0, 1, 10), "fixed": np.linspace(1, 0, 10), "num_bins": 4, **kwargs}
    with pytest.raises(ValueError, match=message):
        match_contrast(**arguments)


def test_images_that_share_too_little_are_refused_and_the_command_says_so():
    moving = np.full((8, 8, 8), 0.5, np.float32)  # one intensity: one bin
    fixed = np.random.default_rng(3).uniform(0, 1, moving.shape).astype(np.float32)
    with pytest.raises(ValueError, match=r"at least 2 intensity bins with 20 voxels.*got 1"):
        match_contrast(moving, fixed, 16)
    with pytest.raises(InputError, match=r"^--match-contrast: expected at least 2 intensity bins"):
        matched_input(moving, fixed, None, 16)


def test_the_commands_masks_are_where_the_map_is_read():
    """matched_input counts the voxels inside both cost-function masks (at the masks' level), as the refinement does."""
    moving = np.random.default_rng(4).uniform(0.05, 1, (16, 16, 16)).astype(np.float32)
    fixed = 1.0 - moving
    damaged = fixed.copy()
    damaged[:6] = 1.0
    fixed_mask = np.ones_like(moving)
    fixed_mask[:4] = 0.0
    moving_mask = np.ones_like(moving)
    moving_mask[4:6] = 0.2  # below the masks' level
    got = matched_input(moving, damaged, (fixed_mask, moving_mask), 16)
    np.testing.assert_array_equal(
        got, match_contrast(moving, fixed, 16, np.ones(moving.shape, bool) & (np.arange(16) >= 6)[:, None, None])
    )
    np.testing.assert_array_equal(matched_input(moving, fixed, (None, None), 16), match_contrast(moving, fixed, 16))


@pytest.mark.parametrize("value", [-1, 1, 2.5, 64.0, "64", True, None])
def test_a_bin_count_is_zero_or_an_integer_of_at_least_two(value):
    with pytest.raises(ValueError, match=r"contrast_match_bins must be 0 \(none\) or an integer >= 2; got"):
        check_contrast_match_bins(value)


@pytest.mark.parametrize("value", [0, 2, 64, np.int64(32)])
def test_a_good_bin_count_comes_back_as_an_int(value):
    assert check_contrast_match_bins(value) == int(value) and type(check_contrast_match_bins(value)) is int
