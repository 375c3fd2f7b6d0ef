"""The calibration benchmark's ground truth: the random deformation has the asked RMS and its stated inverse."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from bench_helpers import load_benchmark

from monai_probreg.blocks.warp import compose_displacements, warp_image

bench = load_benchmark("uncertainty_calibration")


@pytest.fixture
def brain():
    """A smooth positive 'brain' inside a zero background (linear interpolation barely blurs it)."""
    x, y, z = torch.meshgrid(*(torch.arange(n, dtype=torch.float32) for n in (32, 36, 28)), indexing="ij")
    image = torch.zeros(1, 1, 32, 36, 28)
    inside = (slice(6, 26), slice(6, 30), slice(5, 23))
    image[0, 0][inside] = (1.5 + torch.sin(x / 3) * torch.cos(y / 4) + 0.5 * torch.sin(z / 5))[inside]
    return image


def test_random_deformation_has_the_asked_rms_and_inverse(brain):
    forward, inverse = bench.random_deformation(brain, 1.5, torch.Generator().manual_seed(1))
    inside = brain[0, 0] > 0
    rms = forward[0][:, inside].pow(2).sum(0).mean().sqrt()
    assert rms.item() == pytest.approx(1.5, rel=0.05)
    # exp(v) o exp(-v) = id: the truth the benchmark scores against is the inverse of what deformed the image
    residual = compose_displacements(forward, inverse)[0][:, inside].abs().max()
    assert residual < 0.05
    # moving = fixed o exp(v); pulling moving back by exp(-v) restores fixed (up to interpolation blur)
    restored = warp_image(warp_image(brain, forward), inverse)
    assert (restored - brain)[0, 0][inside].abs().mean() < 0.1 * brain[0, 0][inside].mean()


def test_recovered_fraction_closed_forms():
    truth = np.random.default_rng(0).normal(size=1000)
    assert bench.recovered_fraction(np.zeros(1000), truth) == pytest.approx(1.0)
    assert bench.recovered_fraction(-truth, truth) == pytest.approx(0.0)
    assert bench.recovered_fraction(-0.7 * truth, truth) == pytest.approx(0.3)


class _Oracle(torch.nn.Module):
    """A 'registration' that returns ``gain`` times the true displacement of a pure translation (found by
    matching the moving image against the fixed one shifted by whole voxels along each axis)."""

    def __init__(self, fixed: torch.Tensor, gain: float) -> None:
        super().__init__()
        self.fixed, self.gain = fixed, gain

    def forward(self, moving, fixed):
        best = None
        for axis in range(3):
            for shift in (-3.0, 3.0):
                d = torch.zeros((1, 3, *fixed.shape[2:]))
                d[:, axis] = shift
                err = (warp_image(self.fixed, d) - moving).abs().mean()
                if best is None or err < best[0]:
                    best = (err, d)
        return type("Out", (), {"displacement": -self.gain * best[1]})()


@pytest.mark.parametrize("gain", [1.0, 0.5, 0.0])
def test_translation_probe_reports_the_recovered_fraction(brain, gain):
    fractions = bench.translation_probe(_Oracle(brain, gain), brain, shift=3.0)
    assert fractions == pytest.approx([gain] * 3, abs=1e-6)


class _ConstantPosterior(torch.nn.Module):
    """posterior(moving, fixed).mean = the moving image's mean intensity, constant on a (3, 4, 5, 3) velocity grid."""

    def posterior(self, moving, fixed):
        return type("Posterior", (), {"mean": moving.mean() * torch.ones((1, 3, 4, 5, 3))})()


def test_population_velocities_are_the_mean_and_the_deviations_from_it():
    items = [
        {"moving": torch.full((1, 8, 8, 8), value), "fixed": torch.zeros((1, 8, 8, 8)), "id": f"T{value}"}
        for value in (1.0, 2.0, 6.0)
    ]
    mean, deviations = bench.population_velocities(_ConstantPosterior(), items)
    assert mean.shape == (3, 4, 5, 3) and deviations.shape == (3, 3, 4, 5, 3)
    assert torch.allclose(mean, torch.full_like(mean, 3.0))
    assert torch.allclose(deviations[:, 0, 0, 0, 0], torch.tensor([-2.0, -1.0, 3.0]))


def test_population_velocities_need_two_subjects():
    with pytest.raises(SystemExit, match=">= 2 training subjects"):
        bench.population_velocities(
            _ConstantPosterior(), [{"moving": torch.ones((1, 8, 8, 8)), "fixed": torch.ones((1, 8, 8, 8))}]
        )


