"""Pull-back warping: ``warped[x] = image[x + ddf[x]]``, channel k of ``ddf`` along tensor axis 2 + k, voxels.

Note on exactness: MONAI's ``Warp`` maps voxel indices to [-1, 1] (``x * 2 / (n - 1) - 1``) and
``grid_sample`` maps them back; that round trip is exact in binary floating point only when ``n - 1`` is a
power of two. Tests that claim bit-exact results use such sizes (5, 9, 17); elsewhere a tolerance of a few
float32 ulps (1e-6 .. 1e-5) absorbs the round trip.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from monai.networks.blocks import Warp

from monai_probreg import CachedWarp, SpatialTransformer, compose_displacements, warp_image, warp_labels, warp_one_hot
from monai_probreg.blocks.warp import MIN_POINTS_PER_THREAD, sampling_grid, split_grid_sample, warp_box

SHAPES = {2: (7, 9), 3: (5, 7, 9)}  # non-cubic, so that an axis flip cannot go unnoticed
CASES = [(2, 0), (2, 1), (3, 0), (3, 1), (3, 2)]  # (spatial_dims, axis)


def _smooth_field(spatial, max_mag, seed, dtype=torch.float32):
    """Random smooth displacement (1, D, *spatial): trilinear upsampling of a 3^D random grid."""
    g = torch.Generator().manual_seed(seed)
    d = len(spatial)
    coarse = torch.randn(1, d, *([3] * d), generator=g, dtype=dtype)
    field = F.interpolate(coarse, size=spatial, mode="bilinear" if d == 2 else "trilinear", align_corners=True)
    return field * (max_mag / field.abs().max())


@pytest.mark.parametrize("spatial_dims, axis", CASES)
def test_positive_displacement_pulls_from_higher_index(spatial_dims, axis):
    shape = SHAPES[spatial_dims]
    bright = [s // 2 for s in shape]
    image = torch.zeros(1, 1, *shape)
    image[(0, 0, *bright)] = 1.0
    ddf = torch.zeros(1, spatial_dims, *shape)
    ddf[:, axis] = 1.0
    warped = warp_image(image, ddf)
    expected = list(bright)
    expected[axis] -= 1  # warped(x) = image(x + 1): the bright voxel shows up one index lower
    assert warped[0, 0].argmax().item() == np.ravel_multi_index(expected, shape)
    # 1e-6: only the index normalisation round trip (a few float32 ulps) separates this from exactly 1 and 0
    assert warped[(0, 0, *expected)].item() == pytest.approx(1.0, abs=1e-6)
    assert warped.sum().item() == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("spatial_dims, axis", CASES)
def test_integer_shift_is_an_exact_index_shift(spatial_dims, axis):
    # sizes with n - 1 a power of two: normalisation is exact, so an integer shift is an exact copy
    shape = {2: (9, 17), 3: (5, 9, 17)}[spatial_dims]
    image = torch.rand(2, 3, *shape)
    ddf = torch.zeros(2, spatial_dims, *shape)
    ddf[:, axis] = 2.0
    warped = warp_image(image, ddf)
    n = shape[axis]
    ax = 2 + axis
    assert torch.equal(warped.narrow(ax, 0, n - 2), image.narrow(ax, 2, n - 2))
    # border padding: the last two slices repeat the last slice of the image
    last = image.narrow(ax, n - 1, 1)
    assert torch.equal(warped.narrow(ax, n - 2, 2), torch.cat([last, last], dim=ax))


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_zero_displacement_returns_the_image(spatial_dims):
    shape = {2: (9, 17), 3: (5, 9, 17)}[spatial_dims]
    image = torch.rand(2, 3, *shape)
    warped = warp_image(image, torch.zeros(2, spatial_dims, *shape))
    assert torch.equal(warped, image)  # exact (n - 1 a power of two, see the module docstring)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_zero_displacement_any_size_within_float_ulps(spatial_dims):
    shape = SHAPES[spatial_dims]
    image = torch.rand(2, 3, *shape)
    warped = warp_image(image, torch.zeros(2, spatial_dims, *shape))
    # 1e-6 on values in [0, 1]: a few float32 ulps from the [-1, 1] normalisation round trip, nothing more
    torch.testing.assert_close(warped, image, atol=1e-6, rtol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_compose_displacements_order(spatial_dims):
    """compose(outer, inner) = inner + outer o (id + inner): warping by it = warp by outer, then by inner."""
    shape = {2: (9, 17), 3: (5, 9, 17)}[spatial_dims]
    outer = _smooth_field(shape, 1.5, seed=1)
    inner = torch.zeros_like(outer)
    inner[:, -1] = 2.0  # an integer translation: no interpolation in the second warp
    composed = compose_displacements(outer, inner)
    interior = (Ellipsis, slice(0, shape[-1] - 2))  # x + 2 stays inside the grid
    # exact: x + 2 is a grid point and n - 1 is a power of two (see the module docstring)
    assert torch.equal(composed[interior], inner[interior] + outer[..., 2:])
    image = torch.rand(1, 2, *shape)
    sequential = warp_image(warp_image(image, outer), inner)  # (I o phi_outer) o phi_inner
    # 1e-6: both sides interpolate `image` once at the same points; only float rounding differs
    torch.testing.assert_close(warp_image(image, composed)[interior], sequential[interior], atol=1e-6, rtol=0)


def test_warp_labels_keeps_the_label_set():
    g = torch.Generator().manual_seed(0)
    values = torch.tensor([0, 3, 7, 12])
    labels = values[torch.randint(0, 4, (2, 1, 10, 11, 9), generator=g)]
    ddf = torch.cat([_smooth_field((10, 11, 9), 2.5, seed=s) for s in (2, 3)])  # non-integer, some outside
    warped = warp_labels(labels, ddf)
    assert warped.dtype == labels.dtype and warped.shape == labels.shape
    assert set(warped.unique().tolist()) <= set(values.tolist())  # no blended values like 1.5 or 5
    assert not torch.equal(warped, labels)  # it did move something


def test_warp_labels_integer_shift_and_outside_is_zero():
    labels = torch.randint(1, 5, (1, 1, 9, 17))
    ddf = torch.zeros(1, 2, 9, 17)
    ddf[:, 1] = 3.0
    warped = warp_labels(labels, ddf)
    assert torch.equal(warped[..., :14], labels[..., 3:])
    assert torch.equal(warped[..., 14:], torch.zeros_like(warped[..., 14:]))  # zeros padding for labels


def test_warp_labels_accepts_integer_valued_floats():
    labels = torch.randint(0, 4, (1, 1, 9, 9)).float()
    warped = warp_labels(labels, torch.zeros(1, 2, 9, 9))
    assert warped.dtype == torch.float32
    assert torch.equal(warped, labels)


def test_warp_labels_rejects_non_integer_floats():
    labels = torch.randint(0, 4, (1, 1, 8, 8)).float()
    labels[0, 0, 2, 3] = 1.5
    with pytest.raises(ValueError, match="integer"):
        warp_labels(labels, torch.zeros(1, 2, 8, 8))


@pytest.mark.parametrize("spatial_dims, axis", CASES)
def test_warp_one_hot_integer_shift(spatial_dims, axis):
    shape = SHAPES[spatial_dims]
    labels = torch.randint(0, 3, (2, *shape))
    one_hot = F.one_hot(labels, 3).movedim(-1, 1).float()  # (B, L, *S)
    ddf = torch.zeros(2, spatial_dims, *shape)
    ddf[:, axis] = 2.0
    warped = warp_one_hot(one_hot, ddf)
    n, ax = shape[axis], 2 + axis
    expected = torch.zeros_like(one_hot)  # zeros padding: nothing comes in from outside the grid
    expected.narrow(ax, 0, n - 2).copy_(one_hot.narrow(ax, 2, n - 2))
    # 1e-5: integer sample points, up to the float32 round trip of the index normalisation
    torch.testing.assert_close(warped, expected, atol=1e-5, rtol=0)


def test_warp_one_hot_is_differentiable():
    one_hot = F.one_hot(torch.randint(0, 3, (1, 8, 8)), 3).movedim(-1, 1).float()
    ddf = (0.3 * torch.randn(1, 2, 8, 8)).requires_grad_()
    warp_one_hot(one_hot, ddf).pow(2).sum().backward()
    assert ddf.grad is not None and ddf.grad.abs().sum() > 0


def test_cached_warp_reuses_grid_across_calls():
    warp = CachedWarp(fast=False)  # the reference-grid cache belongs to MONAI's path
    image, ddf = torch.rand(2, 1, 6, 7), torch.randn(2, 2, 6, 7)
    warp(image, ddf)
    grid = warp.ref_grid
    assert grid.shape == (1, 2, 6, 7)  # one grid, broadcast over the batch
    warp(torch.rand(2, 1, 6, 7), torch.randn(2, 2, 6, 7))
    assert warp.ref_grid is grid
    warp(torch.rand(5, 1, 6, 7), torch.randn(5, 2, 6, 7))  # another batch size: same spatial grid
    assert warp.ref_grid is grid


def test_cached_warp_rebuilds_grid_on_shape_or_dtype_change():
    warp = CachedWarp(fast=False)
    warp(torch.rand(1, 1, 6, 7), torch.zeros(1, 2, 6, 7))
    grid_a = warp.ref_grid
    warp(torch.rand(1, 1, 6, 8), torch.zeros(1, 2, 6, 8))
    grid_b = warp.ref_grid
    assert grid_b is not grid_a and grid_b.shape == (1, 2, 6, 8)
    warp(torch.rand(1, 1, 6, 8, dtype=torch.float64), torch.zeros(1, 2, 6, 8, dtype=torch.float64))
    grid_c = warp.ref_grid
    assert grid_c is not grid_b and grid_c.dtype == torch.float64
    warp(torch.rand(1, 1, 4, 5, 6), torch.zeros(1, 3, 4, 5, 6))
    assert warp.ref_grid.shape == (1, 3, 4, 5, 6)
    # the grid holds the voxel index along axis k in channel k
    assert torch.equal(warp.ref_grid[0, 1, :, 3, :], torch.full((4, 6), 3.0))


@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("spatial_dims", [2, 3])
@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
@pytest.mark.parametrize("padding_mode", ["border", "zeros", "reflection"])
def test_cached_warp_matches_monai_warp(spatial_dims, mode, padding_mode, fast):
    g = torch.Generator().manual_seed(spatial_dims)
    shape = SHAPES[spatial_dims]
    image = torch.rand(2, 3, *shape, generator=g)
    ddf = 3.0 * torch.randn(2, spatial_dims, *shape, generator=g)  # reaches outside the grid: padding matters
    ours = CachedWarp(mode=mode, padding_mode=padding_mode, fast=fast)
    monai = Warp(mode=mode, padding_mode=padding_mode)
    # fast=False, 1e-6: same arithmetic as MONAI (grid + ddf, same normalisation, same grid_sample), only the grid's
    # construction differs (float arange vs int arange cast, both exact), so any gap is float noise.
    # fast=True, 5e-6: the normalised coordinate i * s - 1 + u * s (s = 2 / (n - 1)) is summed in another order than
    # MONAI's (i + u) * s - 1, a few ulps of a value <= 4 in size (~1e-6, measured max 1.3e-6 here), times the
    # image's slope (< 1 per normalised unit for values in [0, 1] on these grids, measured gap 1.25e-6)
    atol = 5e-6 if fast else 1e-6
    for _ in range(2):  # second call goes through our cache
        torch.testing.assert_close(ours(image, ddf), monai(image, ddf), atol=atol, rtol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_sampling_grid_is_the_normalised_pull_back_in_xyz_order(spatial_dims):
    shape = SHAPES[spatial_dims]
    ddf = torch.randn(2, spatial_dims, *shape, generator=torch.Generator().manual_seed(0))
    index = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij"))
    sizes = torch.tensor(shape, dtype=torch.float32).view(1, spatial_dims, *[1] * spatial_dims)
    expected = ((index + ddf) * 2 / (sizes - 1) - 1).movedim(1, -1).flip(-1)  # grid_sample: last axis x, y, z
    grid = sampling_grid(ddf)
    assert grid.shape == (2, *shape, spatial_dims)
    torch.testing.assert_close(grid, expected, atol=2e-6, rtol=0)  # ulps of values up to ~4 (see above)
    with torch.enable_grad():  # the differentiable (stacked) branch builds the same grid
        differentiable = sampling_grid(ddf.clone().requires_grad_())
    assert differentiable.requires_grad
    torch.testing.assert_close(differentiable, grid, atol=1e-6, rtol=0)


@pytest.mark.parametrize("num_splits", [2, 3, 7])
@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
def test_split_grid_sample_is_bit_identical_to_one_call(num_splits, mode):
    """The split only changes which thread samples which point: each point's arithmetic is the same."""
    g = torch.Generator().manual_seed(num_splits)
    image = torch.rand(1, 3, 6, 7, 8, generator=g)  # rows S0 * S1 = 42: divisible by 2, 3 and 7
    grid = 1.2 * torch.rand(1, 6, 7, 8, 3, generator=g) - 0.6
    expected = F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=True)
    assert torch.equal(split_grid_sample(image, grid, mode, "border", num_splits=num_splits), expected)


