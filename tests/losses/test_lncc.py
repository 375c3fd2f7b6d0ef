"""monai_probreg.losses.lncc: MONAI's rectangular-window LNCC with pooled window sums (forced with
``pooled_from_voxels=0`` on these small grids), the same values and gradients; MONAI's own forward below the threshold."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from monai.losses import LocalNormalizedCrossCorrelationLoss

from monai_probreg.losses.lncc import (
    BoxLNCCLoss,
    FixedImageLNCC,
    box_mean,
    box_sum,
    padded_box_sum,
    support_box,
)

SHAPES = {1: (2, 3, 40), 2: (2, 1, 30, 41), 3: (1, 2, 11, 14, 17)}


def _pair(shape, dtype=torch.float64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    target = torch.rand(shape, generator=generator, dtype=dtype)
    # partly related to the target, so the NCC is neither ~0 nor ~1 and its gradient is not flat
    pred = 0.6 * target + 0.4 * torch.rand(shape, generator=generator, dtype=dtype)
    return pred, target


@pytest.mark.parametrize("spatial_dims", [1, 2, 3])
@pytest.mark.parametrize("reduction", ["mean", "sum", "none"])
@pytest.mark.parametrize("kernel_size", [3, 7])
def test_values_and_gradients_are_monais(spatial_dims, reduction, kernel_size):
    pred, target = _pair(SHAPES[spatial_dims])
    pred.requires_grad_(True)
    ours = BoxLNCCLoss(spatial_dims, kernel_size, reduction=reduction, pooled_from_voxels=0)(pred, target)
    monai = LocalNormalizedCrossCorrelationLoss(spatial_dims, kernel_size, reduction=reduction)(pred, target)
    assert ours.shape == monai.shape
    torch.testing.assert_close(ours, monai, rtol=1e-10, atol=1e-12)
    (g_ours,) = torch.autograd.grad(ours.sum(), pred)
    (g_monai,) = torch.autograd.grad(monai.sum(), pred)
    torch.testing.assert_close(g_ours, g_monai, rtol=1e-10, atol=1e-12)


def test_a_target_that_needs_gradients_gets_monais():
    """The fixed target is pooled outside autograd; a target that requires grad (both images learnt) is not."""
    pred, target = _pair(SHAPES[3])
    pred.requires_grad_(True)
    target.requires_grad_(True)
    ours = BoxLNCCLoss(3, 5, pooled_from_voxels=0)(pred, target)
    monai = LocalNormalizedCrossCorrelationLoss(3, 5)(pred, target)
    for g_ours, g_monai in zip(torch.autograd.grad(ours, (pred, target)), torch.autograd.grad(monai, (pred, target))):
        torch.testing.assert_close(g_ours, g_monai, rtol=1e-10, atol=1e-12)
    small = tuple(t.detach().requires_grad_(True) for t in _pair((1, 1, 5, 6, 4)))
    assert torch.autograd.gradcheck(BoxLNCCLoss(3, 3, pooled_from_voxels=0), small)


def test_smoothing_constants_are_monais():
    pred, target = _pair(SHAPES[2])
    target[..., :10, :10] = 0.5  # a flat patch: the variance floor smooth_dr decides there
    args = {"spatial_dims": 2, "kernel_size": 5, "reduction": "none", "smooth_nr": 1e-3, "smooth_dr": 1e-2}
    ours = BoxLNCCLoss(**args, pooled_from_voxels=0)(pred, target)
    monai = LocalNormalizedCrossCorrelationLoss(**args)(pred, target)
    torch.testing.assert_close(ours, monai, rtol=1e-10, atol=1e-12)


def test_float32_matches_monai_to_rounding():
    pred, target = _pair((1, 1, 24, 28, 20), dtype=torch.float32)
    ours = BoxLNCCLoss(3, 9, pooled_from_voxels=0)(pred, target)
    monai = LocalNormalizedCrossCorrelationLoss(3, 9)(pred, target)
    assert ours.item() == pytest.approx(monai.item(), rel=1e-5)


def test_box_mean_against_a_brute_force_window():
    """Every voxel's mean over its 3 x 3 window, the outside counted as zeros, on a tiny asymmetric grid."""
    x = torch.arange(20, dtype=torch.float64).reshape(1, 1, 4, 5) ** 1.5
    padded = torch.nn.functional.pad(x, (1, 1, 1, 1))
    expected = torch.empty_like(x)
    for i in range(4):
        for j in range(5):
            expected[0, 0, i, j] = padded[0, 0, i : i + 3, j : j + 3].mean()
    torch.testing.assert_close(box_mean(x, 3), expected)


