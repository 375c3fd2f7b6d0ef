"""Post-hoc calibration: the fit recovers a known scale and bias fraction, the sidecar is tied to its weights."""

import json
import math

import numpy as np
import pytest
import torch

from monai_probreg.metrics.calibration import interval_coverage
from monai_probreg.uncertainty.calibration import (
    FIT_LEVELS,
    bias_variance,
    calibrate_log_var,
    calibration_for,
    calibration_path,
    fit_calibration,
    fit_std_scale,
    load_calibration,
    save_calibration,
    std_scale_for,
)
from monai_probreg.uncertainty.residual import PLAIN_RESIDUAL_FORM, residual_form


def _toy(true_scale: float, n: int = 100_000):
    rng = np.random.default_rng(0)
    std = np.exp(rng.normal(0.0, 0.5, n))
    return std, true_scale * std * rng.standard_normal(n)


def test_calibrate_log_var_scales_the_std():
    log_var = torch.tensor([-4.0, 0.0, 3.0])
    out = calibrate_log_var(log_var, 2.5)
    torch.testing.assert_close(torch.exp(0.5 * out), 2.5 * torch.exp(0.5 * log_var))
    torch.testing.assert_close(calibrate_log_var(log_var, 1.0), log_var)


@pytest.mark.parametrize("scale", [0.0, -1.0, math.inf, math.nan])
def test_calibrate_log_var_rejects_bad_scale(scale):
    with pytest.raises(ValueError, match="std_scale"):
        calibrate_log_var(torch.zeros(1), scale)


@pytest.mark.parametrize("true_scale", [0.3, 1.0, 4.0])
def test_fit_recovers_a_known_scale_and_coverage(true_scale):
    std, error = _toy(true_scale)
    scale = fit_std_scale(std, error)
    assert scale == pytest.approx(true_scale, rel=0.02)
    assert interval_coverage(scale * std, error, 0.95) == pytest.approx(0.95, abs=0.01)
    assert interval_coverage(scale * std, error, 0.68) == pytest.approx(0.68, abs=0.01)


def test_fit_rejects_bad_input():
    with pytest.raises(ValueError, match="same"):
        fit_std_scale(np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="positive"):
        fit_std_scale(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="levels"):
        fit_std_scale(np.ones(3), np.ones(3), levels=())


@pytest.fixture
def weights(tmp_path):
    path = tmp_path / "model.pt"
    torch.save({"w": torch.arange(4.0)}, path)
    return path


def test_sidecar_round_trip(weights):
    record = save_calibration(weights, 3.25, fitted_on=["S11", "S14"], num_samples=16)
    assert calibration_path(weights) == weights.with_name("model.calibration.json")
    assert load_calibration(weights) == record
    assert std_scale_for(weights) == 3.25
    assert std_scale_for(weights, calibrate=False) == 1.0
    assert not list(weights.parent.glob("*.tmp"))
    assert record.refinement == {}  # the network's mean


def test_the_sidecar_records_the_refinement_it_was_fitted_around(weights):
    settings = {"num_iterations": 10, "image_grid_factor": 2}
    record = save_calibration(weights, 0.5, bias_fraction=0.2, refinement=settings)
    assert load_calibration(weights).refinement == settings == record.refinement


def test_the_record_to_use_is_read_once_and_none_means_raw(weights):
    from monai_probreg.uncertainty.calibration import calibration_record_for

    with pytest.warns(UserWarning, match="has no calibration"):
        assert calibration_record_for(weights) is None
    record = save_calibration(weights, 0.5, bias_fraction=0.2, refinement={"num_iterations": 10})
    assert calibration_record_for(weights) == record
    assert calibration_record_for(weights, calibrate=False) is None


def test_a_sidecar_from_before_the_refinement_record_loads_as_not_recorded(weights):
    save_calibration(weights, 0.5, bias_fraction=0.2)
    path = calibration_path(weights)
    data = json.loads(path.read_text())
    del data["refinement"]  # as bundles before 0.18.0 wrote them
    path.write_text(json.dumps(data))
    assert load_calibration(weights).refinement is None  # unknown, not "the network's mean" ({})


