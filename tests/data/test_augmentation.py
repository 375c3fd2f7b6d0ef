"""monai_probreg.data.augmentation: the moving scan and its labels get one random affine; the fixed side never moves."""

from __future__ import annotations

import pytest
import torch
from monai.data import MetaTensor
from monai.transforms import Randomizable

from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.data.augmentation import (
    INPUT_SUFFIX,
    RandDiffeomorphicd,
    intensity_augmentation,
    moving_augmentation,
)
from monai_probreg.data.transforms import registration_transforms
from monai_probreg.metrics.jacobian import jacobian_determinant


def _blob_pair(shape: tuple[int, ...]) -> dict:
    """A smooth off-centre blob and its label map (1 inside, 0 outside), plus a fixed image."""
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in shape], indexing="ij")
    centre = [0.25, -0.2, 0.1][: len(shape)]
    r2 = sum((a - c) ** 2 for a, c in zip(axes, centre))
    image = torch.exp(-r2 / 0.15)[None].float()
    label = (image > 0.5).to(torch.int16)
    return {"moving": MetaTensor(image), "moving_label": MetaTensor(label), "fixed": MetaTensor(image.clone())}


def _strong(seed: int = 0, with_labels: bool = True):
    return moving_augmentation(
        prob=1.0, rotate_range=0.3, scale_range=0.15, translate_range=4.0, with_labels=with_labels, seed=seed
    )


@pytest.mark.parametrize("shape", [(24, 28, 20), (32, 28)])
def test_image_and_labels_move_together_and_fixed_stays(shape):
    pair = _blob_pair(shape)
    out = _strong()(pair)
    moved = out["moving"][0]
    assert not torch.allclose(moved, pair["moving"][0], atol=1e-3)  # the image really moved
    # the label map was resampled with the same affine: it is still the image's >0.5 region, but for rim voxels
    agree = ((moved > 0.5) == (out["moving_label"][0] > 0)).float().mean()
    before = ((moved > 0.5) == (pair["moving_label"][0] > 0)).float().mean()
    assert agree > 0.98 and agree > before + 0.01
    assert torch.equal(out["fixed"], pair["fixed"])


def test_labels_stay_integer_and_no_value_is_invented():
    pair = _blob_pair((20, 24, 20))
    pair["moving_label"] = MetaTensor(pair["moving_label"] * 7 + (pair["moving"] > 0.2).to(torch.int16) * 3)
    out = _strong()(pair)
    assert out["moving_label"].dtype == torch.int16 and out["moving"].dtype == torch.float32
    assert set(torch.unique(out["moving_label"]).tolist()) <= {0, 3, 10}
    assert out["moving"].shape == pair["moving"].shape and out["moving_label"].shape == pair["moving_label"].shape


def test_prob_zero_is_the_identity():
    pair = _blob_pair((16, 16, 16))
    out = moving_augmentation(prob=0.0, rotate_range=0.3, translate_range=4.0, with_labels=True)(pair)
    assert torch.equal(out["moving"], pair["moving"]) and torch.equal(out["moving_label"], pair["moving_label"])


def test_labels_are_left_alone_without_with_labels():
    pair = _blob_pair((16, 16, 16))
    out = _strong(with_labels=False)(pair)
    assert torch.equal(out["moving_label"], pair["moving_label"])


def test_a_single_rotation_value_rotates_about_every_axis():
    rand = moving_augmentation(prob=1.0, rotate_range=0.2).transforms[0].rand_affine.rand_affine_grid
    assert tuple(rand.rotate_range) == (0.2, 0.2, 0.2)  # MONAI randomises only the axes it is given a range for


