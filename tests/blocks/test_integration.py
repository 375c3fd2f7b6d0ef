"""Scaling and squaring (``exp`` of a stationary velocity) and align-corners resizing of displacement fields."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from monai.networks.blocks import DVF2DDF

from monai_probreg import (
    DisplacementResize,
    ScalingAndSquaring,
    compose_displacements,
    integrate_velocity,
    resize_displacement,
    warp_image,
)

SHAPES = {2: (12, 10), 3: (12, 10, 9)}


def _interp_mode(spatial_dims):
    return "bilinear" if spatial_dims == 2 else "trilinear"


def _smooth_velocity(spatial, max_mag, seed, coarse=4, dtype=torch.float32):
    """Smooth random velocity (1, D, *spatial): linear upsampling of a coarse^D random grid, max |v| = max_mag."""
    g = torch.Generator().manual_seed(seed)
    d = len(spatial)
    c = torch.randn(1, d, *([coarse] * d), generator=g, dtype=dtype)
    v = F.interpolate(c, size=spatial, mode=_interp_mode(d), align_corners=True)
    return v * (max_mag / v.abs().max())


def _interior(field, margin):
    return field[(Ellipsis, *[slice(margin, -margin)] * (field.ndim - 2))]


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_zero_velocity_gives_zero_displacement(spatial_dims):
    shape = SHAPES[spatial_dims]
    disp = integrate_velocity(torch.zeros(2, spatial_dims, *shape))
    assert torch.equal(disp, torch.zeros_like(disp))  # exact: interpolating zeros gives zeros
    image = torch.rand(2, 1, *shape)
    # identity warp up to the index normalisation round trip (a few float32 ulps on values in [0, 1])
    torch.testing.assert_close(warp_image(image, disp), image, atol=1e-6, rtol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_constant_velocity_integrates_to_translation(spatial_dims):
    shape = SHAPES[spatial_dims]
    c = torch.tensor([1.5, -0.7, 0.3][:spatial_dims])
    v = c.view(1, spatial_dims, *([1] * spatial_dims)).expand(1, spatial_dims, *shape).contiguous()
    disp = integrate_velocity(v)
    # 1e-5: border padding makes a constant field a fixed point of every squaring, so only float32 rounding
    # of the interpolation weights (7 steps, values ~1) remains, everywhere including the border
    torch.testing.assert_close(disp, v, atol=1e-5, rtol=0)

    # MONAI's DVF2DDF pads with zeros: on the face the translation points to, half the samples come from
    # outside and read 0, so its displacement shrinks there. This is why ScalingAndSquaring uses "border".
    monai_disp = DVF2DDF(num_steps=7)(v)
    last_face = monai_disp[0, 0].select(0, shape[0] - 1)  # c[0] = 1.5 > 0 pulls from beyond the last slice
    assert last_face.max() < 0.6 * c[0]  # measured 0.78 = 0.52 c: about half the samples read the zero padding
    assert (monai_disp[:, 0] - c[0]).abs().max() > 0.3  # our result is within 1e-5 of c everywhere


@pytest.mark.parametrize("seed", [0, 1])
def test_exp_v_composed_with_exp_minus_v_is_identity(seed):
    v = _smooth_velocity((32, 32, 32), max_mag=2.0, seed=seed)
    fwd = integrate_velocity(v)
    inv = integrate_velocity(-v)
    assert fwd.abs().max() > 1.5  # a real deformation, not a near-identity
    # Measured max interior error: 0.064 / 0.063 (seed 0), 0.039 / 0.038 (seed 1). It is the interpolation
    # error of scaling and squaring (7 linearly-interpolated compositions, then one more in the check) on a
    # field with gradients ~0.3 voxel/voxel; 0.15 is ~2.5x the worst measured. Margin 4 voxels: near the
    # faces the border extrapolation does not make exp(-v) the inverse of exp(v).
    assert _interior(compose_displacements(fwd, inv), 4).abs().max() < 0.15
    assert _interior(compose_displacements(inv, fwd), 4).abs().max() < 0.15


def test_inverse_composition_error_is_small_compared_with_the_field():
    v = _smooth_velocity((32, 32, 32), max_mag=2.0, seed=0)
    fwd, inv = integrate_velocity(v), integrate_velocity(-v)
    # mean error, not max: measured 0.0032 voxel; 0.01 is ~3x that, and the mean |displacement| (0.47) is
    # more than 50x the error
    err = _interior(compose_displacements(fwd, inv), 4).norm(dim=1).mean()
    assert err < 0.01
    assert _interior(fwd, 4).norm(dim=1).mean() > 50 * err


def test_scaling_and_squaring_module_matches_function():
    v = _smooth_velocity((16, 12), 2.0, seed=3)
    for steps in (1, 4, 7):
        assert torch.equal(ScalingAndSquaring(num_steps=steps)(v), integrate_velocity(v, num_steps=steps))


def test_single_step_is_one_explicit_composition():
    v = _smooth_velocity((9, 17), 1.0, seed=4)
    half = v / 2
    expected = half + warp_image(half, half)  # u <- u + u o (id + u), once
    assert torch.equal(integrate_velocity(v, num_steps=1), expected)


@pytest.mark.parametrize("num_steps", [0, -1])
def test_non_positive_num_steps_raises(num_steps):
    v = torch.zeros(1, 2, 8, 8)
    with pytest.raises(ValueError, match="num_steps"):
        integrate_velocity(v, num_steps=num_steps)
    with pytest.raises(ValueError, match="num_steps"):
        ScalingAndSquaring(num_steps=num_steps)


@pytest.mark.parametrize("shape", [(1, 3, 8, 8), (1, 2, 8, 8, 8), (1, 1, 8), (1, 4, 4, 4, 4, 4)])
def test_bad_velocity_shape_raises(shape):
    with pytest.raises(ValueError, match="spatial_dims"):
        integrate_velocity(torch.zeros(shape))


# ---------------------------------------------------------------------------------------------- resizing


@pytest.mark.parametrize(
    "src, dst",
    [((5, 9), (17, 12)), ((4, 6, 5), (7, 16, 9))],  # a different factor on every axis
)
def test_resize_constant_field(src, dst):
    d = len(src)
    c = torch.tensor([0.8, -1.3, 2.1][:d], dtype=torch.float64)
    field = c.view(1, d, *([1] * d)).expand(2, d, *src).contiguous()
    out = resize_displacement(field, dst)
    scale = torch.tensor([(m - 1) / (n - 1) for m, n in zip(dst, src)], dtype=torch.float64)
    expected = (c * scale).view(1, d, *([1] * d)).expand(2, d, *dst)
    torch.testing.assert_close(out, expected, atol=1e-12, rtol=0)  # float64, linear interp of a constant


@pytest.mark.parametrize("src, dst", [((5, 9), (17, 12)), ((4, 6, 5), (7, 16, 9))])
def test_resize_linear_field_is_the_same_physical_map(src, dst):
    """u(x) = A x + b on the coarse grid; on the fine grid the same map is u'(y) = s * (A (y / s) + b).

    With align_corners the coarse index x and fine index y of one physical point satisfy y_k = s_k x_k,
    s_k = (m_k - 1) / (n_k - 1); a displacement of u voxels of the coarse grid is s_k u voxels of the fine one.
    """
    d = len(src)
    g = torch.Generator().manual_seed(d)
    a = torch.randn(d, d, generator=g, dtype=torch.float64)
    b = torch.randn(d, generator=g, dtype=torch.float64)
    s = torch.tensor([(m - 1) / (n - 1) for m, n in zip(dst, src)], dtype=torch.float64)

    def linear_field(shape, coord_scale, value_scale):
        idx = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float64) for n in shape], indexing="ij"))
        x = idx / coord_scale.view(d, *([1] * d))  # coarse-grid coordinates of each voxel
        u = torch.einsum("kj,j...->k...", a, x) + b.view(d, *([1] * d))
        return (u * value_scale.view(d, *([1] * d))).unsqueeze(0)

    coarse = linear_field(src, torch.ones(d, dtype=torch.float64), torch.ones(d, dtype=torch.float64))
    fine = resize_displacement(coarse, dst)
    expected = linear_field(dst, s, s)
    # float64 and (bi/tri)linear interpolation reproduces linear functions exactly, up to rounding
    torch.testing.assert_close(fine, expected, atol=1e-10, rtol=0)
    # and the physical map is the same: moving coarse voxel 0 ends where fine voxel 0 ends, in fine units
    torch.testing.assert_close(fine[(0, slice(None), *[0] * d)], s * coarse[(0, slice(None), *[0] * d)])


def test_resize_same_size_is_a_no_op():
    field = torch.randn(1, 2, 6, 7)
    assert resize_displacement(field, (6, 7)) is field


def test_resize_round_trip_of_a_linear_field():
    field = torch.zeros(1, 2, 9, 17, dtype=torch.float64)
    field[:, 0] = 0.5
    field[:, 1] = torch.linspace(-1, 1, 17, dtype=torch.float64)
    back = resize_displacement(resize_displacement(field, (17, 33)), (9, 17))
    torch.testing.assert_close(back, field, atol=1e-12, rtol=0)  # linear field, nested grids: exact up to rounding


def test_displacement_resize_module_matches_function():
    field = torch.randn(2, 3, 4, 6, 5)
    assert torch.equal(DisplacementResize((7, 11, 9))(field), resize_displacement(field, (7, 11, 9)))


@pytest.mark.parametrize(
    "shape, size",
    [
        ((1, 2, 8, 8), (16, 16, 16)),  # 2-d field, 3-d target
        ((1, 3, 8, 8), (16, 16)),  # channels do not match the spatial dims
        ((1, 3, 8, 8, 8), (16, 16)),
        ((1, 2, 1, 8), (4, 16)),  # a 1-voxel axis has no extent to rescale
        ((1, 2, 8, 8), (1, 16)),
    ],
)
def test_resize_bad_shapes_raise(shape, size):
    with pytest.raises(ValueError):
        resize_displacement(torch.zeros(shape), size)


def test_resize_error_names_the_received_shape():
    with pytest.raises(ValueError, match=r"\(1, 3, 8, 8\)"):
        resize_displacement(torch.zeros(1, 3, 8, 8), (16, 16))


# ---------------------------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("shape", [(1, 2, 5, 6), (1, 3, 3, 4, 3)])
def test_scaling_and_squaring_gradcheck(shape):
    g = torch.Generator().manual_seed(0)
    # small random velocity, 0.2 <= |v| <= 0.8 voxel: after v / 4 every sample point is 0.05..0.2 voxel off the
    # grid points, so no finite-difference step of gradcheck (1e-6) crosses an interpolation knot (where
    # linear interpolation has no derivative)
    mag = 0.2 + 0.6 * torch.rand(shape, generator=g, dtype=torch.float64)
    sign = torch.where(torch.rand(shape, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    v = (mag * sign).requires_grad_()
    assert torch.autograd.gradcheck(ScalingAndSquaring(num_steps=2), (v,))