@pytest.mark.parametrize("value", [[10, 2], "lncc", 3])
def test_a_refinement_record_that_is_not_a_mapping_is_named(weights, value):
    save_calibration(weights, 0.5)
    path = calibration_path(weights)
    path.write_text(json.dumps({**json.loads(path.read_text()), "refinement": value}))
    with pytest.raises(ValueError, match="model.calibration.json: refinement must be a mapping"):
        load_calibration(weights)


def test_sidecar_refuses_other_weights(weights):
    save_calibration(weights, 2.0)
    torch.save({"w": torch.zeros(4)}, weights)  # retrained
    with pytest.raises(ValueError, match="SHA-256"):
        std_scale_for(weights)


def test_missing_sidecar_warns_and_gives_raw(weights):
    with pytest.warns(UserWarning, match="no calibration"):
        assert std_scale_for(weights) == 1.0


def test_corrupt_sidecar_names_the_file(weights):
    calibration_path(weights).write_text("{not json")
    with pytest.raises(ValueError, match="model.calibration.json"):
        load_calibration(weights)
    calibration_path(weights).write_text(json.dumps({"std_scale": 2.0}))  # missing fields
    with pytest.raises(ValueError, match="not a calibration record"):
        load_calibration(weights)


def test_the_shipped_default_weights_carry_their_own_calibration():
    """New default weights need a refitted calibration (python -m monai_probreg.fitting):
    a stale record would be refused at inference time; this catches it before release."""
    from pathlib import Path

    from monai_probreg.uncertainty.calibration import load_calibration

    weights = Path(__file__).resolve().parents[2] / "bundle" / "models" / "model.pt"
    record = load_calibration(weights)  # raises when the SHA-256 does not match the weights
    # since bundle 0.25.0 the spread follows the registered pair's residual (docs/uncertainty.md): the fit chose a
    # residual weight, which makes std_scale the scale of (sigma^2 + w r), no longer comparable with 1
    assert record.residual_weight > 0 and record.std_scale > 0.0 and record.bias_fraction >= 0.0
    # the 95% half-width the docs quote (README, docs/uncertainty.md, bundle docs: 3.57 std) is the shipped sidecar's
    from monai_probreg.metrics.calibration import interval_z

    half_width = f"{interval_z(0.95, record.interval_dof):.2f}"
    for doc in ("README.md", "docs/uncertainty.md", "bundle/docs/README.md"):
        assert half_width in (weights.parents[2] / doc).read_text(), doc
    assert any("subject probe" in name for name in record.fitted_on)
    # fitted around the mean the configs give by default (the refined one, with these settings)
    from monai.bundle import ConfigParser

    from monai_probreg.registration.demo import DEMO_SAMPLES

    parser = ConfigParser()
    parser.read_config(str(weights.parents[1] / "configs" / "inference.yaml"))
    assert parser.get_parsed_content("refinement").differences(record.refinement) == {}
    # and the label entropy sampled as the samples' gain was measured
    assert record.sample_gain > 1.0  # independent velocity noise reaches the displacement damped
    assert DEMO_SAMPLES == parser.get_parsed_content("num_samples") == record.num_samples


# --- the bias term: (bias_fraction |u|)^2 added to every component's variance ---------------------------------------


def _biased_toy(scale: float, bias_fraction: float, n: int = 400_000):
    """Errors drawn exactly from N(0, scale^2 std^2 + (bias_fraction |u|)^2): the fit's known answer."""
    rng = np.random.default_rng(1)
    std, norm = np.exp(rng.normal(0.0, 0.4, n)), rng.gamma(2.0, 2.0, n)
    error = rng.standard_normal(n) * np.sqrt((scale * std) ** 2 + (bias_fraction * norm) ** 2)
    return std, error, norm


@pytest.mark.parametrize("scale, bias_fraction", [(2.5, 0.2), (1.0, 0.5)])
def test_fit_calibration_recovers_a_known_scale_and_bias_fraction(scale, bias_fraction):
    std, error, norm = _biased_toy(scale, bias_fraction)
    fitted = fit_calibration(std, error, norm)
    assert fitted.std_scale == pytest.approx(scale, rel=0.05)
    assert fitted.bias_fraction == pytest.approx(bias_fraction, abs=0.02)
    total = np.sqrt((fitted.std_scale * std) ** 2 + (fitted.bias_fraction * norm) ** 2)
    for level in (0.68, 0.95):
        assert interval_coverage(total, error, level) == pytest.approx(level, abs=0.01)


