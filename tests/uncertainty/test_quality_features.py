"""monai_probreg.uncertainty.quality_features: closed-form cases of each feature, 2-d and 3-d, and bad input."""

from __future__ import annotations

import math

import pytest
import torch

from monai_probreg.uncertainty.quality_features import FOREGROUND_LEVEL, local_ncc, quality_features


def _blob(shape, centre=(0.2, -0.1, 0.05)):
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in shape], indexing="ij")
    r2 = sum((a - c) ** 2 for a, c in zip(axes, centre))
    texture = 0.2 * torch.sin(7 * axes[0]) * torch.cos(5 * axes[1])  # structure inside, for the local NCC
    return (torch.exp(-r2 / 0.3) * (0.8 + texture)).clamp(0, 1)


@pytest.mark.parametrize("shape", [(20, 24, 18), (28, 24)])
def test_a_perfect_match_and_no_deformation(shape):
    fixed = _blob(shape)
    zero = torch.zeros((len(shape), *shape))
    f = quality_features(fixed, fixed, fixed, zero, torch.full(shape, 0.7))
    assert f.ncc_before == pytest.approx(1.0, abs=1e-5) and f.ncc_after == pytest.approx(1.0, abs=1e-5)
    assert f.lncc_before == pytest.approx(1.0, abs=0.05) and f.lncc_after == pytest.approx(1.0, abs=0.05)
    assert f.entropy == pytest.approx(0.7, abs=1e-6)
    assert f.displacement_mm == 0.0 and f.folding_percent == 0.0 and f.std_log_jacobian == pytest.approx(0, abs=1e-6)


def test_inverted_contrast_correlates_negatively():
    fixed = _blob((20, 24, 18))
    inverted = torch.where(fixed > FOREGROUND_LEVEL, 1 - fixed, fixed)
    f = quality_features(inverted, fixed, fixed, torch.zeros((3, 20, 24, 18)), torch.zeros(20, 24, 18))
    assert f.ncc_before < -0.5 and f.ncc_after == pytest.approx(1.0, abs=1e-5)
    assert f.lncc_before < f.lncc_after


def test_displacement_length_is_in_mm_per_axis_spacing():
    shape = (20, 24, 18)
    fixed = _blob(shape)
    displacement = torch.zeros((3, *shape))
    displacement[0], displacement[2] = 2.0, 1.0  # voxels: a translation
    f = quality_features(fixed, fixed, fixed, displacement, torch.zeros(shape), spacing=(1.5, 1.0, 2.0))
    assert f.displacement_mm == pytest.approx(math.hypot(3.0, 2.0), rel=1e-5)
    assert f.folding_percent == 0.0 and f.std_log_jacobian == pytest.approx(0, abs=1e-6)


def test_folding_is_counted_inside_the_foreground():
    shape = (20, 24, 18)
    fixed = _blob(shape)
    displacement = torch.zeros((3, *shape))
    displacement[0] = -1.5 * torch.arange(shape[0]).view(-1, 1, 1).float()  # du/dx = -1.5: det = -0.5 everywhere
    f = quality_features(fixed, fixed, fixed, displacement, torch.zeros(shape))
    assert f.folding_percent == pytest.approx(100.0)


def test_a_given_jacobian_is_used():
    shape = (12, 14, 10)
    fixed = _blob(shape)
    jacobian = torch.ones(shape)
    jacobian[fixed > FOREGROUND_LEVEL] = -1.0
    f = quality_features(fixed, fixed, fixed, torch.zeros((3, *shape)), torch.zeros(shape), jacobian=jacobian)
    assert f.folding_percent == pytest.approx(100.0)


@pytest.mark.parametrize(
    "name, value, match",
    [
        ("moving", torch.zeros(10, 12, 8), "moving must have shape"),
        ("warped", torch.zeros(12, 14, 10, 1), "warped must have shape"),
        ("displacement", torch.zeros(2, 12, 14, 10), "displacement must have shape"),
        ("entropy", torch.zeros(12, 14), "entropy must have shape"),
        ("jacobian", torch.zeros(12, 14, 11), "jacobian must have shape"),
    ],
)
def test_shapes_that_do_not_match_are_refused(name, value, match):
    shape = (12, 14, 10)
    fixed = _blob(shape)
    args = {
        "moving": fixed,
        "fixed": fixed,
        "warped": fixed,
        "displacement": torch.zeros((3, *shape)),
        "entropy": torch.zeros(shape),
        "jacobian": None,
        name: value,
    }
    with pytest.raises(ValueError, match=match):
        quality_features(**args)