def test_gradcheck_float64():
    pred, target = _pair((1, 1, 6, 7, 5))
    loss = BoxLNCCLoss(3, 3, pooled_from_voxels=0)
    assert torch.autograd.gradcheck(lambda p: loss(p, target), (pred.requires_grad_(True),))


def test_bad_shapes_are_named():
    loss = BoxLNCCLoss(3, 3)
    with pytest.raises(ValueError, match="3 spatial dimensions"):
        loss(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 8))
    with pytest.raises(ValueError, match=r"target must have pred's shape \(1, 1, 8, 8, 8\)"):
        loss(torch.rand(1, 1, 8, 8, 8), torch.rand(1, 1, 8, 8, 9))
    with pytest.raises(ValueError, match="kernel_size must be odd"):
        BoxLNCCLoss(3, 4)


def test_the_window_sums_are_pooled_from_the_threshold_on(monkeypatch):
    """Below ``pooled_from_voxels`` MONAI's forward runs (box_mean is never called), from it on the pooled one."""
    import monai_probreg.losses.lncc as lncc

    calls, grads = [], []
    monkeypatch.setattr(
        lncc, "box_mean", lambda x, k: calls.append(x.shape) or grads.append(x.requires_grad) or box_mean(x, k)
    )
    pred, target = _pair((1, 1, 6, 7, 5))  # 210 voxels
    BoxLNCCLoss(3, 3, pooled_from_voxels=211)(pred, target)
    assert calls == []
    BoxLNCCLoss(3, 3, pooled_from_voxels=210)(pred.requires_grad_(True), target)
    assert calls == [(1, 2, 6, 7, 5), (1, 3, 6, 7, 5)]  # the target's two sums, then the prediction's three
    assert grads == [False, True]  # a fixed target's sums are built outside autograd
    # experiments/lncc_speed.py's crossover: the network's grid stays MONAI's, from 96 x 112 x 96 on it is pooled
    assert 80 * 96 * 80 < lncc.POOLED_FROM_VOXELS <= 96 * 112 * 96


@pytest.mark.parametrize("value", [-1, 1.5, True, None])
def test_a_bad_threshold_is_named(value):
    with pytest.raises(ValueError, match="pooled_from_voxels"):
        BoxLNCCLoss(3, 3, pooled_from_voxels=value)


def _zero_background(shape, seed=0):
    """(pred, target) float64 with the target zero outside an off-centre box (a skull-stripped fixed image)."""
    pred, target = _pair(shape, seed=seed)
    inside = torch.zeros_like(target, dtype=torch.bool)
    inside[(slice(None), slice(None), *(slice(2, max(3, n - 5)) for n in shape[2:]))] = True
    return pred, target * inside


