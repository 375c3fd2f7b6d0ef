"""monai_probreg.losses.mind: the MIND-SSC descriptor against a brute-force reference, its contrast invariance, its
gradients, the losses built on it and their bad arguments."""

from __future__ import annotations

import itertools

import pytest
import torch

from monai_probreg.losses.likelihood import make_image_loss
from monai_probreg.losses.mind import VARIANCE_CLAMP, FixedImageMIND, MINDLoss, mind_descriptor, mind_pairs


def _brute_force(image: torch.Tensor, radius: int, dilation: int) -> torch.Tensor:
    """The module docstring's formula voxel by voxel with Python loops (one channel, float64): (P, *S)."""
    spatial = image.shape[2:]
    pairs = mind_pairs(len(spatial), dilation)
    array = image[0, 0].numpy()

    def value(index):  # the image repeated beyond its border
        return float(array[tuple(min(max(i, 0), n - 1) for i, n in zip(index, spatial))])

    def distance(x, p, q):  # the mean over the window (its centres repeated beyond the border) of (I(.+p) - I(.+q))^2
        total, count = 0.0, 0
        for step in itertools.product(range(-radius, radius + 1), repeat=len(spatial)):
            c = [min(max(a + s, 0), n - 1) for a, s, n in zip(x, step, spatial)]
            total += (value([a + b for a, b in zip(c, p)]) - value([a + b for a, b in zip(c, q)])) ** 2
            count += 1
        return total / count

    d = torch.zeros(len(pairs), *spatial, dtype=torch.float64)
    for x in itertools.product(*[range(n) for n in spatial]):
        for j, (p, q) in enumerate(pairs):
            d[(j, *x)] = distance(x, p, q)
    d = d - d.amin(0, keepdim=True)
    v = d.mean(0, keepdim=True)
    level = v.mean()
    v = v.clamp(level / VARIANCE_CLAMP, level * VARIANCE_CLAMP)
    return torch.exp(-d / v)


@pytest.mark.parametrize(("spatial_dims", "count"), [(2, 4), (3, 12)])
def test_the_pairs_are_neighbours_on_different_axes(spatial_dims, count):
    pairs = mind_pairs(spatial_dims, dilation=2)
    assert len(pairs) == count == len(set(pairs))
    for p, q in pairs:
        assert sum(map(abs, p)) == sum(map(abs, q)) == 2  # one axis each, 2 voxels away
        assert sum((a - b) ** 2 for a, b in zip(p, q)) == 8  # sqrt(2) * dilation apart: never the same axis


