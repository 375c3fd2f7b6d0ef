"""Tests of the Jacobian determinant of displacement fields and of the folding statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_probreg import JacobianStats, jacobian_determinant, jacobian_stats

SHAPES = {2: (9, 11), 3: (6, 7, 8)}


def _coords(shape, dtype=torch.float64):
    """(D, *S): channel k = index along spatial axis k (the package convention)."""
    return torch.stack(torch.meshgrid(*[torch.arange(n, dtype=dtype) for n in shape], indexing="ij"))


def _affine_ddf(matrix, translation, shape, dtype=torch.float64):
    """u(x) = (A - I) x + t as (1, D, *S): u_k = sum_a (A - I)[k, a] x_a + t_k."""
    ndims = len(shape)
    a = torch.as_tensor(matrix, dtype=dtype) - torch.eye(ndims, dtype=dtype)
    t = torch.as_tensor(translation, dtype=dtype).view(ndims, *([1] * ndims))
    return (torch.einsum("ka,a...->k...", a, _coords(shape, dtype)) + t).unsqueeze(0)


def _random_near_identity(ndims, seed):
    gen = torch.Generator().manual_seed(seed)
    return torch.eye(ndims, dtype=torch.float64) + 0.15 * torch.randn(ndims, ndims, generator=gen, dtype=torch.float64)


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_affine_field_determinant_is_det_a_everywhere(ndims, seed):
    matrix = _random_near_identity(ndims, seed)
    translation = torch.randn(ndims, generator=torch.Generator().manual_seed(100 + seed), dtype=torch.float64)
    ddf = _affine_ddf(matrix, translation, SHAPES[ndims])
    det = jacobian_determinant(ddf)
    assert det.shape == (1, *SHAPES[ndims])
    expected = torch.linalg.det(matrix).item()
    assert expected > 0
    # central and one-sided differences are exact for linear fields, borders included; float64 rounding of
    # coordinates up to ~10 leaves ~1e-14
    torch.testing.assert_close(det, torch.full_like(det, expected), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("ndims", [2, 3])
def test_affine_field_float32(ndims):
    matrix = _random_near_identity(ndims, 7)
    ddf = _affine_ddf(matrix, [0.5] * ndims, SHAPES[ndims], dtype=torch.float32)
    det = jacobian_determinant(ddf)
    assert det.dtype == torch.float32
    # float32 differences of values up to ~10: a few 1e-6 absolute
    torch.testing.assert_close(det, torch.full_like(det, torch.linalg.det(matrix).item()), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("ndims", [2, 3])
def test_affine_field_with_negative_determinant_folds_everywhere(ndims):
    flip = torch.eye(ndims, dtype=torch.float64)
    flip[0, 0] = -1.0
    matrix = flip @ _random_near_identity(ndims, 3)
    expected = torch.linalg.det(matrix).item()
    assert expected < 0
    det = jacobian_determinant(_affine_ddf(matrix, [1.0] * ndims, SHAPES[ndims]))
    # exact for linear fields, float64 rounding only
    torch.testing.assert_close(det, torch.full_like(det, expected), rtol=1e-12, atol=1e-12)
    stats = jacobian_stats(det)
    n = math.prod(SHAPES[ndims])
    assert stats.num_folding == n
    assert stats.percent_folding == 100.0
    assert math.isnan(stats.std_log_jacobian)  # no positive determinant to take the log of


def _smooth_field(ndims, shape, batch=2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    x = _coords(shape, torch.float64)
    field = torch.zeros(batch, ndims, *shape, dtype=torch.float64)
    for b in range(batch):
        for k in range(ndims):
            for _ in range(3):
                freq = 0.6 * torch.rand(ndims, generator=gen, dtype=torch.float64)
                phase = 6.3 * torch.rand(1, generator=gen, dtype=torch.float64)
                amp = 3.0 * torch.rand(1, generator=gen, dtype=torch.float64)
                field[b, k] += amp * torch.sin(torch.einsum("a,a...->...", freq, x) + phase)
    return field.float()


def _numpy_jacobian_determinant(ddf):
    u = ddf.double().numpy()
    batch, ndims = u.shape[:2]
    out = np.empty((batch, *u.shape[2:]))
    for b in range(batch):
        jac = np.empty((*u.shape[2:], ndims, ndims))
        for k in range(ndims):
            for a in range(ndims):
                jac[..., k, a] = np.gradient(u[b, k], axis=a) + (1.0 if k == a else 0.0)
        out[b] = np.linalg.det(jac)
    return out


@pytest.mark.parametrize("ndims", [2, 3])
def test_matches_numpy_gradient_on_smooth_field(ndims):
    ddf = _smooth_field(ndims, SHAPES[ndims])
    det = jacobian_determinant(ddf)
    expected = _numpy_jacobian_determinant(ddf)
    assert (expected <= 0).any() and (expected > 0).any()  # a field with both regular and folding voxels
    # float32 inputs (|u| < 9): differences and the determinant carry a few 1e-7 relative error
    np.testing.assert_allclose(det.numpy(), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("ndims", [2, 3])
def test_zero_displacement_gives_ones(ndims):
    det = jacobian_determinant(torch.zeros(2, ndims, *SHAPES[ndims]))
    assert det.shape == (2, *SHAPES[ndims])
    assert torch.equal(det, torch.ones_like(det))


def test_minimal_axis_size_two_is_accepted():
    matrix = _random_near_identity(3, 4)
    det = jacobian_determinant(_affine_ddf(matrix, [0, 0, 0], (2, 2, 3)))
    # one-sided differences on 2 voxels are still exact for a linear field
    torch.testing.assert_close(det, torch.full_like(det, torch.linalg.det(matrix).item()), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "shape",
    [(1, 3, 8, 8), (1, 2, 8, 8, 8), (1, 1, 8), (1, 4, 4, 4, 4, 4), (8, 8)],
    ids=["3ch-2d", "2ch-3d", "1d", "4d", "no-batch"],
)
def test_bad_field_shape_raises(shape):
    with pytest.raises(ValueError, match=r"\(B, spatial_dims, \*S\)"):
        jacobian_determinant(torch.zeros(shape))


@pytest.mark.parametrize("shape", [(1, 2, 1, 8), (1, 3, 4, 1, 4)])
def test_axis_of_one_voxel_raises(shape):
    with pytest.raises(ValueError, match=r">= 2 voxels"):
        jacobian_determinant(torch.zeros(shape))


# ---------------------------------------------------------------------------------------------------
# jacobian_stats
# ---------------------------------------------------------------------------------------------------

DET_MAP = torch.tensor([[1.0, 2.0, -0.5, 0.0], [0.5, 3.0, 1.2, -2.0], [0.8, 1.0, 4.0, 0.25]], dtype=torch.float64)


def test_stats_on_hand_made_map():
    stats = jacobian_stats(DET_MAP)
    assert isinstance(stats, JacobianStats)
    assert stats.num_folding == 3  # -0.5, 0.0 (|J| = 0 counts), -2.0
    assert isinstance(stats.num_folding, int)
    assert stats.percent_folding == pytest.approx(100.0 * 3 / 12, rel=1e-15)
    positive = DET_MAP.numpy()[DET_MAP.numpy() > 0]
    # float64 log and std of 9 values, summation order only
    assert stats.std_log_jacobian == pytest.approx(float(np.std(np.log(positive))), rel=1e-12)


def test_stats_accept_leading_singleton_and_float32():
    a = jacobian_stats(DET_MAP.float().unsqueeze(0))
    b = jacobian_stats(DET_MAP)
    assert a.num_folding == b.num_folding and a.percent_folding == b.percent_folding
    # float32 inputs: log of values rounded at ~6e-8 relative
    assert a.std_log_jacobian == pytest.approx(b.std_log_jacobian, rel=1e-6)


def test_stats_with_mask():
    mask = torch.zeros_like(DET_MAP, dtype=torch.bool)
    mask[0] = True  # 1.0, 2.0, -0.5, 0.0
    mask[2, 3] = True  # 0.25
    stats = jacobian_stats(DET_MAP, mask)
    assert stats.num_folding == 2
    assert stats.percent_folding == pytest.approx(40.0, rel=1e-15)
    # float64: see test_stats_on_hand_made_map
    assert stats.std_log_jacobian == pytest.approx(float(np.std(np.log([1.0, 2.0, 0.25]))), rel=1e-12)
    # an integer (0/1) mask is read as boolean
    assert jacobian_stats(DET_MAP, mask.to(torch.uint8)) == stats


def test_stats_empty_mask_raises():
    with pytest.raises(ValueError, match=r"no voxel"):
        jacobian_stats(DET_MAP, torch.zeros_like(DET_MAP, dtype=torch.bool))


def test_stats_of_identity_field():
    stats = jacobian_stats(jacobian_determinant(torch.zeros(1, 3, 4, 5, 6))[0])
    assert stats == JacobianStats(0, 0.0, 0.0)


@pytest.mark.parametrize("ndims", [2, 3])
def test_determinant_gradcheck_float64(ndims):
    """The cofactor determinant is differentiable (a Jacobian penalty can be trained through it)."""
    ddf = (
        0.3 * torch.randn(1, ndims, *([4] * ndims), generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    ).requires_grad_()
    assert torch.autograd.gradcheck(jacobian_determinant, (ddf,))


@pytest.mark.parametrize("shape", [(1, 3, 13, 6, 5), (2, 3, 7, 4, 3), (1, 2, 11, 9)])
@pytest.mark.parametrize("slab_voxels", [1, 25, 10**9])
def test_determinant_in_slabs_is_the_whole_fields_to_the_bit(shape, slab_voxels):
    """Slabs with one row of neighbours each side: the same central and one-sided differences, the same bits."""
    ddf = torch.randn(shape, generator=torch.Generator().manual_seed(0)) * 2
    whole = jacobian_determinant(ddf, slab_voxels=10**9)
    assert torch.equal(jacobian_determinant(ddf, slab_voxels=slab_voxels), whole)


def test_determinant_of_a_field_that_needs_gradients_is_differentiable():
    ddf = (torch.randn(1, 3, 6, 5, 4) * 0.1).requires_grad_(True)
    jacobian_determinant(ddf, slab_voxels=1).sum().backward()  # the whole field at once: autograd sees one graph
    assert ddf.grad is not None and ddf.grad.shape == ddf.shape