def test_fit_calibration_without_bias_matches_fit_std_scale():
    std, error = _toy(3.0)
    fitted = fit_calibration(std, error, np.ones_like(std), bias_fractions=(0.0,), interval_dofs=(None,))
    assert fitted == (pytest.approx(fit_std_scale(std, error)), 0.0, None, 0.0, None, 1.0)


@pytest.mark.parametrize(
    "norm, fractions, match",
    [
        (np.ones(4), (), "must not be empty"),
        (np.ones(4), (-0.1,), "bias_fraction"),
        (-np.ones(4), (0.1,), "displacement_norm finite and >= 0"),
        (np.ones(3), (0.1,), "same non-empty shape"),
    ],
)
def test_fit_calibration_rejects_bad_input(norm, fractions, match):
    with pytest.raises(ValueError, match=match):
        fit_calibration(np.ones(4), np.ones(4), norm, bias_fractions=fractions)


def test_calibrate_log_var_adds_the_bias_term_in_quadrature():
    log_var = torch.log(torch.full((1, 3, 2, 2, 2), 4.0))  # sigma 2 per component
    mean = torch.zeros(1, 3, 2, 2, 2)
    mean[0, :, 0, 0, 0] = torch.tensor([3.0, 4.0, 0.0])  # |mu| = 5
    out = calibrate_log_var(log_var, 1.5, mean, 0.8)  # (1.5 * 2)^2 + (0.8 * 5)^2 = 9 + 16 = 25
    torch.testing.assert_close(out[0, :, 0, 0, 0].exp(), torch.full((3,), 25.0))
    torch.testing.assert_close(out[0, :, 1, 1, 1].exp(), torch.full((3,), 9.0))  # mu = 0: the scaled std alone
    torch.testing.assert_close(calibrate_log_var(log_var, 1.5, mean, 0.0), calibrate_log_var(log_var, 1.5))
    with pytest.raises(ValueError, match="needs the posterior mean"):
        calibrate_log_var(log_var, 1.5, None, 0.8)
    with pytest.raises(ValueError, match="needs the posterior mean"):
        calibrate_log_var(log_var, 1.5, mean[:, :2], 0.8)
    with pytest.raises(ValueError, match="bias_fraction"):
        calibrate_log_var(log_var, 1.5, mean, -0.1)


def test_bias_variance_is_the_squared_fraction_of_the_length():
    u = torch.zeros(1, 3, 2, 2, 2)
    u[0, :, 0, 0, 0] = torch.tensor([3.0, 4.0, 0.0])  # |u| = 5
    variance = bias_variance(u, 0.2)
    assert variance.shape == (1, 1, 2, 2, 2)
    assert variance[0, 0, 0, 0, 0].item() == pytest.approx(1.0) and variance.sum().item() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="bias_fraction"):
        bias_variance(u, float("nan"))
    with pytest.raises(ValueError, match=r"\(B, D, \*S\)"):
        bias_variance(torch.zeros(3, 4), 0.1)


def test_sidecar_keeps_the_bias_fraction_and_old_sidecars_read_as_zero(weights):
    save_calibration(weights, 2.0, bias_fraction=0.15)
    assert (
        calibration_for(weights) == (2.0, 0.15, None, 0.0, None, 1.0)
        and load_calibration(weights).bias_fraction == 0.15
    )
    assert calibration_for(weights, calibrate=False) == (1.0, 0.0, None, 0.0, None, 1.0)
    record = json.loads(calibration_path(weights).read_text())
    del record["bias_fraction"]  # written before the bias term existed
    calibration_path(weights).write_text(json.dumps(record))
    assert calibration_for(weights) == (2.0, 0.0, None, 0.0, None, 1.0)
    record["bias_fraction"] = -0.5
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match="model.calibration.json: bias_fraction"):
        load_calibration(weights)
    with pytest.raises(ValueError, match="bias_fraction"):
        save_calibration(weights, 2.0, bias_fraction=-1.0)


