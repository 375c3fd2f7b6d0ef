"""Post-hoc std scaling: the fit recovers a known scale, the sidecar is tied to its weights."""

import json
import math

import numpy as np
import pytest
import torch

from monai_probreg.calibration import (
    calibrate_log_var,
    calibration_path,
    fit_std_scale,
    load_calibration,
    save_calibration,
    std_scale_for,
)
from monai_probreg.metrics.calibration import interval_coverage


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
    """New default weights need a refitted calibration (benchmarks/uncertainty_calibration.py --write-calibration):
    a stale record would be refused at inference time; this catches it before release."""
    from pathlib import Path

    from monai_probreg.calibration import load_calibration

    weights = Path(__file__).resolve().parents[1] / "bundle" / "models" / "model_semisupervised.pt"
    record = load_calibration(weights)  # raises when the SHA-256 does not match the weights
    assert record.std_scale > 1.0  # the raw variational posterior is over-confident (README "Uncertainty")
