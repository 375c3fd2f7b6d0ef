"""monai_probreg.uncertainty.quality: the failure definition, the fits, the warning and the sidecar."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from monai.bundle import ConfigParser

from monai_probreg.fitting.quality_fit import fit_quality_model
from monai_probreg.uncertainty.quality import (
    FAILURE_MARGIN,
    LNCC_DROP_MARGIN,
    PERFECT_DICE,
    QualityModel,
    failed,
    load_quality_model,
    quality_path,
    quality_record,
    save_quality_model,
)
from monai_probreg.uncertainty.quality_features import QualityFeatures

N = len(QualityFeatures._fields)


def _features(ncc_after: float, rng: np.random.Generator) -> QualityFeatures:
    noise = rng.normal(0, 0.01, N)
    return QualityFeatures(*(float(v) for v in np.r_[0.5, ncc_after, 0.4, ncc_after - 0.1, 1.0, 2.0, 0.2, 0.0] + noise))


def _training_set(seed: int = 0):
    """Synthetic registrations whose Dice is a known linear function of ncc_after; failures below 0.4."""
    rng = np.random.default_rng(seed)
    ncc = rng.uniform(-0.3, 0.9, 120)
    features = [_features(float(c), rng) for c in ncc]
    dice = 0.2 + 0.5 * ncc
    return features, dice, dice < 0.4


@pytest.mark.parametrize(
    "dice, before, identity, expected",
    [
        (0.70, 0.60, 0.55, False),
        (0.59, 0.60, 0.50, True),  # below the affine alone
        (0.58, 0.50, 0.55, True),  # below no registration + margin
        (0.55 + FAILURE_MARGIN, 0.50, 0.55, False),  # exactly at the margin is not a failure
        (PERFECT_DICE, PERFECT_DICE, PERFECT_DICE, False),  # a scan onto itself, left as it was
        (PERFECT_DICE - FAILURE_MARGIN, 0.99, PERFECT_DICE, False),  # within the margin of a perfect overlap
        (0.90, 0.99, PERFECT_DICE, True),  # a copy of itself registered further off than the margin
    ],
)
def test_the_failure_definition(dice, before, identity, expected):
    assert failed(dice, before, identity) is expected


def test_the_failure_probability_has_no_floor_far_from_the_threshold():
    """Logits far below 0 (pairs far on the good side, e.g. scans onto near copies of themselves) keep their own
    probability: no clip of the logit maps them all to one number."""
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    n = len(model.mean)
    far = dataclasses.replace(model, failure_coef=[0.0] * n, failure_intercept=-50.0)
    further = dataclasses.replace(far, failure_intercept=-60.0)
    p_far, p_further = (float(m.predict([features[0]])[1][0]) for m in (far, further))
    assert p_far == pytest.approx(math.exp(-50.0), rel=1e-9, abs=0) and p_further == pytest.approx(
        math.exp(-60.0), rel=1e-9, abs=0
    )


def test_the_fits_recover_a_known_relation():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures, fitted_on=["A", "B"])
    test_features, test_dice, test_failures = _training_set(seed=1)
    predicted, probability = model.predict(test_features)
    assert np.abs(predicted - test_dice).max() < 0.05
    assert (probability[test_failures] > 0.5).mean() > 0.9 and (probability[~test_failures] < 0.5).mean() > 0.9
    assert model.fitted_on == ["A", "B"]


def test_estimate_warns_only_above_the_threshold():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    rng = np.random.default_rng(3)
    good, bad = model.estimate(_features(0.85, rng)), model.estimate(_features(-0.25, rng))
    assert good.warning is None and good.failure_probability < 0.5 and good.predicted_dice > 0.55
    assert bad.warning is not None and "probably failed" in bad.warning and bad.failure_probability >= 0.5


def test_a_drop_in_local_similarity_warns_whatever_the_models_say():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    good = _features(0.85, np.random.default_rng(4))
    # the same registration, but the deformable step lowered the local NCC (0.4 before): the models, clipped to
    # their training range, still call it good
    dropped = good._replace(lncc_before=0.99, lncc_after=0.6)
    estimate = model.estimate(dropped)
    assert estimate.failure_probability < 0.5 and estimate.predicted_dice > 0.55
    assert estimate.warning is not None and "less alike" in estimate.warning and "0.990 -> 0.600" in estimate.warning
    assert model.estimate(dropped._replace(lncc_after=0.99)).warning is None  # equal is no drop


def test_a_drop_within_the_margin_is_rounding_not_a_warning():
    """The rule fires only beyond lncc_drop_margin (LNCC_DROP_MARGIN by default): a registration that changes nothing
    must not warn or not by the UNet's rounding (bf16 or fp32)."""
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    assert model.lncc_drop_margin == LNCC_DROP_MARGIN > 0
    good = _features(0.85, np.random.default_rng(4))
    within = good._replace(lncc_before=0.985, lncc_after=0.985 - 0.5 * LNCC_DROP_MARGIN)
    beyond = good._replace(lncc_before=0.985, lncc_after=0.985 - 2.0 * LNCC_DROP_MARGIN)
    assert model.estimate(within).warning is None
    assert "less alike" in model.estimate(beyond).warning
    strict = dataclasses.replace(model, lncc_drop_margin=0.0)  # no margin: any drop warns (the rule before)
    assert "less alike" in strict.estimate(within).warning


