"""A displacement resized onto a box of a finer grid: the box of the whole resize, its matrices and its gradient."""

from __future__ import annotations

import pytest
import torch

from monai_probreg.blocks.box_resize import interpolation_matrix, resize_displacement_box
from monai_probreg.blocks.integration import resize_displacement

# asymmetric sizes and boxes: a swapped axis or a box read from the wrong corner changes the answer
CASES = {
    2: ((7, 5), (19, 13), ((2, 0), (17, 9))),
    3: ((5, 7, 4), (13, 20, 9), ((1, 3, 0), (12, 17, 6))),
}


def _field(source: tuple[int, ...], dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(len(source))
    return torch.randn(2, len(source), *source, generator=g, dtype=dtype)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_the_box_of_the_whole_resize(spatial_dims):
    source, target, (starts, stops) = CASES[spatial_dims]
    field = _field(source)
    whole = resize_displacement(field, target)
    box = (slice(None), slice(None), *(slice(a, b) for a, b in zip(starts, stops)))
    out = resize_displacement_box(field, target, (starts, stops))
    assert out.shape == whole[box].shape
    torch.testing.assert_close(out, whole[box], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_the_whole_grid_as_a_box(spatial_dims):
    source, target, _ = CASES[spatial_dims]
    field = _field(source, torch.float64)
    out = resize_displacement_box(field, target, ([0] * spatial_dims, list(target)))
    torch.testing.assert_close(out, resize_displacement(field, target))


def test_a_constant_field_keeps_its_value_in_target_voxels():
    """A constant displacement of 1 source voxel along axis k is (m_k - 1) / (n_k - 1) target voxels everywhere."""
    source, target, region = CASES[3]
    field = torch.zeros(1, 3, *source)
    field[:, 1] = 1.0
    out = resize_displacement_box(field, target, region)
    torch.testing.assert_close(out[:, 1], torch.full_like(out[:, 1], (target[1] - 1) / (source[1] - 1)))
    assert out[:, 0].abs().max() == 0 and out[:, 2].abs().max() == 0


def test_interpolation_matrix_rows():
    weights = interpolation_matrix(3, 5, 1, 5, torch.float64)
    expected = torch.tensor([[0.5, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(weights, expected)
    torch.testing.assert_close(interpolation_matrix(4, 9, 0, 9, torch.float64).sum(dim=1), torch.ones(9).double())


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_gradcheck(spatial_dims):
    source = (3, 4, 3)[:spatial_dims]
    target = (5, 7, 4)[:spatial_dims]
    region = ((1, 2, 0)[:spatial_dims], (4, 7, 3)[:spatial_dims])
    field = _field(source, torch.float64)[:1].requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: resize_displacement_box(f, target, region), (field,))


@pytest.mark.parametrize(
    "source, target, start, stop, match",
    [(1, 5, 0, 5, "at least 2"), (4, 1, 0, 1, "at least 2"), (4, 9, 3, 3, "start < stop"), (4, 9, 0, 10, "<= 9")],
)
def test_interpolation_matrix_rejects(source, target, start, stop, match):
    with pytest.raises(ValueError, match=match):
        interpolation_matrix(source, target, start, stop, torch.float32)


def test_rejects_a_field_without_one_channel_per_axis():
    with pytest.raises(ValueError, match=r"expected a \(B, D, \*S\) field"):
        resize_displacement_box(torch.zeros(1, 2, 4, 4, 4), (8, 8, 8), ((0, 0, 0), (8, 8, 8)))


def test_rejects_a_region_of_other_dims():
    with pytest.raises(ValueError, match="expected 3 target sizes"):
        resize_displacement_box(torch.zeros(1, 3, 4, 4, 4), (8, 8, 8), ((0, 0), (8, 8)))
