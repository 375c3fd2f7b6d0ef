"""The voxel index -> grid_sample coordinate rule (monai_probreg.blocks.grid_coords), pinned on asymmetric grids."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from monai_probreg.blocks.grid_coords import index_scale, index_to_grid, index_to_grid_matrix, normalise_index
from monai_probreg.blocks.warp import identity_grid, sampling_grid

SHAPES = [(5, 8), (4, 7, 10)]


@pytest.mark.parametrize("shape", SHAPES)
def test_corners_map_to_minus_and_plus_one_in_xyz_order(shape):
    first = torch.zeros(len(shape), dtype=torch.float64)
    last = torch.tensor([n - 1 for n in shape], dtype=torch.float64)
    torch.testing.assert_close(index_to_grid(first, list(shape)), -torch.ones(len(shape), dtype=torch.float64))
    torch.testing.assert_close(index_to_grid(last, list(shape)), torch.ones(len(shape), dtype=torch.float64))
    # one step along tensor axis 0 moves the LAST grid coordinate (grid_sample's y in 2-d, z in 3-d)
    step = torch.zeros(len(shape), dtype=torch.float64)
    step[0] = 1.0
    moved = index_to_grid(step, list(shape)) - index_to_grid(torch.zeros_like(step), list(shape))
    expected = torch.zeros(len(shape), dtype=torch.float64)
    expected[-1] = 2.0 / (shape[0] - 1)
    torch.testing.assert_close(moved, expected)


@pytest.mark.parametrize("shape", SHAPES)
def test_round_trip_through_grid_sample_returns_the_index(shape):
    """Sampling each index ramp at index_to_grid(index) gives back the (non-integer) index itself."""
    dims = len(shape)
    ramps = identity_grid(shape, torch.float64, torch.device("cpu"))  # (1, D, *S): channel k = index along axis k
    points = torch.rand(1, 11, dims, dtype=torch.float64) * (torch.tensor(shape, dtype=torch.float64) - 1)
    grid = index_to_grid(points, list(shape)).view(1, 11, *([1] * (dims - 1)), dims)
    sampled = F.grid_sample(ramps, grid, mode="bilinear", padding_mode="border", align_corners=True)
    torch.testing.assert_close(sampled.reshape(dims, 11).T, points[0])


@pytest.mark.parametrize("shape", SHAPES)
def test_matrix_form_is_the_same_map(shape):
    dims = len(shape)
    points = torch.rand(6, dims, dtype=torch.float64) * 20 - 5
    matrix = index_to_grid_matrix(list(shape))
    homogeneous = torch.cat([points, torch.ones(6, 1, dtype=torch.float64)], dim=1)
    torch.testing.assert_close((homogeneous @ matrix.T)[:, :dims], index_to_grid(points, list(shape)))
    torch.testing.assert_close(matrix[dims], torch.eye(dims + 1, dtype=torch.float64)[dims])


@pytest.mark.parametrize("shape", [*SHAPES, (1, 6, 9)])
def test_callers_arithmetic_is_kept_bit_for_bit(shape):
    """Each form computes exactly what its callers computed before the rule moved here: point sampling's
    ``(index * 2 / max(n - 1, 1) - 1).flip(-1)`` with the slope first, the affine stage's and the inverse field's
    homogeneous matrix ``diag(slopes) - 1``, its rows reversed. MONAI's order (``normalise_index``, the warp's grid)
    differs from the slope-first one in the last bit, which is why both exist."""
    dims = len(shape)
    points = torch.rand(1000, dims, dtype=torch.float64) * (torch.tensor(shape, dtype=torch.float64) - 1)
    slopes = 2.0 / torch.clamp(torch.tensor(shape, dtype=torch.float64) - 1.0, min=1.0)
    assert torch.equal(index_to_grid(points, list(shape)), (points * slopes - 1.0).flip(-1))
    before = torch.diag(torch.cat([slopes, torch.ones(1, dtype=torch.float64)]))
    before[:dims, dims] = -1.0
    assert torch.equal(index_to_grid_matrix(list(shape)), before[[*reversed(range(dims)), dims]])
    monai_order = torch.stack([normalise_index(points[:, k], n) for k, n in enumerate(shape)], dim=-1).flip(-1)
    torch.testing.assert_close(monai_order, index_to_grid(points, list(shape)), rtol=0, atol=1e-15)


def test_singleton_axis_maps_to_minus_one_and_scale_is_the_slope():
    assert normalise_index(torch.zeros(1), 1).item() == -1.0
    assert index_scale(1) == 2.0 and index_scale(9) == 0.25
    x = torch.arange(9.0)
    torch.testing.assert_close(normalise_index(x + 1, 9) - normalise_index(x, 9), torch.full((9,), index_scale(9)))


@pytest.mark.parametrize("shape", SHAPES)
def test_sampling_grid_follows_the_rule(shape):
    ddf = torch.randn(2, len(shape), *shape, dtype=torch.float64)
    index = identity_grid(shape, torch.float64, torch.device("cpu")) + ddf
    torch.testing.assert_close(sampling_grid(ddf), index_to_grid(index.movedim(1, -1), list(shape)))


def test_wrong_coordinate_count_is_refused():
    with pytest.raises(ValueError, match="3 coordinates"):
        index_to_grid(torch.zeros(4, 2), [4, 5, 6])


def test_compiles_with_torchscript():
    scripted = torch.jit.script(index_to_grid)
    points = torch.rand(3, 3) * 4
    torch.testing.assert_close(scripted(points, [5, 6, 7]), index_to_grid(points, [5, 6, 7]))