@pytest.mark.parametrize("spacing", [(1.0, 1.0), (1.0, 0.0, 1.0), (1.0, -2.0, 1.0)])
def test_bad_spacing_is_refused(spacing):
    fixed = _blob((12, 14, 10))
    with pytest.raises(ValueError, match="spacing"):
        quality_features(fixed, fixed, fixed, torch.zeros((3, 12, 14, 10)), torch.zeros(12, 14, 10), spacing)


def test_an_empty_fixed_image_is_refused():
    empty = torch.zeros(12, 14, 10)
    with pytest.raises(ValueError, match="voxels above"):
        quality_features(empty, empty, empty, torch.zeros((3, 12, 14, 10)), empty)


@pytest.mark.parametrize("shape", [(20, 24, 18), (28, 24)])
def test_the_local_ncc_of_a_batch_is_each_items_and_the_features(shape):
    """local_ncc ranks a copy above a shifted copy, item by item of a batch, and is what the features report."""
    fixed = _blob(shape)
    shifted = torch.roll(fixed, 3, dims=0)
    values = local_ncc(torch.stack([fixed, shifted])[:, None], fixed.expand(2, 1, *shape))
    assert values.shape == (2,) and values[0] > values[1]
    features = quality_features(shifted, fixed, fixed, torch.zeros((len(shape), *shape)), torch.zeros(shape))
    assert features.lncc_before == pytest.approx(float(values[1]), abs=1e-6)
    assert features.lncc_after == pytest.approx(float(values[0]), abs=1e-6)


@pytest.mark.parametrize(
    ("images", "fixed"),
    [((1, 1, 8, 8, 8), (1, 1, 8, 8, 9)), ((1, 2, 8, 8, 8), (1, 2, 8, 8, 8)), ((8, 8, 8), (8, 8, 8))],
)
def test_the_local_ncc_names_shapes_it_cannot_compare(images, fixed):
    with pytest.raises(ValueError, match="images and fixed"):
        local_ncc(torch.rand(images), torch.rand(fixed))


@pytest.mark.parametrize("shape", [(9, 8, 7), (12, 10)])
def test_the_features_are_the_whole_array_expressions_to_the_bit(shape):
    """The features computed one after the other, each one's temporaries gone before the next (a 256^3 pair's
    transient memory), are bit for bit the expressions on whole arrays: the centred copies, the summed squares."""
    g = torch.Generator().manual_seed(7)
    fixed, moving, warped, entropy = (torch.rand(shape, generator=g) for _ in range(4))
    displacement = torch.randn((len(shape), *shape), generator=g) * 2
    jacobian = torch.rand(shape, generator=g) * 2 - 0.2
    spacing = (1.1, 0.8, 1.3)[: len(shape)]
    ours = quality_features(moving, fixed, warped, displacement, entropy, spacing, jacobian=jacobian)
    mask = fixed > FOREGROUND_LEVEL

    def ncc(a: torch.Tensor, b: torch.Tensor) -> float:
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).sum()) / float((a.square().sum() * b.square().sum()).sqrt())

    s = torch.as_tensor(spacing).view(len(shape), *([1] * len(shape)))
    length = (displacement * s).square_().sum(0).sqrt_()
    det = jacobian[mask]
    assert ours.ncc_before == ncc(moving[mask], fixed[mask]) and ours.ncc_after == ncc(warped[mask], fixed[mask])
    assert ours.entropy == float(entropy[mask].mean()) and ours.displacement_mm == float(length[mask].mean())
    assert ours.std_log_jacobian == float(det[det > 0].log().std())
    assert ours.folding_percent == 100.0 * float((det <= 0).float().mean())