def test_non_finite_features_warn():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    estimate = model.estimate(QualityFeatures(*([math.nan] + [0.0] * (N - 1))))
    assert estimate.failure_probability == 1.0 and "not finite" in estimate.warning


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"features": [], "dice": [], "failures": []}, ">= 2 registrations"),
        ({"dice": [0.5]}, ">= 2 registrations"),
        ({"failures": [True]}, ">= 2 registrations"),
    ],
)
def test_bad_fit_inputs_are_refused(kwargs, match):
    features, dice, failures = _training_set()
    args = {"features": features, "dice": dice, "failures": failures, **kwargs}
    with pytest.raises(ValueError, match=match):
        fit_quality_model(**args)


def test_non_finite_training_features_are_refused():
    features, dice, failures = _training_set()
    features[3] = QualityFeatures(*([math.inf] + list(features[3])[1:]))
    with pytest.raises(ValueError, match="finite"):
        fit_quality_model(features, dice, failures)


def _model(**changes) -> dict:
    features, dice, failures = _training_set()
    data = fit_quality_model(features, dice, failures).__dict__.copy()
    data.update(changes)
    return data


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"feature_names": ["a"] * N}, "feature_names"),
        ({"mean": [0.0]}, "mean must have"),
        ({"scale": [0.0] * N}, "scale must be positive"),
        ({"low": [1.0] * N, "high": [0.0] * N}, "low must be <= high"),
        ({"threshold": 1.0}, "threshold"),
        ({"lncc_drop_margin": -0.001}, "lncc_drop_margin"),
        ({"lncc_drop_margin": 1.0}, "lncc_drop_margin"),
        ({"dice_range": [0.8, 0.2]}, "dice_range"),
        ({"dice_low": [0.0] * N}, "dice_low and dice_high must be"),  # one without the other
        ({"dice_low": [1.0] * N, "dice_high": [0.0] * N}, "dice_low and dice_high must be"),
        ({"entropy_calibration": {"std_scale": 0.5}}, "entropy_calibration must be"),
        ({"entropy_calibration": {"std_scale": 0.5, "bias_fraction": 0.1, "x": 1}}, "entropy_calibration must be"),
        ({"entropy_calibration": {"std_scale": 0.0, "bias_fraction": 0.1}}, "std_scale must be"),
        ({"entropy_calibration": {"std_scale": 0.5, "bias_fraction": -0.1}}, "bias_fraction must be"),
        # the intervals' dof is no part of an entropy: a sidecar that records one was not written by this package
        (
            {"entropy_calibration": {"std_scale": 0.5, "bias_fraction": 0.1, "interval_dof": 3.0}},
            "entropy_calibration must be",
        ),
    ],
)
def test_bad_model_values_are_refused(changes, match):
    with pytest.raises(ValueError, match=match):
        QualityModel(**_model(**changes))


def test_sidecar_round_trip_and_weights_check(tmp_path):
    weights = tmp_path / "model.pt"
    torch.save({"w": torch.zeros(2)}, weights)
    assert load_quality_model(weights) is None  # none yet
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    path = save_quality_model(model, weights)
    assert path == quality_path(weights) == tmp_path / "model.quality.json"
    loaded = load_quality_model(weights)
    assert loaded == model and loaded.weights_file == "model.pt"
    torch.save({"w": torch.ones(2)}, weights)  # retrained weights: the old sidecar must not be used
    with pytest.raises(ValueError, match="refit"):
        load_quality_model(weights)
    path.write_text(json.dumps({"not": "a model"}))
    with pytest.raises(ValueError, match="not a quality model"):
        load_quality_model(weights)


def test_features_outside_the_training_range_are_not_extrapolated():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    rng = np.random.default_rng(5)
    edge, beyond = _features(0.9, rng), _features(5.0, rng)  # ncc_after far above anything seen
    assert model.predict([beyond])[0][0] == pytest.approx(model.predict([edge])[0][0], abs=0.02)
    assert model.predict([beyond])[0][0] < 0.7
    assert model.dice_range == [pytest.approx(min(dice)), pytest.approx(max(dice))]
    assert np.all(model.predict(features)[0] <= max(dice) + 1e-12)