def test_population_deformation_is_the_drawn_subject_to_atlas_field_and_its_inverse(brain):
    """Deviations (d, -d): the draw is -v = (w0 - w1) d with w = randn(2) of the same generator; the truth is
    exp(-v) integrated at full resolution, the forward field its inverse."""
    velocity_grid = tuple(n // 2 for n in brain.shape[2:])
    d = torch.zeros((3, *velocity_grid))
    x = torch.linspace(0, math.pi, velocity_grid[0])[:, None, None]
    d[0] = 0.8 * torch.sin(x).expand(velocity_grid)  # a smooth bump along axis 0, velocity-grid voxels
    draw = bench.population_velocity((torch.zeros_like(d), torch.stack([d, -d])), torch.Generator().manual_seed(3))
    forward, truth = bench.population_deformation(brain, draw)
    w = torch.randn(2, generator=torch.Generator().manual_seed(3))
    expected = bench.ScalingAndSquaring(num_steps=bench.TRUTH_STEPS)(
        bench.resize_displacement(((w[0] - w[1]) * d)[None], brain.shape[2:])
    )
    assert torch.allclose(truth, expected, atol=1e-5)
    inside = brain[0, 0] > 0
    assert compose_displacements(forward, truth)[0][:, inside].abs().max() < 0.05


def test_displacement_metrics_on_a_perfectly_calibrated_gaussian_reach_their_ceiling():
    rng = np.random.default_rng(3)
    std = np.exp(rng.normal(0.0, 0.8, (3, 50_000)))
    m = bench.displacement_metrics(std, std * rng.standard_normal(std.shape))
    assert m["coverage_68"] == pytest.approx(0.68, abs=0.01) and m["coverage_95"] == pytest.approx(0.95, abs=0.01)
    assert m["spearman_std_abs_error"] == pytest.approx(m["spearman_ceiling"], abs=0.02)
    assert m["spearman_vector"] == pytest.approx(m["spearman_vector_ceiling"], abs=0.02)
    # one component's |error| scatters more at a given std than a vector's length: the vector ceiling is higher
    assert 0.3 < m["spearman_ceiling"] < m["spearman_vector_ceiling"] < 1.0
    blind = bench.displacement_metrics(
        np.ones_like(std) + 1e-9 * rng.random(std.shape), std * rng.standard_normal(std.shape)
    )
    assert abs(blind["spearman_std_abs_error"]) < 0.02  # a std that knows nothing ranks nothing


def test_main_writes_the_table_the_figures_and_a_two_number_calibration(tmp_path, tiny_dataset, single_thread):
    from bench_helpers import REPO
    from conftest import bundle_with_random_model

    from monai_probreg.uncertainty.calibration import load_calibration

    bundle = bundle_with_random_model(tmp_path / "bundle", REPO / "bundle")  # configs' network grid, random weights
    out = tmp_path / "out"
    code = bench.main(
        [
            "--dataset-dir",
            str(tiny_dataset),
            "--bundle-root",
            str(bundle),
            "--subjects",
            "T01",
            "T02",
            "--deformations",
            "1",
            "--samples",
            "2",
            "--probe",
            "noise",
            "--out-dir",
            str(out),
            "--write-calibration",
            "--refine",
            "0",
        ]
    )  # the network's mean: random weights refined on a 16^3 blob fit no calibration
    assert code == 0
    report = json.loads((out / "uncertainty_calibration.json").read_text())
    assert (out / "uncertainty_reliability.png").stat().st_size > 0 and (
        out / "uncertainty_figure4.png"
    ).stat().st_size > 0
    for row in ("raw", "calibrated"):
        m = report["summary"][row]
        assert 0 <= m["coverage_68"] <= m["coverage_95"] <= 1
        assert all(
            -1 <= m[k] <= 1
            for k in ("spearman_std_abs_error", "spearman_ceiling", "spearman_vector", "spearman_vector_ceiling")
        )
    assert set(report["fold_calibrations"]) == {"0", "1"}
    written = load_calibration(bundle / "models" / "model.pt")
    assert written.std_scale == report["written_calibration"]["std_scale"] > 0
    assert 0 <= written.bias_fraction == report["written_calibration"]["bias_fraction"] <= 1
    assert written.interval_dof == report["written_calibration"]["interval_dof"]
    assert set(report["summary"]["calibrated"]["coverage_by_level"]) == {"0.5", "0.68", "0.8", "0.9", "0.95"}
    assert written.refinement == {}  # --refine 0: fitted around the network's own mean
    assert "Spearman of vectors (ceiling)" in report["markdown"]
    # the subject probe (default: the first training subjects; the tiny dataset has one, T03), fitted and held out
    probe = report["settings"]["subject_probe"]
    assert probe["templates"] == ["T03"] and probe["seeds"] == [bench.SUBJECT_SEED]
    assert "T03 (subject probe, seed 1000)" in written.fitted_on and {"T01", "T02"} <= set(written.fitted_on)
    for row in ("raw", "calibrated"):
        m = report["subject_probe_summary"][row]
        assert 0 <= m["coverage_68"] <= m["coverage_95"] <= 1 and set(m["per_template"]) == {"T03"}
    assert "calibrated (subject probe, mm)" in report["markdown"]


@pytest.mark.parametrize("deformations", [0, bench.SEED_STRIDE + 1])
def test_deformations_outside_the_seed_stride_are_refused(tmp_path, tiny_dataset, deformations):
    """Subject n's deformation r is drawn with seed + SEED_STRIDE n + r: 0 deformations score nothing, SEED_STRIDE + 1
    would reuse the next subject's first seed."""
    from bench_helpers import REPO
    from conftest import bundle_with_random_model

    bundle = bundle_with_random_model(tmp_path / "bundle", REPO / "bundle")
    with pytest.raises(SystemExit, match=rf"--deformations must be in \[1, {bench.SEED_STRIDE}\]"):
        bench.main(
            [
                "--dataset-dir",
                str(tiny_dataset),
                "--bundle-root",
                str(bundle),
                "--subjects",
                "T01",
                "T02",
                "--deformations",
                str(deformations),
                "--out-dir",
                str(tmp_path / "out"),
            ]
        )


def test_the_posterior_of_the_default_path_has_the_refined_mean_and_the_networks_variance(brain):
    from monai_probreg import ProbRegNet
    from monai_probreg.engines.refinement import RefinementSettings

    torch.manual_seed(0)
    network = ProbRegNet(network_size=(16, 16, 16)).eval()
    moving = warp_image(brain, torch.full((1, 3, *brain.shape[2:]), 1.5))  # the brain shifted: something to refine
    with torch.inference_mode():
        plain = network.posterior(moving, brain)
    same = bench.posterior_for(network, moving, brain, RefinementSettings(num_iterations=0))
    assert torch.equal(same.mean, plain.mean) and torch.equal(same.log_var, plain.log_var)
    refined = bench.posterior_for(network, moving, brain, RefinementSettings(num_iterations=3))
    assert torch.equal(refined.log_var, plain.log_var)  # the refinement moves the mean only
    assert (refined.mean - plain.mean).abs().max() > 1e-4


def test_main_calibrates_the_refined_mean_when_asked(tmp_path, tiny_dataset, single_thread, monkeypatch):
    from bench_helpers import REPO
    from conftest import bundle_with_random_model

    from monai_probreg.uncertainty.calibration import Calibration, load_calibration

    # random weights refined on a 16^3 blob leave some sampled spreads at 0, which no fit accepts: a fixed fit here
    monkeypatch.setattr(bench, "fit_calibration", lambda *args, **kwargs: Calibration(0.5, 0.1))

    bundle = bundle_with_random_model(tmp_path / "bundle", REPO / "bundle")
    out = tmp_path / "out"
    common = [
        "--dataset-dir",
        str(tiny_dataset),
        "--bundle-root",
        str(bundle),
        "--subjects",
        "T01",
        "T02",
        "--deformations",
        "1",
        "--samples",
        "2",
        "--probe",
        "noise",
        "--out-dir",
        str(out),
    ]
    assert bench.main([*common, "--refine", "2", "--write-calibration"]) == 0
    report = json.loads((out / "uncertainty_calibration.json").read_text())
    assert report["settings"]["refinement"]["num_iterations"] == 2
    # the sidecar records the refinement it was fitted around (summary.json compares a run's against it)
    assert load_calibration(bundle / "models" / "model.pt").refinement == report["settings"]["refinement"]
    with pytest.raises(SystemExit, match="--refine must be >= 0"):
        bench.main([*common, "--refine", "-1"])


def test_pooled_metrics_score_each_part_with_its_own_intervals():
    """Folds that fitted different dofs: each part's coverage is taken with its own intervals, then pooled by size.
    Errors of 2.5 std: outside the Gaussian 95% interval (1.96), inside the 3-dof one (3.18)."""
    std = [np.ones((3, 10)), np.ones((3, 30))]
    error = [2.5 * np.ones((3, 10)), 2.5 * np.ones((3, 30))]
    mixed = bench.pooled_metrics(std, error, [None, 3.0])
    assert mixed["coverage_95"] == pytest.approx(30 / 40) and mixed["interval_dof"] == [None, 3.0]
    same = bench.pooled_metrics(std, error, [3.0, 3.0])
    assert same["coverage_95"] == 1.0 and same["interval_dof"] == 3.0
