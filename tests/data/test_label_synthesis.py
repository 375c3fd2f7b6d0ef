"""Images rendered from label maps (monai_probreg.data.label_synthesis): the table lands where the labels are, one
table per pair, random contrasts where asked, slots that never collide, the blur's mass kept, bad arguments refused."""

from __future__ import annotations

import pytest
import torch
from monai.data import MetaTensor

from monai_probreg.data.label_synthesis import (
    ASEG_LABELS,
    T1_LIKE,
    RandLabelContrastd,
    SlotLabelsd,
    render_labels,
    scale_to_unit,
)


def _blocks(shape=(12, 10, 8)) -> torch.Tensor:
    """(1, *S) map: background, white matter (2), cortex (3), a ventricle (4) and an unknown label (507)."""
    labels = torch.zeros(1, *shape, dtype=torch.int16)
    labels[0, 1:6] = 2
    labels[0, 6:9] = 3
    labels[0, 9:11, :5] = 4
    labels[0, 9:11, 5:] = 507
    return labels


def test_render_puts_each_labels_intensity_in_its_voxels_background_at_zero():
    labels = _blocks()
    image = render_labels(labels, {2: 1.0, 3: 0.6, 4: 0.2, 507: 0.4})
    assert image.shape == labels.shape and image.dtype == torch.float32
    values = {v: image[labels == v].unique() for v in (0, 2, 3, 4, 507)}
    assert all(len(u) == 1 for u in values.values()), "no noise, no blur: one value per label"
    order = sorted(values, key=lambda v: float(values[v][0]))
    assert order == [0, 4, 507, 3, 2]  # the table's order, background darkest
    assert float(image.min()) == 0.0 and float(image.max()) == 1.0  # scaled to [0, 1] by the percentiles


def test_texture_noise_stays_off_the_background_and_the_blur_spreads_it():
    labels = _blocks()
    generator = torch.Generator().manual_seed(0)
    noisy = render_labels(labels, {2: 1.0, 3: 0.6, 4: 0.2, 507: 0.4}, texture_std=0.05, generator=generator)
    assert float(noisy[labels == 0].std()) == 0.0 and float(noisy[labels == 2].std()) > 0.01
    blurred = render_labels(labels, {2: 1.0, 3: 0.6, 4: 0.2, 507: 0.4}, blur_sigma=1.0)
    edge = blurred[0, 0, 0, 0]  # background next to white matter: lifted by the blur
    assert 0.0 < float(edge) < 0.5


def test_scale_to_unit_maps_the_percentiles_to_zero_and_one():
    image = torch.linspace(0, 10, 1001)
    out = scale_to_unit(image, 10.0, 90.0)
    assert float(out.min()) == 0.0 and float(out.max()) == 1.0
    assert float(out[500]) == pytest.approx(0.5, abs=0.01)  # the middle of a linear ramp stays in the middle


def test_one_table_per_pair_the_same_label_the_same_intensity_in_both_images():
    labels = _blocks()
    pair = {
        "moving": MetaTensor(torch.zeros(1, 12, 10, 8)),
        "fixed": torch.zeros(1, 12, 10, 8),
        "moving_label": labels,
        "fixed_label": labels.flip(1),
    }
    render = RandLabelContrastd(random_prob=0.0, texture_std=0.0, blur_sigma=(0.0, 0.0))
    render.set_random_state(seed=3)
    out = render(pair)
    assert isinstance(out["moving"], MetaTensor) and out["moving"].shape == labels.shape
    for v in (2, 3, 4, 507):
        assert torch.allclose(out["moving"][labels == v].unique(), out["fixed"][labels.flip(1) == v].unique())
    assert pair["moving"].abs().sum() == 0, "the input dict's tensors are not changed in place"


def test_t1_like_tables_keep_the_t1_order_random_ones_do_not():
    render = RandLabelContrastd(random_prob=0.0, jitter=0.02)
    render.set_random_state(seed=0)
    for _ in range(20):  # with a 2% jitter white matter > cortex > ventricle every time
        table = render.draw_table([2, 3, 4])
        assert table[2] > table[3] > table[4]
    random = RandLabelContrastd(random_prob=1.0)
    random.set_random_state(seed=0)
    orders = {tuple(sorted((2, 3, 4), key=random.draw_table([2, 3, 4]).get)) for _ in range(50)}
    assert len(orders) > 3, f"random contrasts should reorder the labels; saw only {orders}"


def test_prob_zero_leaves_the_pair_as_it_is():
    pair = {
        "moving": torch.ones(1, 4, 4, 4),
        "fixed": torch.ones(1, 4, 4, 4),
        "moving_label": torch.ones(1, 4, 4, 4, dtype=torch.int16),
        "fixed_label": torch.ones(1, 4, 4, 4),
    }
    out = RandLabelContrastd(prob=0.0)(pair)
    assert out["moving"] is pair["moving"] and out["fixed"] is pair["fixed"]


def test_slots_map_the_structures_in_order_and_everything_else_to_zero():
    labels = torch.tensor([[0, 2, 3, 41, 163, 507, 24]], dtype=torch.int16)
    out = SlotLabelsd(keys=["moving_label"], structures=[2, 3, 41, 24], slots=[21, 22, 23, 24, 25])(
        {"moving_label": MetaTensor(labels)}
    )["moving_label"]
    assert out.tolist() == [[0, 21, 22, 23, 0, 0, 24]]  # 163 is an LPBA40 slot too: it must not survive as one
    assert out.dtype == torch.int16 and isinstance(out, MetaTensor)


def test_the_tables_know_the_aseg_structures_left_and_right():
    assert set(ASEG_LABELS) <= set(T1_LIKE) and len(ASEG_LABELS) == 32
    for left, right in ((2, 41), (3, 42), (17, 53), (10, 49)):
        assert T1_LIKE[left] == T1_LIKE[right]
    assert T1_LIKE[2] > T1_LIKE[3] > T1_LIKE[4]  # T1: white matter > grey matter > CSF


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"image_keys": ["moving"], "label_keys": ["moving_label", "fixed_label"]}, "one label key per image key"),
        ({"random_prob": 1.5}, "random_prob"),
        ({"jitter": -0.1}, "jitter"),
        ({"texture_std": -1.0}, "texture_std"),
        ({"blur_sigma": (1.0, 0.5)}, "blur_sigma"),
        ({"blur_sigma": (0.5,)}, "blur_sigma"),
    ],
)
def test_rand_label_contrast_rejects_bad_arguments(kwargs, words):
    with pytest.raises(ValueError, match=words):
        RandLabelContrastd(**kwargs)


@pytest.mark.parametrize(
    "structures, slots, words",
    [
        ([1, 2, 3], [5, 6], "at most 2"),
        ([1, 1], [5, 6], "distinct"),
        ([-1], [5], "non-negative"),
    ],
)
def test_slots_reject_bad_arguments(structures, slots, words):
    with pytest.raises(ValueError, match=words):
        SlotLabelsd(keys=["moving_label"], structures=structures, slots=slots)


@pytest.mark.parametrize(
    "labels, words", [(torch.zeros(4, 4), "spatial axes"), (-torch.ones(1, 3, 3, 3), "non-negative")]
)
def test_render_rejects_bad_label_maps(labels, words):
    with pytest.raises(ValueError, match=words):
        render_labels(labels.long(), {1: 1.0})