def test_split_grid_sample_is_differentiable_and_checks_its_split():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(1, 2, 4, 3, 5, dtype=torch.float64, generator=g, requires_grad=True)
    grid = (1.6 * torch.rand(1, 4, 3, 5, 3, dtype=torch.float64, generator=g) - 0.8).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, x: split_grid_sample(i, x, num_splits=2), (image, grid))
    with pytest.raises(ValueError, match="divides"):
        split_grid_sample(image, grid, num_splits=5)  # 12 rows
    with pytest.raises(ValueError, match="one 3-d item"):
        split_grid_sample(image.expand(2, -1, -1, -1, -1), grid.expand(2, -1, -1, -1, -1), num_splits=2)


def test_split_is_automatic_for_one_large_item(monkeypatch):
    """With 2 threads a grid of 2 * MIN_POINTS_PER_THREAD points is cut in two, a small one is not."""
    calls = []
    real = F.grid_sample
    monkeypatch.setattr(
        F, "grid_sample", lambda image, grid, **kw: calls.append(image.shape[0]) or real(image, grid, **kw)
    )
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    shape = (64, 64, 2 * MIN_POINTS_PER_THREAD // 4096)
    image, ddf = torch.rand(1, 1, *shape), torch.zeros(1, 3, *shape)
    # zero displacement: the identity, up to the index normalisation round trip (module docstring): an ulp of 1
    # (1.2e-7) times (n - 1) / 2 <= 32 voxels -> < 4e-6 voxels, times a slope < 1 per voxel
    torch.testing.assert_close(warp_image(image, ddf), image, atol=1e-5, rtol=0)
    small = torch.rand(1, 1, 8, 8, 8)
    warp_image(small, torch.zeros(1, 3, 8, 8, 8))
    assert calls == [2, 1]


def test_spatial_transformer_matches_functional():
    image, ddf = torch.rand(1, 2, 6, 7), torch.randn(1, 2, 6, 7)
    assert torch.equal(SpatialTransformer()(image, ddf), warp_image(image, ddf))
    labels = torch.randint(0, 4, (1, 1, 6, 7))
    out = SpatialTransformer(mode="nearest", padding_mode="zeros")(labels.float(), ddf)
    assert torch.equal(out, warp_labels(labels, ddf).float())


def test_bad_ddf_shape_names_the_expected_shape():
    image = torch.rand(2, 1, 8, 9)
    expected = "(2, 2, 8, 9)"
    for ddf in (torch.zeros(2, 3, 8, 9), torch.zeros(2, 2, 8, 8), torch.zeros(1, 2, 8, 9), torch.zeros(2, 2, 8, 9, 1)):
        with pytest.raises(ValueError, match=re.escape(expected)):
            warp_image(image, ddf)
    with pytest.raises(ValueError, match=re.escape("(1, 3, 4, 5, 6)")):
        CachedWarp()(torch.rand(1, 1, 4, 5, 6), torch.zeros(1, 2, 4, 5, 6))


@pytest.mark.parametrize("image_shape", [(1, 1, 8), (1, 1, 2, 3, 4, 5)])
def test_bad_image_dims_raise(image_shape):
    ddf = torch.zeros(1, len(image_shape) - 2, *image_shape[2:])
    with pytest.raises(ValueError, match=re.escape(str(image_shape))):
        warp_image(torch.zeros(image_shape), ddf)


def _off_knot_field(shape, seed):
    """Small random displacement with |u| in [0.1, 0.4]: x + u never lands on (or near) a grid knot."""
    g = torch.Generator().manual_seed(seed)
    mag = 0.1 + 0.3 * torch.rand(shape, generator=g, dtype=torch.float64)
    sign = torch.where(torch.rand(shape, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    return mag * sign


@pytest.mark.parametrize("spatial_shape", [(4, 5), (3, 4, 3)])
@pytest.mark.parametrize("padding_mode", ["border", "zeros"])
def test_warp_image_gradcheck(spatial_shape, padding_mode):
    d = len(spatial_shape)
    image = torch.rand(1, 2, *spatial_shape, dtype=torch.float64, requires_grad=True)
    ddf = _off_knot_field((1, d, *spatial_shape), seed=d).requires_grad_()
    # linear interpolation is piecewise linear: gradcheck's finite differences (eps 1e-6) are valid because no
    # sample point is within 0.1 voxel of a knot (and none sits on the border clamp)
    assert torch.autograd.gradcheck(lambda i, u: warp_image(i, u, padding_mode=padding_mode), (image, ddf))


@pytest.mark.parametrize("spatial_dims", [2, 3])
@pytest.mark.parametrize("padding_mode", ["border", "zeros"])
def test_warp_box_is_the_box_of_the_whole_warp(spatial_dims, padding_mode):
    """warp_box samples the whole image at origin + x + ddf(x) for a field on a box: the box of warp_image's result
    (values and both gradients), on an asymmetric box of a non-cubic grid."""
    spatial = SHAPES[spatial_dims]
    starts, stops = (1, 2, 3)[:spatial_dims], (5, 6, 8)[:spatial_dims]
    box = (slice(None), slice(None), *(slice(a, b) for a, b in zip(starts, stops)))
    image = torch.rand(1, 2, *spatial, dtype=torch.float64, requires_grad=True)
    ddf = _smooth_field(spatial, 2.5, seed=spatial_dims, dtype=torch.float64).requires_grad_()
    whole = warp_image(image, ddf, padding_mode=padding_mode)[box]
    part = warp_box(image, ddf[box], starts, padding_mode=padding_mode)
    torch.testing.assert_close(part, whole, rtol=1e-12, atol=1e-12)
    weights = torch.rand_like(whole)
    expected = torch.autograd.grad((whole * weights).sum(), (image, ddf))
    got = torch.autograd.grad((part * weights).sum(), (image, ddf))
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)


def test_warp_box_names_a_bad_origin():
    with pytest.raises(ValueError, match="expected 3 origin indices"):
        warp_box(torch.rand(1, 1, 5, 7, 9), torch.zeros(1, 3, 2, 2, 2), (0, 1))
