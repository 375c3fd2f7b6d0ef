"""Tests of the per-label Dice from integer label maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_probreg import label_dice

LABELS = np.array([0, 21, 22, 181])  # not contiguous, like FreeSurfer's


def naive_dice(pred, target, labels):
    pred, target = np.asarray(pred), np.asarray(target)
    out = {}
    for lab in labels:
        a, b = pred == lab, target == lab
        denom = a.sum() + b.sum()
        out[int(lab)] = 2.0 * np.logical_and(a, b).sum() / denom if denom > 0 else float("nan")
    return out


def _random_maps(shape, seed=0, values=LABELS):
    rng = np.random.default_rng(seed)
    return rng.choice(values, size=shape), rng.choice(values, size=shape)


def _assert_dice_equal(got, expected):
    assert list(got) == list(expected)
    for lab in expected:
        if math.isnan(expected[lab]):
            assert math.isnan(got[lab]), lab
        else:
            # exact counts, one float64 division each: 1e-12 relative
            assert got[lab] == pytest.approx(expected[lab], rel=1e-12), lab


@pytest.mark.parametrize("shape", [(2, 1, 7, 8, 9), (1, 1, 12, 13), (50,)], ids=["3d", "2d", "flat"])
@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.float32])
def test_matches_naive_numpy_dice(shape, dtype):
    pred, target = _random_maps(shape)
    got = label_dice(torch.as_tensor(pred).to(dtype), torch.as_tensor(target).to(dtype))
    _assert_dice_equal(got, naive_dice(pred, target, [21, 22, 181]))


def test_matches_naive_numpy_dice_with_explicit_labels_including_background():
    pred, target = _random_maps((3, 10, 10), seed=1)
    labels = [181, 0, 22]
    got = label_dice(torch.as_tensor(pred), torch.as_tensor(target), labels=labels)
    _assert_dice_equal(got, naive_dice(pred, target, labels))


def test_labels_present_in_pred_only_do_not_disturb_scored_labels():
    pred, target = _random_maps((4, 9, 9), seed=2)
    pred[0, :3] = 500  # a label that target never has, larger than every scored label
    got = label_dice(torch.as_tensor(pred), torch.as_tensor(target))
    assert 500 not in got
    _assert_dice_equal(got, naive_dice(pred, target, [21, 22, 181]))


def test_identical_maps_score_one():
    _, target = _random_maps((2, 1, 6, 7, 8), seed=3)
    t = torch.as_tensor(target)
    got = label_dice(t.clone(), t)
    assert set(got) == {21, 22, 181}
    assert all(v == 1.0 for v in got.values())


def test_disjoint_maps_score_zero():
    target = torch.zeros(20, dtype=torch.long)
    target[:5] = 21
    target[5:10] = 22
    pred = torch.zeros_like(target)
    pred[10:15] = 21
    pred[15:20] = 22
    assert label_dice(pred, target) == {21: 0.0, 22: 0.0}


def test_label_absent_from_both_is_nan_when_requested():
    pred, target = _random_maps((5, 6, 7), seed=4)
    got = label_dice(torch.as_tensor(pred), torch.as_tensor(target), labels=[21, 7, 181])
    assert math.isnan(got[7])
    _assert_dice_equal(got, naive_dice(pred, target, [21, 7, 181]))


def test_label_absent_from_target_only_scores_zero():
    target = torch.tensor([0, 21, 21, 0])
    pred = torch.tensor([22, 21, 21, 0])
    assert label_dice(pred, target, labels=[21, 22]) == {21: 1.0, 22: 0.0}


def test_default_labels_are_nonzero_labels_of_target():
    target = torch.tensor([[0, 0, 181], [22, 22, 0]])
    pred = torch.tensor([[21, 0, 181], [22, 0, 0]])  # 21 only in pred: not scored by default
    got = label_dice(pred, target)
    assert list(got) == [22, 181]
    # 22: |A & B| = 1, |A| + |B| = 1 + 2
    assert got[22] == pytest.approx(2 / 3, rel=1e-15)
    assert got[181] == 1.0


def test_all_background_target_gives_empty_dict():
    assert label_dice(torch.tensor([0, 3, 4]), torch.zeros(3, dtype=torch.long)) == {}


def test_float_maps_with_integer_values_are_accepted():
    pred, target = _random_maps((4, 5, 6), seed=5)
    got = label_dice(torch.as_tensor(pred, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64))
    _assert_dice_equal(got, naive_dice(pred, target, [21, 22, 181]))


@pytest.mark.parametrize("which", ["pred", "target"])
def test_float_maps_with_non_integer_values_raise(which):
    good = torch.tensor([0.0, 21.0, 22.0, 181.0])
    bad = torch.tensor([0.0, 21.0, 21.5, 181.0])
    args = (bad, good) if which == "pred" else (good, bad)
    with pytest.raises(ValueError, match=rf"{which} must hold integer labels"):
        label_dice(*args)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match=r"same shape.*\(2, 3\).*\(3, 2\)"):
        label_dice(torch.zeros(2, 3, dtype=torch.long), torch.zeros(3, 2, dtype=torch.long))


@pytest.mark.parametrize(
    "pred,target,labels",
    [
        # a negative value (e.g. an "ignore" marker) must not be counted as label 0
        ([-1, -1, 0, 0, 3], [0, 0, 0, 0, 3], [0, 3]),
        # a requested negative label must be scored as itself
        ([-1, 3, 0], [-1, 0, 3], [-1, 3]),
    ],
    ids=["negative-value-vs-label-0", "negative-label-requested"],
)
def test_negative_values_are_scored_correctly_or_rejected(pred, target, labels):
    # Either behaviour is acceptable: a ValueError saying labels must be >= 0, or the exact Dice.
    # Silently merging negative values into other labels is not.
    pred_t, target_t = torch.tensor(pred), torch.tensor(target)
    try:
        got = label_dice(pred_t, target_t, labels=labels)
    except ValueError:
        return
    _assert_dice_equal(got, naive_dice(pred, target, labels))


def test_mean_dice_skips_labels_absent_from_both_maps_and_counts_one_sided_ones_as_zero():
    from monai_probreg.metrics.dice import mean_dice

    pred = torch.tensor([[1, 1, 2, 0]])
    target = torch.tensor([[1, 1, 0, 3]])
    dice = label_dice(pred, target, [1, 2, 3, 4])  # 1 matches, 2 only in pred, 3 only in target, 4 in neither
    assert dice[1] == 1.0 and dice[2] == 0.0 and dice[3] == 0.0 and math.isnan(dice[4])
    assert mean_dice(dice) == pytest.approx(1 / 3)
    assert math.isnan(mean_dice({}))
    assert math.isnan(mean_dice({5: float("nan")}))


def test_every_mean_dice_in_the_package_follows_the_one_rule():
    """score_pair (bundle evaluation), the validation metric (training) and the command line's summary agree on a
    pair where one scored label is absent from both maps."""
    import numpy as np

    from monai_probreg.engines.validation_metric import RegistrationMetrics
    from monai_probreg.metrics.dice import mean_dice
    from monai_probreg.metrics.scores import score_pair
    from monai_probreg.networks.probreg_net import RegistrationOutput
    from monai_probreg.registration.compose import _dice
    from monai_probreg.spatial.volume_io import Volume

    moving = torch.zeros(1, 1, 4, 5, 6, dtype=torch.long)
    fixed = torch.zeros_like(moving)
    moving[..., :2, :, :] = 1
    fixed[..., :3, :, :] = 1
    moving[..., 3, :, :] = 2  # label 2 in the moving map only; label 7 in neither
    labels = [1, 2, 7]
    expected = mean_dice(label_dice(moving, fixed, labels))
    assert not math.isnan(expected)
    assert score_pair(None, moving, fixed, labels=labels).mean_dice == pytest.approx(expected)
    zero = torch.zeros(1, 3, 4, 5, 6)
    metric = RegistrationMetrics(label_values=labels)
    metric.reset()
    pred = RegistrationOutput(*([None] * len(RegistrationOutput._fields)))._replace(displacement=zero)
    metric.update((pred, {"moving_label": moving.float(), "fixed_label": fixed.float()}))
    assert metric.compute()["dice"] == pytest.approx(expected)
    fixed_volume = Volume(fixed[0, 0].numpy().astype(np.int32), np.eye(4))
    assert _dice(moving[0, 0].numpy(), fixed_volume, labels)["mean"] == pytest.approx(expected)


def test_dice_histogram_in_chunks_is_the_whole_maps(monkeypatch):
    """The joint histogram summed over chunks of voxels (int32 maps read as they are): the same Dice exactly."""
    from monai_probreg.metrics import dice

    rng = np.random.default_rng(0)
    pred = torch.from_numpy(rng.integers(0, 7, (9, 8, 7)).astype(np.int32))
    target = torch.from_numpy(rng.integers(0, 7, (9, 8, 7)).astype(np.int32))
    whole = label_dice(pred.long(), target.long(), [1, 2, 3, 6, 9])
    monkeypatch.setattr(dice, "_CHUNK", 37)
    assert label_dice(pred, target, [1, 2, 3, 6, 9]) == pytest.approx(whole, nan_ok=True)
    assert label_dice(pred, target) == label_dice(pred.long(), target.long())
