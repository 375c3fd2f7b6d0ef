"""Tests of the KL to the Laplacian prior (paper Eq. 5) against brute-force dense-matrix computations.

Everything numerical runs in float64 so that the comparisons can be tight: the only error left is the
summation order (a few ulps on sums of ~100 terms), hence relative tolerances of 1e-10 or better.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from monai_probreg import LaplacianKLLoss, laplacian_kl, neighbour_degree

SHAPES = {2: (4, 5), 3: (3, 4, 5)}


def brute_force_laplacian(spatial_shape):
    """Dense graph Laplacian L = D - A of the 2*ndims-neighbour grid, voxels in C (row-major) order."""
    coords = list(np.ndindex(*spatial_shape))
    n = len(coords)
    adjacency = np.zeros((n, n))
    for i, j in itertools.product(range(n), repeat=2):
        # neighbours: differ by exactly 1 along exactly one axis
        if sum(abs(a - b) for a, b in zip(coords[i], coords[j])) == 1:
            adjacency[i, j] = 1.0
    degree = np.diag(adjacency.sum(axis=1))
    return degree - adjacency, degree


def brute_force_kl(mean, log_var, prior_lambda, reduction):
    """0.5 * sum_{b,c} [ sum_j (lambda D_jj exp(s_cj) - s_cj) + lambda mu_c^T L mu_c ] (/ B*N for "mean")."""
    mean = mean.numpy()
    log_var = log_var.numpy()
    batch, channels = mean.shape[:2]
    spatial = mean.shape[2:]
    lap, degree = brute_force_laplacian(spatial)
    d = np.diag(degree)
    total = 0.0
    for b in range(batch):
        for c in range(channels):
            mu = mean[b, c].reshape(-1)
            s = log_var[b, c].reshape(-1)
            total += 0.5 * (np.sum(prior_lambda * d * np.exp(s) - s) + prior_lambda * mu @ lap @ mu)
    if reduction == "mean":
        total /= batch * int(np.prod(spatial))
    return total


def random_fields(ndims, batch=2, shape=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = SHAPES[ndims] if shape is None else shape
    mean = torch.randn(batch, ndims, *shape, generator=gen, dtype=torch.float64)
    log_var = torch.randn(batch, ndims, *shape, generator=gen, dtype=torch.float64) - 1.0
    return mean, log_var


# ---------------------------------------------------------------------------------------------------
# (1) against the explicit Laplacian
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
@pytest.mark.parametrize("prior_lambda", [0.3, 20.0])
def test_kl_matches_explicit_laplacian_on_tiny_grid(ndims, reduction, prior_lambda):
    mean, log_var = random_fields(ndims)
    got = laplacian_kl(mean, log_var, prior_lambda, reduction=reduction)
    expected = brute_force_kl(mean, log_var, prior_lambda, reduction)
    assert got.dtype == torch.float64 and got.ndim == 0
    # float64, same terms summed in a different order: 1e-10 relative is ~1e5 ulps of headroom
    assert got.item() == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("ndims", [2, 3])
def test_mean_reduction_is_sum_over_batch_times_voxels(ndims):
    mean, log_var = random_fields(ndims, batch=3)
    n_voxels = math.prod(SHAPES[ndims])
    total = laplacian_kl(mean, log_var, 2.0, reduction="sum")
    per_voxel = laplacian_kl(mean, log_var, 2.0, reduction="mean")
    # float64, one division apart
    assert per_voxel.item() == pytest.approx(total.item() / (3 * n_voxels), rel=1e-12)


def test_kl_with_size_one_axis_matches_explicit_laplacian():
    # a flat 3D grid (1, 4, 5): the size-1 axis adds no edge and no degree
    mean, log_var = random_fields(3, shape=(1, 4, 5))
    got = laplacian_kl(mean, log_var, 1.5, reduction="sum")
    # float64 summation-order differences only
    assert got.item() == pytest.approx(brute_force_kl(mean, log_var, 1.5, "sum"), rel=1e-10)


# ---------------------------------------------------------------------------------------------------
# (2) degree
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(3, 4, 5), (4, 5), (2, 2, 2), (1, 4, 5), (1, 1, 3), (6,), (1, 6)])
def test_neighbour_degree_is_diagonal_of_explicit_degree(shape):
    _, degree = brute_force_laplacian(shape)
    got = neighbour_degree(shape, dtype=torch.float64)
    assert tuple(got.shape) == shape
    # small integers, exact in floating point
    np.testing.assert_array_equal(got.numpy().reshape(-1), np.diag(degree))


def test_neighbour_degree_counts_in_3d():
    deg = neighbour_degree((3, 4, 5))
    assert deg.dtype == torch.float32
    assert deg[1, 1, 1] == 6 and deg[1, 2, 3] == 6  # interior
    assert deg[0, 1, 1] == 5 and deg[1, 0, 2] == 5 and deg[1, 2, 4] == 5  # faces
    assert deg[0, 0, 1] == 4 and deg[2, 1, 4] == 4  # edges
    assert deg[0, 0, 0] == 3 and deg[2, 3, 4] == 3  # corners
    values, counts = torch.unique(deg, return_counts=True)
    # 3x4x5: interior 1*2*3, faces 2*(2*3 + 1*3 + 1*2), edges 4*(1 + 2 + 3), corners 8
    assert dict(zip(values.tolist(), counts.tolist())) == {3.0: 8, 4.0: 24, 5.0: 22, 6.0: 6}


def test_neighbour_degree_size_one_axis_contributes_zero():
    # along a size-1 axis a voxel has no neighbour: (1, 4, 5) has the degrees of the 2D 4x5 grid
    np.testing.assert_array_equal(neighbour_degree((1, 4, 5))[0].numpy(), neighbour_degree((4, 5)).numpy())
    assert torch.all(neighbour_degree((1, 1, 1)) == 0)


def test_neighbour_degree_dtype():
    assert neighbour_degree((3, 3), dtype=torch.float64).dtype == torch.float64


# ---------------------------------------------------------------------------------------------------
# (3) optimum over the variance: sigma^2 = 1 / (lambda D)
# ---------------------------------------------------------------------------------------------------


def _optimal_log_var(ndims, prior_lambda, batch=2):
    degree = neighbour_degree(SHAPES[ndims], dtype=torch.float64)
    return (-torch.log(prior_lambda * degree)).expand(batch, ndims, *SHAPES[ndims]).clone()


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("prior_lambda", [0.5, 20.0])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_gradient_wrt_log_var_vanishes_at_optimum(ndims, prior_lambda, reduction):
    mean, _ = random_fields(ndims)
    log_var = _optimal_log_var(ndims, prior_lambda).requires_grad_(True)
    (grad,) = torch.autograd.grad(laplacian_kl(mean, log_var, prior_lambda, reduction), log_var)
    # d/ds = 0.5 (lambda D e^s - 1) = 0.5 (1 - 1) up to the rounding of exp(-log(lambda D)): a few 1e-16
    assert grad.abs().max().item() < 1e-12


@pytest.mark.parametrize("ndims", [2, 3])
def test_gradient_wrt_log_var_is_nonzero_away_from_optimum(ndims):
    prior_lambda, shift = 3.0, 0.3
    mean, _ = random_fields(ndims)
    log_var = (_optimal_log_var(ndims, prior_lambda) + shift).requires_grad_(True)
    (grad,) = torch.autograd.grad(laplacian_kl(mean, log_var, prior_lambda, "sum"), log_var)
    # exactly 0.5 (e^shift - 1) at every voxel (lambda D e^{s*} = 1); float64 rounding only
    torch.testing.assert_close(grad, torch.full_like(grad, 0.5 * math.expm1(shift)), rtol=1e-12, atol=1e-14)
    assert grad.abs().min().item() > 0.1


@pytest.mark.parametrize("ndims", [2, 3])
def test_optimum_is_a_minimum_in_log_var(ndims):
    prior_lambda = 4.0
    mean, _ = random_fields(ndims)
    s_opt = _optimal_log_var(ndims, prior_lambda)
    base = laplacian_kl(mean, s_opt, prior_lambda, "sum")
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        delta = 0.1 * torch.randn(s_opt.shape, generator=gen, dtype=torch.float64)
        for sign in (1.0, -1.0):
            increase = (laplacian_kl(mean, s_opt + sign * delta, prior_lambda, "sum") - base).item()
            # separable: 0.5 * sum(e^d - 1 - d) > 0; the loss is O(100) so the difference carries ~1e-14
            # absolute rounding error, far below the O(1e-2) increase
            expected = 0.5 * torch.sum(torch.expm1(sign * delta) - sign * delta).item()
            assert increase > 0
            assert increase == pytest.approx(expected, rel=1e-9, abs=1e-12)
    # second order: the Hessian in log_var is diagonal, 0.5 * lambda D e^s = 0.5 at the optimum
    s = s_opt.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(laplacian_kl(mean, s, prior_lambda, "sum"), s, create_graph=True)
    (hess_diag,) = torch.autograd.grad(grad.sum(), s)
    torch.testing.assert_close(hess_diag, torch.full_like(hess_diag, 0.5), rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------------------------------------
# (4) smoothness term
# ---------------------------------------------------------------------------------------------------


def _smoothness(mean, log_var, prior_lambda=2.0, reduction="sum"):
    return laplacian_kl(mean, log_var, prior_lambda, reduction) - laplacian_kl(
        torch.zeros_like(mean), log_var, prior_lambda, reduction
    )


@pytest.mark.parametrize("ndims", [2, 3])
def test_smoothness_zero_for_constant_mean(ndims):
    _, log_var = random_fields(ndims)
    const = torch.tensor([1.7, -0.4, 3.0][:ndims], dtype=torch.float64).view(1, ndims, *([1] * ndims))
    mean = const.expand_as(log_var).clone()
    # differences of a constant are exactly 0, so both KLs are bitwise equal
    assert _smoothness(mean, log_var).item() == 0.0


@pytest.mark.parametrize("ndims", [2, 3])
def test_smoothness_positive_for_nonconstant_mean(ndims):
    mean, log_var = random_fields(ndims)
    assert _smoothness(mean, log_var).item() > 0
    # a single bump: its 2*ndims (interior) edges each contribute 1, halved by the 1/2, times lambda
    bump = torch.zeros_like(mean)
    bump[(0, 0) + (1,) * ndims] = 1.0
    # float64, exact small integers up to rounding of the exp/log terms cancelling: 1e-12 relative
    assert _smoothness(bump, log_var, prior_lambda=2.0).item() == pytest.approx(2.0 * ndims, rel=1e-12)


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_kl_invariant_to_constant_offset_of_mean(ndims, reduction):
    mean, log_var = random_fields(ndims)
    offset = torch.randn(2, ndims, *([1] * ndims), dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    a = laplacian_kl(mean, log_var, 5.0, reduction)
    b = laplacian_kl(mean + 5.0 * offset, log_var, 5.0, reduction)
    # float64; the offset changes the rounding of each difference by ~1e-15 relative
    assert b.item() == pytest.approx(a.item(), rel=1e-10)


# ---------------------------------------------------------------------------------------------------
# (5) bad inputs
# ---------------------------------------------------------------------------------------------------


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match=r"same shape.*\(2, 3, 3, 4, 5\).*\(2, 3, 3, 4, 4\)"):
        laplacian_kl(torch.zeros(2, 3, 3, 4, 5), torch.zeros(2, 3, 3, 4, 4), 1.0)


@pytest.mark.parametrize("prior_lambda", [0.0, -1.0])
def test_nonpositive_lambda_raises(prior_lambda):
    with pytest.raises(ValueError, match=r"prior_lambda must be > 0"):
        laplacian_kl(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 4), prior_lambda)
    with pytest.raises(ValueError, match=r"prior_lambda must be > 0"):
        LaplacianKLLoss(prior_lambda)


def test_unknown_reduction_raises():
    with pytest.raises(ValueError, match=r"reduction must be one of.*'mean'.*'sum'.*got 'none'"):
        laplacian_kl(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 4), 1.0, reduction="none")
    with pytest.raises(ValueError, match=r"reduction must be one of"):
        LaplacianKLLoss(1.0, reduction="batchmean")


def test_too_few_dims_raises():
    with pytest.raises(ValueError, match=r"\(B, D, \*V\).*got shape \(2, 3\)"):
        laplacian_kl(torch.zeros(2, 3), torch.zeros(2, 3), 1.0)


# ---------------------------------------------------------------------------------------------------
# (6) module
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_module_equals_function(ndims, reduction):
    mean, log_var = random_fields(ndims)
    module = LaplacianKLLoss(prior_lambda=7.0, reduction=reduction)
    assert module.prior_lambda == 7.0 and module.reduction == reduction
    # same code path: bitwise equal
    assert module(mean, log_var).item() == laplacian_kl(mean, log_var, 7.0, reduction).item()


def test_module_default_reduction_is_mean():
    mean, log_var = random_fields(3)
    assert LaplacianKLLoss(3.0)(mean, log_var).item() == laplacian_kl(mean, log_var, 3.0, "mean").item()


# ---------------------------------------------------------------------------------------------------
# (7) the docstring's conversion from the VoxelMorph (MICCAI 2018) loss
# ---------------------------------------------------------------------------------------------------


def voxelmorph_kl(mean, log_var, lambda_v):
    """The VoxelMorph KL as described in kl.py's docstring (written from that description):

    ``1/2 * ndims * (mean(lambda_v D e^s - s) + lambda_v * prec)``, ``prec = 1/(2 ndims) sum_axes mean(diff^2)``,
    every mean over batch, voxels (or difference positions) *and* components.
    """
    ndims = mean.ndim - 2
    degree = neighbour_degree(mean.shape[2:], dtype=mean.dtype)
    sigma_part = torch.mean(lambda_v * degree * torch.exp(log_var) - log_var)
    prec = sum(torch.mean(torch.diff(mean, dim=axis) ** 2) for axis in range(2, mean.ndim)) / (2 * ndims)
    return 0.5 * ndims * (sigma_part + lambda_v * prec)


@pytest.mark.parametrize("ndims", [2, 3])
def test_voxelmorph_log_variance_part_equals_ours_with_same_lambda(ndims):
    # zero mean: both smoothness parts vanish and only the log-variance parts remain
    _, log_var = random_fields(ndims, shape=(5, 6, 7)[:ndims])
    zero = torch.zeros_like(log_var)
    lambda_v = 13.0
    # float64, same terms with a different normalisation order
    assert laplacian_kl(zero, log_var, lambda_v, "mean").item() == pytest.approx(
        voxelmorph_kl(zero, log_var, lambda_v).item(), rel=1e-12
    )


def _vm_smoothness(mean, log_var, lambda_v):
    return voxelmorph_kl(mean, log_var, lambda_v) - voxelmorph_kl(torch.zeros_like(mean), log_var, lambda_v)


@pytest.mark.parametrize("ndims", [2, 3])
def test_voxelmorph_smoothness_equals_ours_with_lambda_over_2ndims_on_cubic_grid(ndims):
    # On an n^ndims grid every axis has n-1 difference positions per line, so VoxelMorph's per-axis means
    # divide by B*ndims*N*(n-1)/n where ours divides by B*N: the ratio is exactly n/(n-1) for any field.
    n, lambda_v = 40, 20.0
    mean, log_var = random_fields(ndims, batch=1, shape=(n,) * ndims)
    ours = _smoothness(mean, log_var, prior_lambda=lambda_v / (2 * ndims), reduction="mean")
    vm = _vm_smoothness(mean, log_var, lambda_v)
    # float64; differences of O(1) KLs each carrying ~1e-15 relative rounding
    assert (vm / ours).item() == pytest.approx(n / (n - 1), rel=1e-10)
    # and with lambda = lambda_v the smoothness parts do not match (off by 2*ndims): no single lambda
    ours_same_lambda = _smoothness(mean, log_var, prior_lambda=lambda_v, reduction="mean")
    assert (vm / ours_same_lambda).item() == pytest.approx(n / (n - 1) / (2 * ndims), rel=1e-10)


@pytest.mark.parametrize("shape", [(40, 40, 40), (40, 30, 20), (40, 25)])
def test_voxelmorph_smoothness_ratio_on_constant_gradient_field(shape):
    # mu_c(x) = sum_a G[c, a] x_a: the difference along axis a is G[c, a] everywhere, so with
    # g_a = sum_c G[c, a]^2 and N voxels:
    #   ours (lambda) = lambda/2 * sum_a g_a * N (n_a - 1)/n_a / N            ("mean", B = 1)
    #   VoxelMorph    = lambda_v/4 * sum_a g_a / ndims                         (means over components too)
    # so with lambda = lambda_v/(2 ndims): ratio VM/ours = sum_a g_a / sum_a g_a (n_a - 1)/n_a exactly.
    ndims = len(shape)
    lambda_v = 20.0
    gen = torch.Generator().manual_seed(5)
    grad = torch.randn(ndims, ndims, generator=gen, dtype=torch.float64)
    coords = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float64) for n in shape], indexing="ij"))
    mean = torch.einsum("ca,a...->c...", grad, coords).unsqueeze(0)
    log_var = torch.randn(mean.shape, generator=gen, dtype=torch.float64)
    g = (grad**2).sum(dim=0)
    expected_ratio = (g.sum() / sum(g[a] * (n - 1) / n for a, n in enumerate(shape))).item()
    ours = _smoothness(mean, log_var, prior_lambda=lambda_v / (2 * ndims), reduction="mean")
    vm = _vm_smoothness(mean, log_var, lambda_v)
    # float64 sums over <= 2e5 terms: 1e-9 relative
    assert (vm / ours).item() == pytest.approx(expected_ratio, rel=1e-9)
    # the edge-count factor is bounded by max n/(n-1) and is small on a 40-voxel grid
    assert 1.0 < expected_ratio <= max(n / (n - 1) for n in shape)
    # absolute check of ours: 0.5 * lambda * sum_a g_a (n_a - 1)/n_a
    lam = lambda_v / (2 * ndims)
    ours_closed = 0.5 * lam * sum(g[a].item() * (n - 1) / n for a, n in enumerate(shape))
    assert ours.item() == pytest.approx(ours_closed, rel=1e-9)
