"""The fit's choice of the residual term's weight: the weight whose sampled std ranks the population probe's errors
best. Cases made by hand (a std that is the network's spread plus the weighted residual, errors drawn at a known
spread), so that the right choice is known: the residual's weight when the errors follow the residual, none when they
follow the network's spread alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monai_probreg.fitting.calibration_probes import RESIDUAL_WEIGHTS, CalibrationProbes
from monai_probreg.uncertainty.calibration import Calibration

VOXELS = 20_000


class _HandMadeProbes(CalibrationProbes):
    """Population cases whose sampled std at a calibration is sqrt(sigma^2 + w r) (the residual term unscaled) and
    whose errors were drawn with the spread ``truth`` of each voxel."""

    def __init__(self, sigma: np.ndarray, residual: np.ndarray, truth: np.ndarray) -> None:
        case = {"velocity_std": torch.from_numpy(sigma), "residual_std": torch.from_numpy(np.sqrt(residual))}
        super().__init__(None, 2, None, {"S1": [case], "S2": [case]}, {}, {}, None, {}, {})
        rng = np.random.default_rng(0)
        self.sigma, self.residual = sigma, residual
        self.errors = {sid: truth * rng.standard_normal(truth.shape) for sid in self.cases}

    def population_errors(self, sid: str, calibration: Calibration) -> list[tuple[np.ndarray, ...]]:
        std = calibration.std_scale * np.sqrt(self.sigma**2 + calibration.residual_weight * self.residual)
        return [(std, self.errors[sid], np.zeros_like(std))]


def _spreads() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.3, 0.4, (3, VOXELS))  # the network's spread: nearly the same everywhere
    residual = rng.uniform(0.0, 1e-3, (3, VOXELS))  # the pair's residual: from none to some
    return sigma, residual


def test_errors_that_follow_the_residual_choose_a_residual_weight():
    sigma, residual = _spreads()
    truth = np.sqrt(sigma**2 + 300.0 * residual)  # the errors' spread follows the residual
    assert _HandMadeProbes(sigma, residual, truth).residual_weight_for(["S1", "S2"]) >= 100.0


def test_errors_that_follow_the_networks_spread_keep_it_alone():
    sigma, residual = _spreads()
    truth = sigma**4  # the errors' spread follows the network's spread only (steeply, to rank clearly)
    assert _HandMadeProbes(sigma, residual, truth).residual_weight_for(["S1", "S2"]) == 0.0


def test_each_weight_is_sampled_as_wide_as_the_networks_spread_alone():
    sigma, residual = _spreads()
    probes = _HandMadeProbes(sigma, residual, sigma)
    assert probes.unit_scale(["S1"], 0.0) == 1.0
    for weight in (10.0, 1000.0):
        unit = probes.unit_scale(["S1", "S2"], weight)
        assert unit < 1.0
        assert np.mean(unit**2 * (sigma**2 + weight * residual)) == pytest.approx(np.mean(sigma**2))


def test_the_weights_tried_start_with_none_and_grow():
    assert RESIDUAL_WEIGHTS[0] == 0.0 and list(RESIDUAL_WEIGHTS) == sorted(set(RESIDUAL_WEIGHTS))
    assert all(w >= 0 for w in RESIDUAL_WEIGHTS)


@pytest.mark.parametrize("sids", [["S1"], ["S1", "S2"]])
def test_the_choice_reads_only_the_subjects_asked_for(sids):
    sigma, residual = _spreads()
    probes = _HandMadeProbes(sigma, residual, np.sqrt(sigma**2 + 300.0 * residual))
    read: list[str] = []
    original = probes.population_errors

    def spy(sid: str, calibration: Calibration) -> list[tuple[np.ndarray, ...]]:
        read.append(sid)
        return original(sid, calibration)

    probes.population_errors = spy
    probes.residual_weight_for(sids)
    assert set(read) == set(sids) and len(read) == len(sids) * len(RESIDUAL_WEIGHTS)


def test_the_sample_gain_makes_the_samples_spread_as_far_as_the_map():
    from test_population_probe import _case

    from monai_probreg.fitting.calibration_probes import GAIN_TOLERANCE
    from monai_probreg.fitting.population_probe import case_errors, sampled_case_variance

    network, case = _case(sigma=0.2)
    probes = CalibrationProbes(network, 16, None, {"S1": [case]}, {}, {}, None, {}, {})
    calibration = Calibration(1.0, 0.0)
    gain = probes.sample_gain_for(["S1"], calibration)
    assert gain > 1.2
    mapped = float(np.mean(case_errors(case, calibration)[0] ** 2))
    sampled = float(sampled_case_variance(network, case, calibration._replace(sample_gain=gain), 16).mean())
    assert sampled / mapped == pytest.approx(1.0, abs=GAIN_TOLERANCE)
