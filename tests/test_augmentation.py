"""monai_probreg.augmentation: the moving scan and its labels get one random affine; the fixed side never moves."""

from __future__ import annotations

import pytest
import torch
from monai.data import MetaTensor
from monai.transforms import Randomizable

from monai_probreg.augmentation import moving_augmentation
from monai_probreg.data import registration_transforms


def _blob_pair(shape: tuple[int, ...]) -> dict:
    """A smooth off-centre blob and its label map (1 inside, 0 outside), plus a fixed image."""
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in shape], indexing="ij")
    centre = [0.25, -0.2, 0.1][: len(shape)]
    r2 = sum((a - c) ** 2 for a, c in zip(axes, centre))
    image = torch.exp(-r2 / 0.15)[None].float()
    label = (image > 0.5).to(torch.int16)
    return {"moving": MetaTensor(image), "moving_label": MetaTensor(label), "fixed": MetaTensor(image.clone())}


def _strong(seed: int = 0, with_labels: bool = True):
    return moving_augmentation(prob=1.0, rotate_range=0.3, scale_range=0.15, translate_range=4.0,
                               with_labels=with_labels, seed=seed)


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
    pair["moving_label"] = MetaTensor((pair["moving_label"] * 7 + (pair["moving"] > 0.2).to(torch.int16) * 3))
    out = _strong()(pair)
    assert out["moving_label"].dtype == torch.int16 and out["moving"].dtype == torch.float32
    assert set(torch.unique(out["moving_label"]).tolist()) <= {0, 3, 10}
    assert out["moving"].shape == pair["moving"].shape and out["moving_label"].shape == pair["moving_label"].shape


def test_prob_zero_is_the_identity():
    pair = _blob_pair((16, 16, 16))
    out = moving_augmentation(prob=0.0, rotate_range=0.3, translate_range=4.0, with_labels=True)(pair)
    assert torch.equal(out["moving"], pair["moving"]) and torch.equal(out["moving_label"], pair["moving_label"])


def test_a_seed_makes_the_draw_repeatable_and_seeds_differ():
    pair = _blob_pair((16, 20, 16))
    a, b, c = (_strong(seed=s)(dict(pair))["moving"] for s in (1, 1, 2))
    assert torch.equal(a, b) and not torch.allclose(a, c)


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


@pytest.mark.parametrize("kwargs, match", [
    ({"prob": 1.5}, "prob must be in"),
    ({"prob": -0.1}, "prob must be in"),
    ({"rotate_range": -0.1}, "rotate_range"),
    ({"scale_range": (0.1, -0.2, 0.1)}, "scale_range"),
    ({"translate_range": ()}, "translate_range"),
])
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        moving_augmentation(**kwargs)
