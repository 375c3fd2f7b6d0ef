"""The calibration benchmark's ground truth: the random deformation has the asked RMS and its stated inverse."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from bench_helpers import load_benchmark

from monai_probreg.blocks.warp import warp_image

bench = load_benchmark("uncertainty_calibration")


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


def test_main_writes_the_table_and_the_figures_and_no_sidecar(tmp_path, tiny_dataset, single_thread):
    """The benchmark measures; python -m monai_probreg.fitting writes the sidecar (tests/fitting/test_command.py)."""
    from bench_helpers import REPO
    from conftest import bundle_with_random_model

    from monai_probreg.fitting.subject_probe import SUBJECT_SEED

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
    assert all(c["std_scale"] > 0 and c["bias_fraction"] >= 0 for c in report["fold_calibrations"].values())
    assert not list((bundle / "models").glob("*.json"))  # measured only: no sidecar written
    assert set(report["summary"]["calibrated"]["coverage_by_level"]) == {"0.5", "0.68", "0.8", "0.9", "0.95"}
    assert report["settings"]["refinement"]["num_iterations"] == 0  # --refine 0: the network's own mean
    assert "Spearman of vectors (ceiling)" in report["markdown"]
    # the subject probe (default: the first training subjects; the tiny dataset has one, T03), fitted and held out
    probe = report["settings"]["subject_probe"]
    assert probe["templates"] == ["T03"] and probe["seeds"] == [SUBJECT_SEED]
    assert set(report["subjects"]) == {"T01", "T02"}
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


def test_main_calibrates_the_refined_mean_when_asked(tmp_path, tiny_dataset, single_thread, monkeypatch):
    from bench_helpers import REPO
    from conftest import bundle_with_random_model

    from monai_probreg.fitting import calibration_probes
    from monai_probreg.uncertainty.calibration import Calibration

    # random weights refined on a 16^3 blob leave some sampled spreads at 0, which no fit accepts: a fixed fit here
    monkeypatch.setattr(calibration_probes, "fit_calibration", lambda *args, **kwargs: Calibration(0.5, 0.1))

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
    assert bench.main([*common, "--refine", "2"]) == 0
    report = json.loads((out / "uncertainty_calibration.json").read_text())
    assert report["settings"]["refinement"]["num_iterations"] == 2
    assert set(report["fold_calibrations"]) == {"0", "1"}
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