def test_sidecar_keeps_the_residual_weight_and_old_sidecars_read_as_zero(weights):
    save_calibration(weights, 1.5, interval_dof=2.0, residual_weight=300.0)
    assert calibration_for(weights) == (1.5, 0.0, 2.0, 300.0, None, 1.0)
    record = json.loads(calibration_path(weights).read_text())
    del record["residual_weight"]  # written before the residual term existed
    calibration_path(weights).write_text(json.dumps(record))
    assert calibration_for(weights) == (1.5, 0.0, 2.0, 0.0, None, 1.0)
    record["residual_weight"] = -1.0
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match="model.calibration.json: residual_weight"):
        load_calibration(weights)


def test_the_sidecar_records_the_residual_form_and_refuses_another(weights):
    save_calibration(weights, 1.5, residual_weight=300.0)
    record = json.loads(calibration_path(weights).read_text())
    assert record["residual"] == residual_form()
    for fitted in (None, PLAIN_RESIDUAL_FORM, {**residual_form(), "window": residual_form()["window"] + 2}):
        if fitted is None:  # a sidecar of bundles 0.24.0-0.28.0: fitted with the plain squared difference
            del record["residual"]
        else:
            record["residual"] = fitted
        calibration_path(weights).write_text(json.dumps(record))
        expected = PLAIN_RESIDUAL_FORM if fitted is None else fitted
        if expected == residual_form():
            assert load_calibration(weights).residual_weight == 300.0
            continue
        with pytest.raises(ValueError, match=r"model.calibration.json: fitted for the pair's residual .* refit it"):
            load_calibration(weights)
    record["residual_weight"] = 0.0  # no residual term: the form does not matter
    calibration_path(weights).write_text(json.dumps(record))
    assert load_calibration(weights).residual_weight == 0.0


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf"), True])
def test_a_bad_residual_weight_is_refused(weight, weights):
    with pytest.raises(ValueError, match="residual_weight must be a finite number >= 0"):
        save_calibration(weights, 1.0, residual_weight=weight)


def test_the_residual_term_adds_its_weighted_variance_before_the_scale():
    log_var = torch.log(torch.full((1, 2, 3, 4), 0.5))
    residual = torch.linspace(0.0, 1.0, 12).view(1, 1, 3, 4)
    mean = torch.randn(1, 2, 3, 4)
    calibrated = calibrate_log_var(log_var, 2.0, mean, 0.1, residual, 3.0)
    expected = 4.0 * (0.5 + 3.0 * residual) + 0.01 * mean.square().sum(1, keepdim=True)
    torch.testing.assert_close(calibrated.exp(), expected.expand_as(calibrated))
    # weight 0: the residual is not needed and changes nothing
    torch.testing.assert_close(calibrate_log_var(log_var, 2.0), calibrate_log_var(log_var, 2.0, None, 0.0, residual))


@pytest.mark.parametrize("residual", [None, torch.zeros(1, 2, 3, 4), torch.zeros(1, 1, 3, 5)])
def test_a_residual_weight_without_a_residual_of_the_grid_is_refused(residual):
    with pytest.raises(ValueError, match=r"residual_weight > 0 needs the residual \(1, 1, 3, 4\)"):
        calibrate_log_var(torch.zeros(1, 2, 3, 4), 1.0, None, 0.0, residual, 1.0)


# --- groups: several probes, each one's coverage matched on its own -------------------------------------------------


def _grouped_toy():
    """Group 0: 200k errors of scale 1; group 1: 10k errors of scale 3 (std 1 everywhere)."""
    rng = np.random.default_rng(3)
    sizes, scales = (200_000, 10_000), (1.0, 3.0)
    error = np.concatenate([rng.standard_normal(n) * s for n, s in zip(sizes, scales)])
    groups = np.repeat([0, 1], sizes)
    return np.ones(error.size), error, np.zeros(error.size), groups


def _grouped_cost(scale: float, std, error, groups, levels=FIT_LEVELS) -> float:
    """The brute-force cost: sum over groups and levels of (coverage - level)^2."""
    return sum(
        (interval_coverage(scale * std[groups == g], error[groups == g], p) - p) ** 2
        for g in np.unique(groups)
        for p in levels
    )


