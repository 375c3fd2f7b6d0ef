"""The pair's residual on the velocity grid: zero where the images agree, the local squared difference where not,
area-averaged onto the velocity grid, in the grid's axis order (an asymmetric difference lands where it is); a local
gain (a bias field) leaves none, and the noise of single voxels is averaged down by the smoothing."""

from __future__ import annotations

import pytest
import torch

from monai_probreg.uncertainty.residual import (
    RESIDUAL_GAIN_WINDOW,
    RESIDUAL_SMOOTHING,
    RESIDUAL_WINDOW,
    residual_variance,
)

PLAIN = {"smoothing": 1, "gain_window": 1}  # the squared difference itself: no smoothing, no gain


def test_identical_images_have_no_residual_2d_and_3d():
    for shape in ((1, 1, 12, 16), (1, 1, 8, 12, 16)):
        image = torch.rand(shape)
        velocity = tuple(n // 4 for n in shape[2:])
        residual = residual_variance(image, image.clone(), velocity)
        assert residual.shape == (1, 1, *velocity)
        assert torch.equal(residual, torch.zeros_like(residual))


def test_a_constant_difference_gives_its_square_inside_and_the_box_shares_it_at_the_border():
    fixed = torch.zeros(1, 1, 24, 24, 24)
    residual = residual_variance(fixed + 0.1, fixed, (6, 6, 6), **PLAIN)
    inside = residual[0, 0, 2:4, 2:4, 2:4]  # cells whose box never leaves the grid
    torch.testing.assert_close(inside, torch.full_like(inside, 0.01))
    assert residual[0, 0, 0, 0, 0] < 0.01  # the box counts the voxels outside the image as zeros


def test_the_residual_lands_in_the_cell_of_the_difference_along_each_axis():
    # one differing block near the end of axis 0, the start of axis 1 and the middle of axis 2: asymmetric
    fixed = torch.zeros(1, 1, 32, 24, 16)
    warped = fixed.clone()
    warped[0, 0, 24:28, 4:8, 6:10] = 1.0
    residual = residual_variance(warped, fixed, (8, 6, 4), window=1, **PLAIN)
    peak = torch.nonzero(residual[0, 0] == residual.max())[0].tolist()
    assert peak == [6, 1, 1] or peak == [6, 1, 2]  # voxels 24-27 -> cell 6 of 8; 4-7 -> 1 of 6; 6-9 straddle 1 and 2
    assert residual[0, 0, 6, 1].sum() == pytest.approx(64 / (4 * 4 * 4) * 1.0)  # 64 voxels of 1 over cells of 64


def test_channels_are_averaged():
    fixed = torch.zeros(1, 2, 8, 8)
    warped = fixed.clone()
    warped[:, 0] = 1.0
    torch.testing.assert_close(
        residual_variance(warped, fixed, (8, 8), window=1, **PLAIN), torch.full((1, 1, 8, 8), 0.5)
    )


def test_the_defaults_still_place_an_asymmetric_block_in_its_cell():
    fixed = torch.full((1, 1, 32, 24, 16), 0.5)
    warped = fixed.clone()
    warped[0, 0, 24:28, 4:8, 6:10] = 1.0
    residual = residual_variance(warped, fixed, (8, 6, 4))
    peak = torch.nonzero(residual[0, 0] == residual.max())[0].tolist()
    assert peak[:2] == [6, 1] and peak[2] in (1, 2)


@pytest.mark.parametrize("spatial", [(64, 72), (40, 44, 72)])
def test_a_smooth_gain_leaves_almost_no_residual_where_the_plain_difference_leaves_much(spatial):
    generator = torch.Generator().manual_seed(0)
    fixed = 0.2 + 0.6 * torch.rand((1, 1, *spatial), generator=generator)
    ramp = torch.linspace(0.8, 1.2, spatial[-1])  # a bias field along the last axis
    warped = fixed * ramp
    inside = (..., *[slice(13, n - 13) for n in spatial])  # voxels whose gain box never leaves the grid
    plain = residual_variance(warped, fixed, spatial, window=1, **PLAIN)[inside]
    corrected = residual_variance(warped, fixed, spatial, window=1, smoothing=1)[inside]
    assert corrected.mean() < 0.02 * plain.mean()


def test_the_smoothing_averages_white_noise_down_by_the_box_volume():
    generator = torch.Generator().manual_seed(1)
    fixed = torch.full((1, 1, 40, 40, 40), 0.5)
    sigma = 0.1
    warped = fixed + sigma * torch.randn(fixed.shape, generator=generator)
    residual = residual_variance(warped, fixed, (40, 40, 40), window=9, smoothing=3, gain_window=1)
    inside = residual[0, 0, 6:-6, 6:-6, 6:-6]  # boxes that never leave the grid
    assert float(inside.mean()) == pytest.approx(sigma**2 / 27, rel=0.1)
    plain = residual_variance(warped, fixed, (40, 40, 40), window=9, **PLAIN)[0, 0, 6:-6, 6:-6, 6:-6]
    assert float(plain.mean()) == pytest.approx(sigma**2, rel=0.1)


def test_the_defaults_are_odd_boxes():
    for size in (RESIDUAL_WINDOW, RESIDUAL_SMOOTHING, RESIDUAL_GAIN_WINDOW):
        assert size >= 1 and size % 2 == 1


@pytest.mark.parametrize(
    ("name", "size"), [("smoothing", 2), ("smoothing", 0), ("gain_window", 4), ("gain_window", True), ("window", 2.0)]
)
def test_bad_box_sizes_are_refused(name, size):
    image = torch.zeros(1, 1, 8, 8)
    with pytest.raises(ValueError, match=f"{name} must be an odd number of voxels"):
        residual_variance(image, image, (4, 4), **{name: size})


@pytest.mark.parametrize(
    ("warped", "fixed", "velocity", "window", "message"),
    [
        ((1, 1, 8, 8), (1, 1, 8, 9), (4, 4), RESIDUAL_WINDOW, "of one shape"),
        ((1, 8, 8), (1, 8, 8), (4,), RESIDUAL_WINDOW, "2D or 3D"),
        ((1, 1, 8, 8), (1, 1, 8, 8), (4, 4, 4), RESIDUAL_WINDOW, "expected 2 velocity grid sizes"),
        ((1, 1, 8, 8), (1, 1, 8, 8), (4, 0), RESIDUAL_WINDOW, "expected 2 velocity grid sizes >= 1"),
        ((1, 1, 8, 8), (1, 1, 8, 8), (4, 4), 4, "window must be an odd number"),
    ],
)
def test_bad_input_is_refused(warped, fixed, velocity, window, message):
    with pytest.raises(ValueError, match=message):
        residual_variance(torch.zeros(warped), torch.zeros(fixed), velocity, window)