@pytest.mark.parametrize("spatial_dims", [1, 2, 3])
@pytest.mark.parametrize("kernel_size", [3, 5])
@pytest.mark.parametrize("cropped", [False, True])
def test_fixed_image_lncc_is_monais_values_and_gradients(spatial_dims, kernel_size, cropped):
    """The target's sums once, the gradient by hand, and (cropped) only the box around the target's nonzero voxels
    (two radii of margin): MONAI's mean LNCC and its autograd gradient, over the whole grid."""
    pred, target = _zero_background(SHAPES[spatial_dims])
    pred.requires_grad_(True)
    monai = LocalNormalizedCrossCorrelationLoss(spatial_dims, kernel_size)(pred, target)
    region = support_box(target, margin=2 * (kernel_size // 2)) if cropped else None
    if cropped:
        assert region is not None
    loss = FixedImageLNCC(target, kernel_size, region=region)
    ours = loss(loss.crop(pred))
    torch.testing.assert_close(ours, monai, rtol=1e-10, atol=1e-12)
    (g_ours,) = torch.autograd.grad(ours, pred)
    (g_monai,) = torch.autograd.grad(monai, pred)
    torch.testing.assert_close(g_ours, g_monai, rtol=1e-9, atol=1e-12)


def test_fixed_image_lncc_passes_gradcheck_with_a_flat_patch():
    """float64 gradcheck, a flat patch of the target included (the variance floor decides there)."""
    pred, target = _pair((1, 1, 7, 6, 5))
    target[..., :3, :3, :] = 0.5
    loss = FixedImageLNCC(target, 3)
    assert torch.autograd.gradcheck(loss, (pred.requires_grad_(True),))


@pytest.mark.parametrize("spatial_dims", [1, 2, 3])
@pytest.mark.parametrize("kernel_size", [1, 3, 9, 15])
def test_box_sum_is_a_convolution_with_ones(spatial_dims, kernel_size):
    """Doubling sums against a convolution with a box of ones (zeros outside), a window wider than some axes
    included; and the pooled box mean times the window where pooling takes the size."""
    x, _ = _pair(SHAPES[spatial_dims])
    conv = {1: F.conv1d, 2: F.conv2d, 3: F.conv3d}[spatial_dims]
    ones = torch.ones((1, 1) + (kernel_size,) * spatial_dims, dtype=x.dtype)
    flat = x.reshape(-1, 1, *x.shape[2:])
    expected = conv(flat, ones, padding=kernel_size // 2).reshape(x.shape)
    torch.testing.assert_close(box_sum(x, kernel_size), expected, rtol=1e-12, atol=1e-12)
    if kernel_size <= min(x.shape[2:]):
        torch.testing.assert_close(box_sum(x, kernel_size), box_mean(x, kernel_size) * kernel_size**spatial_dims)


@pytest.mark.parametrize("spatial_dims", [2, 3])
@pytest.mark.parametrize("planes", [1, 3, 8, 100])
@pytest.mark.parametrize("kernel_size", [3, 9])
def test_box_sums_by_blocks_of_planes_are_the_same_bits(spatial_dims, planes, kernel_size):
    """Blocks of the first axis (sizes that do not divide it, and one larger than it) add the same numbers in the same
    order as the whole tensor at once: equal to the last bit, in float32."""
    g = torch.Generator().manual_seed(planes)
    shape = (2, 3, 13, 11, 7)[: 2 + spatial_dims]
    radius = kernel_size // 2
    padded = F.pad(torch.rand(shape, generator=g), [radius, radius] * spatial_dims)
    whole = padded_box_sum(padded, kernel_size, planes=None)
    assert whole.shape == shape
    assert torch.equal(padded_box_sum(padded, kernel_size, planes=planes), whole)


@pytest.mark.parametrize("planes", [0, -1, 2.0, True])
def test_box_sum_names_a_bad_block_size(planes):
    with pytest.raises(ValueError, match="planes must be a positive integer or None"):
        padded_box_sum(torch.zeros(1, 1, 12, 12), 3, planes=planes)


def test_support_box_is_the_nonzero_box_grown_and_clipped():
    target = torch.zeros(2, 1, 20, 30, 12)
    target[1, 0, 5, 7, 3] = 1.0
    target[0, 0, 9, 20, 4] = -2.0  # any item, any sign
    assert support_box(target, margin=0) == ((5, 7, 3), (10, 21, 5))
    assert support_box(target, margin=4) == ((1, 3, 0), (14, 25, 9))
    assert support_box(torch.zeros(1, 1, 4, 4), margin=1) is None  # all zero: nothing to compare
    assert support_box(torch.ones(1, 1, 4, 4), margin=0) is None  # the whole grid: no gain


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"target": torch.zeros(4, 4)}, "expected a target"),
        ({"target": torch.zeros(1, 1, 4, 4), "kernel_size": 4}, "kernel_size"),
        ({"target": torch.zeros(1, 1, 4, 4), "kernel_size": 3.0}, "kernel_size"),
    ],
)
def test_fixed_image_lncc_names_a_bad_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FixedImageLNCC(**kwargs)


def test_fixed_image_lncc_names_the_expected_shape():
    loss = FixedImageLNCC(torch.rand(1, 1, 8, 9), 3, region=((1, 2), (7, 9)))
    with pytest.raises(ValueError, match=r"expected pred of shape \(1, 1, 6, 7\)"):
        loss(torch.rand(1, 1, 8, 9))


def test_fixed_image_lncc_keeps_its_answers_when_called_again():
    """The window sums' buffer is kept between calls: a second call (another pred, then the first again) gives the
    first call's value and gradient; a double backward is refused (the gradient is written by hand)."""
    pred, target = _pair(SHAPES[3])
    other, _ = _pair(SHAPES[3], seed=1)
    loss = FixedImageLNCC(target, 3)
    first = pred.clone().requires_grad_(True)
    value = loss(first)
    (gradient,) = torch.autograd.grad(value, first)
    loss(other.clone().requires_grad_(True))
    again = pred.clone().requires_grad_(True)
    torch.testing.assert_close(loss(again), value, rtol=0, atol=0)
    (twice,) = torch.autograd.grad(loss(again), again, create_graph=True)
    torch.testing.assert_close(twice, gradient, rtol=0, atol=0)
    with pytest.raises(RuntimeError):
        torch.autograd.grad(twice.sum(), again)