def test_grouped_fit_minimises_the_summed_cost_of_the_groups():
    std, error, norm, groups = _grouped_toy()
    fitted = fit_calibration(std, error, norm, bias_fractions=(0.0,), groups=groups, interval_dofs=(None,))
    grid = np.geomspace(0.5, 5.0, 400)
    brute = min(_grouped_cost(s, std, error, groups) for s in grid)
    assert _grouped_cost(fitted.std_scale, std, error, groups) <= brute + 1e-6
    # the small group is not drowned: one pool would fit close to the large group's scale
    pooled = fit_calibration(std, error, norm, bias_fractions=(0.0,), interval_dofs=(None,))
    assert pooled.std_scale < 1.3 < 1.6 < fitted.std_scale < 3.0


def test_one_group_is_no_group():
    std, error, norm = _biased_toy(2.0, 0.2, n=250_000)  # more than the bias fraction's search subset
    assert fit_calibration(std, error, norm, groups=np.full(std.shape, 7)) == fit_calibration(std, error, norm)
    # two groups drawn from the same errors fit as one (each group's coverage is over its own entries)
    halves = np.random.default_rng(2).integers(0, 2, std.size)
    split = fit_calibration(std, error, norm, groups=halves)
    assert split.std_scale == pytest.approx(2.0, rel=0.05) and split.bias_fraction == pytest.approx(0.2, abs=0.02)


@pytest.mark.parametrize("groups", [np.zeros(3, np.int64), np.zeros(4)])
def test_fit_calibration_rejects_bad_groups(groups):
    with pytest.raises(ValueError, match="groups must be integers"):
        fit_calibration(np.ones(4), np.ones(4), np.ones(4), groups=groups)


def _student_toy(true_scale: float, dof: float, n: int = 200_000):
    rng = np.random.default_rng(3)
    std = np.exp(rng.normal(0.0, 0.5, n))
    return std, true_scale * std * rng.standard_t(dof, n)


@pytest.mark.parametrize("true_scale, true_dof", [(1.5, 3.0), (0.6, 6.0)])
def test_fit_recovers_the_tails_of_student_t_errors(true_scale, true_dof):
    """Errors std * scale * t_dof: the fit finds the dof and the scale, and its intervals cover every level, where
    the best Gaussian scale (the fit without a dof) cannot cover the 68% and the 95% level at once."""
    std, error = _student_toy(true_scale, true_dof)
    fitted = fit_calibration(std, error, np.zeros_like(std), bias_fractions=(0.0,))
    assert fitted.interval_dof == true_dof and fitted.std_scale == pytest.approx(true_scale, rel=0.03)
    for level in FIT_LEVELS:
        assert interval_coverage(fitted.std_scale * std, error, level, fitted.interval_dof) == pytest.approx(
            level, abs=0.01
        )
    gaussian = fit_std_scale(std, error)
    misses = [abs(interval_coverage(gaussian * std, error, p) - p) for p in FIT_LEVELS]
    assert max(misses) > 0.02


def test_fit_keeps_gaussian_intervals_for_gaussian_errors():
    std, error = _toy(2.0, 200_000)
    fitted = fit_calibration(std, error, np.zeros_like(std), bias_fractions=(0.0,))
    assert fitted.interval_dof is None or fitted.interval_dof >= 30  # no tails to fit: Gaussian or nearly
    assert fitted.std_scale == pytest.approx(2.0, rel=0.03)


def test_fit_finds_the_bias_and_the_dof_together():
    rng = np.random.default_rng(4)
    n = 200_000
    std, norm = np.exp(rng.normal(0.0, 0.3, n)), rng.uniform(0.0, 10.0, n)
    sigma = np.sqrt(1.2**2 * std**2 + (0.3 * norm) ** 2)
    error = sigma * rng.standard_t(4.0, n)
    fitted = fit_calibration(std, error, norm)
    assert fitted.interval_dof in (3.0, 4.0, 5.0) and fitted.bias_fraction == pytest.approx(0.3, abs=0.04)
    total = np.sqrt(fitted.std_scale**2 * std**2 + (fitted.bias_fraction * norm) ** 2)
    assert interval_coverage(total, error, 0.95, fitted.interval_dof) == pytest.approx(0.95, abs=0.01)


@pytest.mark.parametrize(
    "dofs, match", [((), "must not be empty"), ((0.0,), "interval_dof"), ((-3.0,), "interval_dof")]
)
def test_fit_rejects_bad_interval_dofs(dofs, match):
    with pytest.raises(ValueError, match=match):
        fit_calibration(np.ones(4), np.ones(4), np.ones(4), interval_dofs=dofs)


