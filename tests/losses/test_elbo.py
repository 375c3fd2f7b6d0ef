"""Tests of ProbRegLoss (negative ELBO + optional Dice term) on hand-made RegistrationOutput tuples."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from monai.losses import DiceLoss

from monai_probreg import LossTerms, ProbRegLoss, gaussian_image_loss, laplacian_kl
from monai_probreg.losses.likelihood import make_image_loss
from monai_probreg.networks.probreg_net import RegistrationOutput

IMAGE_SHAPES = {2: (10, 12), 3: (8, 8, 10)}
NUM_LABELS = 3  # background + 2 structures


def _output(ndims, batch=2, bidirectional=False, displacement=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    s = IMAGE_SHAPES[ndims]
    v = tuple(n // 2 for n in s)  # velocity grid at int_downsize = 2
    if displacement is None:
        displacement = torch.randn(batch, ndims, *s, generator=gen)
    return RegistrationOutput(
        warped=torch.rand(batch, 1, *s, generator=gen),
        displacement=displacement,
        velocity=torch.randn(batch, ndims, *v, generator=gen),
        velocity_mean=torch.randn(batch, ndims, *v, generator=gen),
        velocity_log_var=torch.randn(batch, ndims, *v, generator=gen) - 2.0,
        inverse_displacement=torch.randn(batch, ndims, *s, generator=gen) if bidirectional else None,
        warped_fixed=torch.rand(batch, 1, *s, generator=gen) if bidirectional else None,
    )


def _images(ndims, batch=2, seed=1):
    gen = torch.Generator().manual_seed(seed)
    s = IMAGE_SHAPES[ndims]
    return torch.rand(batch, 1, *s, generator=gen), torch.rand(batch, 1, *s, generator=gen)


def _one_hot(ndims, batch=2, seed=2):
    gen = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, NUM_LABELS, (batch, *IMAGE_SHAPES[ndims]), generator=gen)
    return F.one_hot(labels, NUM_LABELS).movedim(-1, 1).float()


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_total_is_weighted_sum_of_terms(ndims, reduction):
    out = _output(ndims)
    moving, fixed = _images(ndims)
    moving_oh, fixed_oh = _one_hot(ndims, seed=2), _one_hot(ndims, seed=3)
    loss = ProbRegLoss(
        image_loss="gaussian",
        image_sigma=0.1,
        prior_lambda=5.0,
        image_weight=2.0,
        label_weight=0.7,
        spatial_dims=ndims,
        reduction=reduction,
    )
    terms = loss(out, moving, fixed, moving_oh, fixed_oh)
    assert isinstance(terms, LossTerms)
    image = gaussian_image_loss(out.warped, fixed, 0.1, reduction)
    kl = laplacian_kl(out.velocity_mean, out.velocity_log_var, 5.0, reduction)
    # float32 throughout; same operations in the same order, so 1e-6 relative is ample
    torch.testing.assert_close(terms.image, image, rtol=1e-6, atol=0)
    torch.testing.assert_close(terms.kl, kl, rtol=1e-6, atol=0)
    assert terms.label.item() > 0  # random labels under a random displacement do not overlap perfectly
    torch.testing.assert_close(terms.total, 2.0 * image + kl + 0.7 * terms.label, rtol=1e-6, atol=0)


@pytest.mark.parametrize("image_loss", ["gaussian", "lncc"])
def test_bidirectional_image_term_is_half_forward_plus_half_backward(image_loss):
    ndims = 3
    out = _output(ndims, bidirectional=True)
    moving, fixed = _images(ndims)
    loss = ProbRegLoss(
        image_loss=image_loss,
        image_sigma=0.2,
        prior_lambda=3.0,
        image_weight=1.5,
        spatial_dims=ndims,
        lncc_kernel_size=3,
    )
    terms = loss(out, moving, fixed)
    term = make_image_loss(image_loss, ndims, 0.2, 3)
    expected = 0.5 * term(out.warped, fixed) + 0.5 * term(out.warped_fixed, moving)
    # float32, same operations: 1e-6 relative
    torch.testing.assert_close(terms.image, expected, rtol=1e-6, atol=1e-7)
    # moving != fixed here, so using the wrong target for the backward term would be caught
    wrong = 0.5 * term(out.warped, fixed) + 0.5 * term(out.warped_fixed, fixed)
    assert abs(terms.image.item() - wrong.item()) > 1e-3
    kl = laplacian_kl(out.velocity_mean, out.velocity_log_var, 3.0, "mean")
    torch.testing.assert_close(terms.total, 1.5 * expected + kl, rtol=1e-6, atol=1e-7)
    assert terms.label.item() == 0.0


def test_unidirectional_ignores_missing_warped_fixed():
    out = _output(2)
    moving, fixed = _images(2)
    terms = ProbRegLoss(image_sigma=0.3, spatial_dims=2)(out, moving, fixed)
    # float32, same single call: 1e-6 relative
    torch.testing.assert_close(terms.image, gaussian_image_loss(out.warped, fixed, 0.3), rtol=1e-6, atol=0)


def test_label_weight_zero_needs_no_labels_and_gives_zero_label_term():
    out = _output(3)
    moving, fixed = _images(3)
    terms = ProbRegLoss(label_weight=0.0)(out, moving, fixed)
    assert terms.label.item() == 0.0
    # extra labels are ignored when the weight is 0
    terms2 = ProbRegLoss(label_weight=0.0)(out, moving, fixed, _one_hot(3), _one_hot(3, seed=5))
    assert terms2.label.item() == 0.0 and terms2.total.item() == terms.total.item()


@pytest.mark.parametrize("missing", ["moving", "fixed", "both"])
def test_label_weight_positive_requires_one_hot_maps(missing):
    out = _output(3)
    moving, fixed = _images(3)
    moving_oh = None if missing in ("moving", "both") else _one_hot(3)
    fixed_oh = None if missing in ("fixed", "both") else _one_hot(3)
    with pytest.raises(ValueError, match=r"moving_one_hot and fixed_one_hot"):
        ProbRegLoss(label_weight=1.0)(out, moving, fixed, moving_oh, fixed_oh)


def test_label_one_hot_shape_mismatch_raises():
    out = _output(3)
    moving, fixed = _images(3)
    with pytest.raises(ValueError, match=r"one-hot label maps must match"):
        ProbRegLoss(label_weight=1.0)(out, moving, fixed, _one_hot(3), _one_hot(3)[:, :2])


@pytest.mark.parametrize("kwargs", [{"label_weight": -0.1}, {"image_weight": -1.0}])
def test_negative_weights_raise(kwargs):
    with pytest.raises(ValueError, match=r"weights must be >= 0"):
        ProbRegLoss(**kwargs)


def _shift_pull_back(x, axis, step):
    """warped[i] = x[i + step] along spatial ``axis`` (tensor axis 2 + axis), zero outside the grid."""
    out = torch.zeros_like(x)
    n = x.shape[2 + axis]
    src = x.narrow(2 + axis, step, n - step) if step > 0 else x.narrow(2 + axis, 0, n + step)
    if step > 0:
        out.narrow(2 + axis, 0, n - step).copy_(src)
    else:
        out.narrow(2 + axis, -step, n + step).copy_(src)
    return out


@pytest.mark.parametrize("ndims", [2, 3])
@pytest.mark.parametrize("axis,step", [(0, 1), (1, -2)])
def test_label_term_is_monai_dice_of_warped_one_hot(ndims, axis, step):
    # an integer displacement makes linear interpolation exact: the warped one-hot is a shifted copy,
    # zero where it samples outside the grid (warp_one_hot pads with zeros)
    s = IMAGE_SHAPES[ndims]
    disp = torch.zeros(2, ndims, *s)
    disp[:, axis] = float(step)
    out = _output(ndims, displacement=disp)
    moving, fixed = _images(ndims)
    moving_oh, fixed_oh = _one_hot(ndims, seed=2), _one_hot(ndims, seed=3)
    terms = ProbRegLoss(label_weight=0.5, spatial_dims=ndims)(out, moving, fixed, moving_oh, fixed_oh)
    expected = DiceLoss(include_background=False)(_shift_pull_back(moving_oh, axis, step), fixed_oh)
    # float32 grid coordinates are normalised and unnormalised inside grid_sample (~1e-6 error on weights)
    torch.testing.assert_close(terms.label, expected, rtol=1e-5, atol=1e-6)
    # the background channel is excluded: changing it leaves the term unchanged
    moving_bg = moving_oh.clone()
    moving_bg[:, 0] = 0.0
    terms_bg = ProbRegLoss(label_weight=0.5, spatial_dims=ndims)(out, moving, fixed, moving_bg, fixed_oh)
    torch.testing.assert_close(terms_bg.label, terms.label, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("ndims", [2, 3])
def test_label_term_zero_for_identical_labels_and_zero_displacement(ndims):
    s = IMAGE_SHAPES[ndims]
    out = _output(ndims, displacement=torch.zeros(2, ndims, *s))
    moving, fixed = _images(ndims)
    one_hot = _one_hot(ndims)
    terms = ProbRegLoss(label_weight=1.0, spatial_dims=ndims)(out, moving, fixed, one_hot, one_hot.clone())
    # Dice = (2I + 1e-5) / (2I + 1e-5) per label up to float32 rounding of the identity warp
    assert abs(terms.label.item()) < 1e-5


def test_label_term_is_differentiable_wrt_displacement():
    ndims = 2
    s = IMAGE_SHAPES[ndims]
    disp = (0.3 * torch.randn(1, ndims, *s, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    out = _output(ndims, batch=1, displacement=disp)
    moving, fixed = _images(ndims, batch=1)
    terms = ProbRegLoss(label_weight=1.0, spatial_dims=ndims)(
        out, moving, fixed, _one_hot(ndims, 1, 2), _one_hot(ndims, 1, 3)
    )
    (grad,) = torch.autograd.grad(terms.total, disp)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