def test_the_shipped_default_weights_carry_their_own_quality_model():
    """New default weights need a refitted quality model (python -m monai_probreg.fitting): a stale one would be
    refused at inference time; this catches it before release."""
    from pathlib import Path

    weights = Path(__file__).resolve().parents[2] / "bundle" / "models" / "model.pt"
    model = load_quality_model(weights)  # raises when the SHA-256 does not match the weights
    assert model is not None and len(model.fitted_on) >= 2
    assert not {"S11", "S14", "S16", "S21", "S28", "S29"} & set(model.fitted_on)  # never a validation subject
    # the calibration its entropy feature was fitted with, whatever calibration the maps use now
    assert set(model.entropy_calibration) == {"std_scale", "bias_fraction"}
    # fitted on the outcome of the path the configs run by default (the refined one, with these settings)
    parser = ConfigParser()
    parser.read_config(str(weights.parents[1] / "configs" / "inference.yaml"))
    assert parser.get_parsed_content("refinement").differences(model.refinement) == {}


def test_the_models_read_the_networks_registration_and_the_drop_rule_reads_the_answer():
    """With refinement the estimate has two feature sets (quality.py, "Whose features"): the failure and Dice models
    read the network's registration, the local-NCC drop rule the refined answer the user gets."""
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures)
    rng = np.random.default_rng(5)
    failed_network, good = _features(-0.25, rng), _features(0.85, rng)
    # a refined answer that looks perfect does not hide a failed network registration (a turned header)
    hidden = model.estimate(failed_network, answer=good)
    assert hidden.failure_probability >= 0.5 and "probably failed" in hidden.warning
    assert hidden.failure_probability == model.estimate(failed_network).failure_probability
    # the network's step lowered the local NCC but the refined answer did not: no drop warning
    network_dropped = good._replace(lncc_before=0.99, lncc_after=0.6)
    assert "less alike" in model.estimate(network_dropped).warning
    assert model.estimate(network_dropped, answer=good._replace(lncc_before=0.99, lncc_after=0.995)).warning is None
    # the refined answer lowered it: warned, with the answer's numbers
    warned = model.estimate(good, answer=good._replace(lncc_before=0.99, lncc_after=0.6)).warning
    assert "less alike" in warned and "0.990 -> 0.600" in warned
    # a non-finite answer is no answer to trust either
    assert model.estimate(good, answer=QualityFeatures(*([math.nan] * N))).failure_probability == 1.0


def test_the_record_names_both_feature_sets():
    features, dice, failures = _training_set()
    model = fit_quality_model(features, dice, failures, refinement={"num_iterations": 10})
    assert model.refinement == {"num_iterations": 10}
    assert fit_quality_model(features, dice, failures).refinement == {}
    rng = np.random.default_rng(6)
    network, answer = _features(0.8, rng), _features(0.9, rng)
    record = quality_record(network, model.estimate(network, answer), answer)
    assert record["features"]["ncc_after"] == pytest.approx(network.ncc_after)
    assert record["answer_features"]["ncc_after"] == pytest.approx(answer.ncc_after)
    assert quality_record(network, model.estimate(network))["answer_features"] is None


def test_the_entropy_feature_keeps_the_fits_calibration():
    """A sidecar that records its entropy's calibration gives it whatever calibration is in use; one without (before
    0.19.0) reads the calibration in use; fit_quality_model records the one it is given, and it survives a round trip."""
    from monai_probreg.uncertainty.calibration import Calibration

    features, dice, failures = _training_set()
    unrecorded = fit_quality_model(features, dice, failures)
    assert unrecorded.entropy_calibration == {}
    assert unrecorded.feature_calibration(0.7, 0.3) == Calibration(0.7, 0.3)
    recorded = fit_quality_model(features, dice, failures, entropy_calibration=Calibration(0.49, 0.24))
    assert recorded.entropy_calibration == {"std_scale": 0.49, "bias_fraction": 0.24}
    assert recorded.feature_calibration(0.7, 0.3) == Calibration(0.49, 0.24)
    assert QualityModel(**json.loads(json.dumps(dataclasses.asdict(recorded)))) == recorded
    # the intervals' dof does not enter an entropy: a calibration with Student-t intervals records the same two numbers
    with_dof = fit_quality_model(features, dice, failures, entropy_calibration=Calibration(0.49, 0.24, 3.0))
    assert with_dof.entropy_calibration == recorded.entropy_calibration