def test_sidecar_keeps_the_interval_dof_and_old_sidecars_read_as_gaussian(weights):
    save_calibration(weights, 1.3, interval_dof=3.0)
    assert calibration_for(weights) == (1.3, 0.0, 3.0, 0.0, None, 1.0) and load_calibration(weights).interval_dof == 3.0
    record = json.loads(calibration_path(weights).read_text())
    del record["interval_dof"]  # written before bundle 0.21.0
    calibration_path(weights).write_text(json.dumps(record))
    assert calibration_for(weights) == (1.3, 0.0, None, 0.0, None, 1.0)


@pytest.mark.parametrize("dof", [0.0, -1.0, "3", True])
def test_a_sidecar_with_a_bad_interval_dof_is_refused(weights, dof):
    save_calibration(weights, 1.3)
    record = json.loads(calibration_path(weights).read_text())
    record["interval_dof"] = dof
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match="model.calibration.json: interval_dof"):
        load_calibration(weights)
    with pytest.raises(ValueError, match="interval_dof"):
        save_calibration(weights, 1.3, interval_dof=dof)


def test_sidecar_keeps_the_error_model_with_its_features(weights):
    from monai_probreg.uncertainty.error_model import ERROR_FEATURES

    coefficients = tuple(0.1 * k for k in range(len(ERROR_FEATURES) + 1))
    save_calibration(weights, 1.5, residual_weight=10.0, error_model=coefficients)
    record = json.loads(calibration_path(weights).read_text())
    assert record["error_features"] == list(ERROR_FEATURES) and len(record["error_model"]) == len(ERROR_FEATURES) + 1
    assert calibration_for(weights).error_model == pytest.approx(coefficients)
    assert isinstance(calibration_for(weights).error_model, tuple)
    del record["error_model"], record["error_features"]  # written before the error model: the residual
    calibration_path(weights).write_text(json.dumps(record))
    assert calibration_for(weights).error_model is None


def test_an_error_model_of_other_features_is_refused_with_the_refit_command(weights):
    from monai_probreg.uncertainty.error_model import ERROR_FEATURES

    save_calibration(weights, 1.5, residual_weight=10.0, error_model=(0.0,) * (len(ERROR_FEATURES) + 1))
    record = json.loads(calibration_path(weights).read_text())
    record["error_features"] = record["error_features"][:-1] + ["something else"]
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"model.calibration.json: an error model of the features .*refit it"):
        load_calibration(weights)


@pytest.mark.parametrize("coefficients", [(1.0, 2.0), (float("nan"),) * 13, ("a",) * 13, (True,) * 13])
def test_a_bad_error_model_is_refused(coefficients, weights):
    with pytest.raises(ValueError, match="an error model is 13 finite numbers"):
        save_calibration(weights, 1.0, residual_weight=1.0, error_model=coefficients)


def test_sidecar_keeps_the_sample_gain_and_refuses_a_sidecar_fitted_on_sampled_stds(weights):
    save_calibration(weights, 1.5, residual_weight=10.0, sample_gain=1.7)
    assert calibration_for(weights).sample_gain == 1.7 and load_calibration(weights).sample_gain == 1.7
    assert calibration_for(weights, calibrate=False).sample_gain == 1.0
    record = json.loads(calibration_path(weights).read_text())
    del record["sample_gain"]  # written before bundle 0.34.0: its std_scale was fitted on the sampled std
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"model.calibration.json: fitted on the sampled displacement std.*refit it"):
        load_calibration(weights)


@pytest.mark.parametrize("gain", [0.0, -1.0, float("nan"), float("inf"), "2", True])
def test_a_bad_sample_gain_is_not_written(weights, gain):
    with pytest.raises(ValueError, match="sample_gain"):
        save_calibration(weights, 1.3, sample_gain=gain)


@pytest.mark.parametrize("gain", [0.0, -1.0, "2", True])
def test_a_sidecar_with_a_bad_sample_gain_is_refused(weights, gain):
    save_calibration(weights, 1.3)
    record = json.loads(calibration_path(weights).read_text())
    record["sample_gain"] = gain
    calibration_path(weights).write_text(json.dumps(record))
    with pytest.raises(ValueError, match="model.calibration.json: sample_gain"):
        load_calibration(weights)