@pytest.mark.parametrize(("shape", "radius", "dilation"), [((5, 6, 7), 1, 1), ((6, 5, 4), 0, 2), ((8, 9), 2, 2)])
def test_the_descriptor_is_the_brute_force_formula(shape, radius, dilation):
    """float64 on a random tiny image, borders included: the same values to float64 rounding (1e-12)."""
    image = torch.rand(1, 1, *shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = _brute_force(image, radius, dilation)
    torch.testing.assert_close(mind_descriptor(image, radius, dilation)[0], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", [(9, 10, 11), (12, 14)])
def test_two_images_of_one_anatomy_in_any_two_contrasts_have_the_same_descriptor(shape):
    """A two-class image at intensities (0.1, 0.4) and at (5, 3) (brightness order inverted, as white matter and CSF
    between T1 and T2): the same descriptor to float rounding; their MIND loss is 0 where a local NCC would be -1."""
    labels = (torch.rand(1, 1, *shape, generator=torch.Generator().manual_seed(2)) > 0.5).double()
    t1_like, t2_like = 0.1 + 0.3 * labels, 5.0 - 2.0 * labels
    torch.testing.assert_close(mind_descriptor(t1_like), mind_descriptor(t2_like), rtol=0, atol=1e-12)
    assert MINDLoss()(t1_like, t2_like).item() == pytest.approx(0.0, abs=1e-12)


def test_the_descriptor_of_a_flat_image_is_all_ones():
    """No contrast anywhere: every distance and the variance are 0; 0 / tiny gives exp(0) = 1, never NaN."""
    out = mind_descriptor(torch.full((1, 2, 6, 7, 8), 0.3))
    assert out.shape == (1, 24, 6, 7, 8)
    assert torch.equal(out, torch.ones_like(out))


def test_each_channel_has_its_own_descriptor_block():
    """Channel c of the image gives channels c * P ... c * P + P - 1 of the descriptor."""
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(1, 1, 6, 7, 8, generator=g), torch.rand(1, 1, 6, 7, 8, generator=g)
    both = mind_descriptor(torch.cat([a, b], dim=1))
    torch.testing.assert_close(both, torch.cat([mind_descriptor(a), mind_descriptor(b)], dim=1), rtol=0, atol=0)


@pytest.mark.parametrize("shape", [(4, 5, 6), (5, 7)])
def test_gradcheck(shape):
    image = torch.rand(1, 1, *shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    fixed = torch.rand(1, 1, *shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    # fast mode (random projections of the Jacobian): the full one takes a backward pass per descriptor entry
    assert torch.autograd.gradcheck(lambda x: mind_descriptor(x, 1, 1), (image.requires_grad_(),), fast_mode=True)
    assert torch.autograd.gradcheck(lambda x: MINDLoss(1, 1)(x, fixed), (image,))


def test_the_loss_is_zero_for_one_image_and_grows_with_a_shift():
    image = torch.rand(1, 1, 12, 12, 12, generator=torch.Generator().manual_seed(6))
    image = torch.nn.functional.avg_pool3d(image, 3, 1, 1)
    loss = MINDLoss()
    assert loss(image, image).item() == 0.0
    one, two = (loss(torch.roll(image, s, dims=2), image).item() for s in (1, 2))
    assert 0.0 < one < two <= 1.0


def test_the_fixed_image_form_is_the_loss_and_weights_count_voxels():
    g = torch.Generator().manual_seed(7)
    fixed, warped = torch.rand(1, 1, 8, 9, 10, generator=g), torch.rand(1, 1, 8, 9, 10, generator=g)
    term = FixedImageMIND(fixed, radius=1, dilation=2)
    torch.testing.assert_close(term(warped), MINDLoss(1, 2)(warped, fixed), rtol=1e-6, atol=0)
    torch.testing.assert_close(term(warped, torch.ones(1, 1, 8, 9, 10)), term(warped), rtol=1e-6, atol=0)
    half = torch.zeros(1, 1, 8, 9, 10)
    half[..., :5] = 1.0
    expected = MINDLoss(1, 2, reduction="none")(warped, fixed)[..., :5].sum() / (8 * 9 * 10)
    torch.testing.assert_close(term(warped, half), expected, rtol=1e-6, atol=0)


def test_make_image_loss_builds_mind_with_its_settings():
    loss = make_image_loss("mind", mind_radius=2, mind_dilation=3, reduction="none")
    assert isinstance(loss, MINDLoss) and (loss.radius, loss.dilation, loss.reduction) == (2, 3, "none")


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: mind_descriptor(torch.rand(1, 8, 8)), "2 or 3 spatial dims"),
        (lambda: mind_descriptor(torch.rand(1, 1, 8, 8), radius=-1), "radius"),
        (lambda: mind_descriptor(torch.rand(1, 1, 8, 8), dilation=0), "dilation"),
        (lambda: mind_descriptor(torch.rand(1, 1, 8, 8), dilation=1.0), "dilation"),
        (lambda: MINDLoss(radius=True), "radius"),
        (lambda: MINDLoss(reduction="sum"), "reduction"),
        (lambda: MINDLoss()(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 9)), "same shape"),
        (lambda: FixedImageMIND(torch.rand(1, 1, 8, 8))(torch.rand(1, 1, 8, 9)), r"expected warped of shape"),
        (lambda: mind_pairs(4), "spatial_dims"),
    ],
)
def test_bad_arguments_name_themselves(call, match):
    with pytest.raises(ValueError, match=match):
        call()