# ------------------------------------------------------------------------ per-voxel weights (cost-function masks)
WEIGHTED_SHAPES = {2: (1, 1, 13, 17), 3: (1, 1, 9, 11, 8)}  # small and asymmetric: a transposed axis would show


def _weights(shape, seed=2):
    """Weights (B, 1, *S) in [0, 1]: a hard 0/1 mask (an off-centre hole) times a soft ramp, so both a mask's edge
    and fractional weights (a warped moving mask) are tested."""
    generator = torch.Generator().manual_seed(seed)
    weight = torch.rand((shape[0], 1, *shape[2:]), generator=generator, dtype=torch.float64)
    weight[(slice(None), slice(None), *(slice(1, max(2, n // 2)) for n in shape[2:]))] = 0.0
    return weight


@pytest.mark.parametrize("spatial_dims", [2, 3])
@pytest.mark.parametrize("cropped", [False, True])
def test_weighted_fixed_image_lncc_is_monais_per_voxel_ncc_times_the_weights(spatial_dims, cropped):
    """-sum(w * ncc) / N, N the whole grid: MONAI's reduction='none' map times the weights, values and autograd
    gradients (cropped: the weights of the box, the box holding every window that reaches a nonzero target voxel)."""
    kernel_size = 3
    pred, target = _zero_background(WEIGHTED_SHAPES[spatial_dims])
    weight = _weights(pred.shape)
    pred.requires_grad_(True)
    per_voxel = LocalNormalizedCrossCorrelationLoss(spatial_dims, kernel_size, reduction="none")(pred, target)
    monai = (per_voxel * weight).sum() / pred.numel()
    region = support_box(target, margin=2 * (kernel_size // 2)) if cropped else None
    loss = FixedImageLNCC(target, kernel_size, region=region)
    ours = loss(loss.crop(pred), loss.crop(weight))
    torch.testing.assert_close(ours, monai, rtol=1e-10, atol=1e-12)
    (g_ours,) = torch.autograd.grad(ours, pred)
    (g_monai,) = torch.autograd.grad(monai, pred)
    torch.testing.assert_close(g_ours, g_monai, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_weighted_fixed_image_lncc_passes_gradcheck(spatial_dims):
    pred, target = _pair(WEIGHTED_SHAPES[spatial_dims])
    weight = _weights(pred.shape)
    loss = FixedImageLNCC(target, 3)
    assert torch.autograd.gradcheck(lambda p: loss(p, weight), (pred.requires_grad_(True),))


def test_unit_weights_give_the_unweighted_loss_exactly():
    """Weights of 1 everywhere: bit for bit the unweighted value and gradient (x * 1 is exact); the unweighted call
    itself takes the path it took before weights existed."""
    pred, target = _pair(SHAPES[3])
    loss = FixedImageLNCC(target, 3)
    plain = pred.clone().requires_grad_(True)
    ones = pred.clone().requires_grad_(True)
    value, weighted = loss(plain), loss(ones, torch.ones(1, 1, *pred.shape[2:], dtype=pred.dtype))
    torch.testing.assert_close(weighted, value, rtol=0, atol=0)
    (g_plain,) = torch.autograd.grad(value, plain)
    (g_ones,) = torch.autograd.grad(weighted, ones)
    torch.testing.assert_close(g_ones, g_plain, rtol=0, atol=0)


def test_fixed_image_lncc_names_a_bad_weight_shape():
    loss = FixedImageLNCC(torch.rand(1, 1, 8, 9), 3)
    with pytest.raises(ValueError, match=r"expected a weight broadcastable to pred's shape \(1, 1, 8, 9\), got"):
        loss(torch.rand(1, 1, 8, 9), torch.rand(1, 1, 9, 8))


def test_box_sums_by_blocks_take_a_monai_metatensor():
    """The bundle's path hands MONAI MetaTensors around: blocks of a MetaTensor give the plain tensor's sums."""
    from monai.data import MetaTensor

    padded = F.pad(torch.rand(1, 2, 12, 9, 8), [1, 1] * 3)
    expected = padded_box_sum(padded, 3, planes=None)
    torch.testing.assert_close(padded_box_sum(MetaTensor(padded), 3, planes=4).as_tensor(), expected)