def test_after_the_cached_chain_only_the_augmentation_is_random():
    chain = registration_transforms(network_size=(32, 32, 32), resize_labels=True)
    full = type(chain)([chain, moving_augmentation(prob=1.0, with_labels=True)]).flatten()
    first_random = full.get_index_of_first(lambda t: isinstance(t, Randomizable))
    assert first_random == len(chain.transforms)  # CacheDataset caches every deterministic step


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"prob": 1.5}, "prob must be in"),
        ({"prob": -0.1}, "prob must be in"),
        ({"rotate_range": -0.1}, "rotate_range"),
        ({"scale_range": (0.1, -0.2, 0.1)}, "scale_range"),
        ({"translate_range": ()}, "translate_range"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        moving_augmentation(**kwargs)


# --- RandDiffeomorphicd -------------------------------------------------------------------------------------------


def _deform(magnitude: float = 1.5, seed: int = 0, **kwargs) -> RandDiffeomorphicd:
    t = RandDiffeomorphicd(keys=["moving"], label_keys=["moving_label"], magnitude=magnitude, **kwargs)
    t.set_random_state(seed=seed)
    return t


@pytest.mark.parametrize("shape", [(40, 48, 36), (64, 56)])
def test_random_deformation_is_smooth_invertible_and_of_the_asked_size(shape):
    t = _deform(magnitude=1.5, control_spacing=8.0)
    t.randomize(shape)
    ddf = t.displacement(shape)
    assert ddf.shape == (1, len(shape), *shape)
    rms = float(ddf.pow(2).sum(1).mean().sqrt())
    assert 1.2 < rms < 1.7  # the velocity's RMS is 1.5; exp(v) of a smooth field stays close to it
    assert float(jacobian_determinant(ddf).min()) > 0  # a diffeomorphism: no folding


@pytest.mark.parametrize("shape", [(40, 48, 36), (64, 56)])
def test_the_inverse_displacement_undoes_the_drawn_one(shape):
    t = _deform(magnitude=2.0, control_spacing=8.0, seed=5)
    t.randomize(shape)
    forward, inverse = t.displacement(shape), t.displacement(shape, inverse=True)
    # exp(v) o exp(-v) = id: x + inverse(x) + forward(x + inverse(x)) = x, away from the border
    composed = inverse + warp_image(forward, inverse)
    inner = (slice(None), slice(None)) + tuple(slice(6, n - 6) for n in shape)
    error, size = composed[inner].norm(dim=1), forward[inner].norm(dim=1)
    assert float(error.mean()) < 0.1 * float(size.mean()) and float(error.max()) < 0.25 * float(size.max())
    assert float(size.mean()) > 1.0


def test_the_images_are_pulled_back_through_the_drawn_displacement():
    pair = _blob_pair((32, 36, 28))
    t = _deform(seed=3)
    out = t(dict(pair))
    ddf = t.displacement((32, 36, 28))  # the same draw: displacement() re-reads the last noise
    torch.testing.assert_close(out["moving"][None].as_tensor(), warp_image(pair["moving"][None].as_tensor(), ddf))
    assert torch.equal(out["moving_label"][None].as_tensor(), warp_labels(pair["moving_label"][None].as_tensor(), ddf))
    assert out["moving_label"].dtype == torch.int16 and torch.equal(out["fixed"], pair["fixed"])
    assert not torch.allclose(out["moving"], pair["moving"], atol=1e-3)


def test_zero_magnitude_or_probability_leaves_the_pair_alone():
    pair = _blob_pair((16, 20, 16))
    for t in (_deform(magnitude=0.0), RandDiffeomorphicd(keys=["moving"], prob=0.0)):
        out = t(dict(pair))
        assert torch.equal(out["moving"], pair["moving"]) and torch.equal(out["moving_label"], pair["moving_label"])


@pytest.mark.parametrize("make", [_strong, _deform], ids=["affine", "deformation"])
def test_a_seed_makes_the_draw_repeatable_and_seeds_differ(make):
    pair = _blob_pair((20, 20, 20))
    a, b, c = (make(seed=s)(dict(pair))["moving"] for s in (5, 5, 6))
    assert torch.equal(a, b) and not torch.allclose(a, c)


def test_a_key_on_another_grid_is_refused_by_name():
    pair = _blob_pair((16, 16, 16))
    pair["moving_label"] = MetaTensor(torch.zeros((1, 8, 16, 16), dtype=torch.int16))
    with pytest.raises(ValueError, match=r"moving_label must be on the grid of moving.*\(16, 16, 16\).*\(8, 16, 16\)"):
        _deform()(pair)


@pytest.mark.parametrize("kwargs", [{"magnitude": -1.0}, {"control_spacing": 0.5}])
def test_bad_deformation_arguments_are_refused(kwargs):
    with pytest.raises(ValueError, match="magnitude must be >= 0 and control_spacing >= 1"):
        RandDiffeomorphicd(keys=["moving"], **kwargs)


def test_moving_augmentation_adds_the_deformation_only_when_asked():
    assert not any(isinstance(t, RandDiffeomorphicd) for t in moving_augmentation(prob=1.0).transforms)
    chain = moving_augmentation(prob=1.0, with_labels=True, deform_magnitude=1.0, deform_spacing=6.0)
    deform = [t for t in chain.transforms if isinstance(t, RandDiffeomorphicd)]
    assert len(deform) == 1 and deform[0].label_keys == ("moving_label",) and deform[0].control_spacing == 6.0
    with pytest.raises(ValueError, match="deform_magnitude"):
        moving_augmentation(deform_magnitude=-0.5)


# --- intensity augmentation of the network inputs ---------------------------------------------------------------


def _intensity_pair(shape=(20, 24, 16)) -> dict:
    pair = _blob_pair(shape)
    pair["fixed"] = MetaTensor(pair["fixed"].flip(1))  # another image: the two draws must not be tied to one input
    return pair


def test_intensity_prob_zero_adds_no_input_keys():
    pair = _intensity_pair()
    out = intensity_augmentation(prob=0.0)(pair)
    assert set(out) == set(pair)


def test_intensity_inputs_change_the_clean_images_stay():
    pair = _intensity_pair()
    clean = {k: v.clone() for k, v in pair.items()}
    out = intensity_augmentation(prob=1.0, seed=3)(pair)
    for key in ("moving", "fixed"):
        assert torch.equal(out[key], clean[key])  # the likelihood's images are untouched
        made = out[key + INPUT_SUFFIX]
        assert made.shape == clean[key].shape and made.dtype == torch.float32
        assert float(made.min()) >= 0.0 and float(made.max()) <= 1.0  # scaled as the preprocessing scales
        assert float((made - clean[key]).abs().mean()) > 0.01
    assert torch.equal(out["moving_label"], clean["moving_label"])


def test_intensity_draws_are_independent_per_image_and_seeded():
    image = _blob_pair((20, 24, 16))["moving"]
    pair = {"moving": image, "fixed": MetaTensor(image.clone())}  # the same image on both sides
    out = intensity_augmentation(prob=1.0, seed=5)(pair)
    assert not torch.allclose(out["moving_input"], out["fixed_input"], atol=1e-3)
    again = intensity_augmentation(prob=1.0, seed=5)({k: v.clone() for k, v in pair.items()})
    assert torch.equal(out["moving_input"], again["moving_input"])
    other = intensity_augmentation(prob=1.0, seed=6)({k: v.clone() for k, v in pair.items()})
    assert not torch.equal(out["moving_input"], other["moving_input"])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"prob": 1.5}, "prob"),
        ({"prob": -0.1}, "prob"),
        ({"bias_coeff": -1.0}, "bias_coeff"),
        ({"noise_std": -0.1}, "noise_std"),
        ({"gamma": (1.5, 0.5)}, "gamma"),
        ({"gamma": (0.0, 1.0)}, "gamma"),
        ({"gamma": (1.0,)}, "gamma"),
        ({"smooth_sigma": (1.0, 0.5)}, "smooth_sigma"),
        ({"smooth_sigma": (-1.0, 0.5)}, "smooth_sigma"),
    ],
)
def test_bad_intensity_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        intensity_augmentation(**{"prob": 0.5, **kwargs})
