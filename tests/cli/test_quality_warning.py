"""The quality estimate on the command line: summary.json, the printed warning, the batch table; never the exit status.

The weights of the tiny bundle are random, so the quality model here is made by hand: all weights 0 and an intercept
that puts the failure probability near 1 (always warns) or near 0 (never warns). What is tested is the plumbing;
the estimate itself is tested in tests/uncertainty and scored by benchmarks/failure_detection.py.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import BUNDLE_DIR, FAST_AFFINE, FIXED_LPS, moved_phantom, run_cli, save_lps, tiny_bundle

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.uncertainty.quality import QualityModel, quality_path, save_quality_model
from monai_probreg.uncertainty.quality_features import QualityFeatures

N = len(QualityFeatures._fields)


def _quality_model(failure_intercept: float, entropy_calibration: dict | None = None) -> QualityModel:
    return QualityModel(
        list(QualityFeatures._fields),
        [-1e9] * N,
        [1e9] * N,
        [0.0] * N,
        [1.0] * N,
        [0.0] * N,
        0.61,
        [0.0] * N,
        failure_intercept,
        entropy_calibration=entropy_calibration or {},
    )


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("quality")
    case = moved_phantom([6.0, -4.0, 5.0], [2.0, -1.0, 1.5])
    bundle = tiny_bundle(root / "bundle", BUNDLE_DIR)
    s = SimpleNamespace(
        root=root,
        bundle=bundle,
        weights=bundle / "models" / "model.pt",
        fixed=save_lps(root / "fixed.nii.gz", case.image, FIXED_LPS),
        moving=save_lps(root / "moving.nii.gz", case.moved, case.grid),
    )
    s.common = ["--fixed", str(s.fixed), "--bundle-root", str(s.bundle), *FAST_AFFINE]
    return s


def _register(scene, out, failure_intercept: float, *extra: str, entropy_calibration: dict | None = None):
    save_quality_model(_quality_model(failure_intercept, entropy_calibration), scene.weights)
    try:
        return run_cli("register", "--moving", str(scene.moving), "--out", str(out), *scene.common, *extra)
    finally:
        quality_path(scene.weights).unlink()


def test_a_probable_failure_is_reported_but_the_run_succeeds(scene):
    out = scene.root / "warned"
    result = _register(scene, out, 20.0)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["warning"] and "probably failed" in summary["warning"]
    assert summary["quality"]["failure_probability"] > 0.99
    assert summary["quality"]["predicted_dice"] == pytest.approx(0.61)
    assert set(summary["quality"]["features"]) == set(QualityFeatures._fields)
    assert "quality" in summary["timings_s"]
    assert f"warning: {out}" in result.err and "probably failed" in result.err
    assert "predicted Dice 0.61" in result.out
    assert (out / "qc.png").is_file()


@pytest.mark.parametrize("precision", ["bf16", "fp32"])
def test_no_warning_for_a_probable_success(scene, precision):
    """In both arithmetics of the UNet: the random tiny network changes the pair by almost nothing, the local-NCC
    rule's edge, where bf16 rounding once warned (its margin, quality.LNCC_DROP_MARGIN, is what passes this). The
    network alone (--refine 0): a refinement on the tiny bundle's 16^3 grid, whose 9-voxel LNCC window is half the
    image, is no registration a user runs."""
    out = scene.root / f"fine_{precision}"
    result = _register(scene, out, -20.0, "--unet-precision", precision, "--refine", "0")
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["warning"] is None and summary["quality"]["failure_probability"] < 0.01
    assert "warning" not in result.err


def test_weights_without_a_quality_model_give_no_estimate(scene):
    out = scene.root / "none"
    result = run_cli("register", "--moving", str(scene.moving), "--out", str(out), "--no-qc", *scene.common)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["quality"] is None and summary["warning"] is None and "quality" not in summary["timings_s"]


def _stale_quality_model(weights) -> Path:
    """A quality sidecar next to ``weights`` stamped with another SHA-256 (fitted for other weights); its path."""
    save_quality_model(_quality_model(0.0), weights)
    path = quality_path(weights)
    record = json.loads(path.read_text())
    record["weights_sha256"] = "0" * 64
    path.write_text(json.dumps(record))
    return path


def test_a_quality_model_of_other_weights_is_refused(scene, tmp_path):
    path = _stale_quality_model(scene.weights)
    try:
        result = run_cli("register", "--moving", str(scene.moving), "--out", str(tmp_path / "o"), *scene.common)
    finally:
        path.unlink()
    assert result.rc == 1 and "refit" in result.err and "--model-file" in result.err


def test_the_batch_lists_the_warning_and_the_scan_stays_ok(scene, tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(scene.moving, scans / "A.nii.gz")
    save_quality_model(_quality_model(20.0), scene.weights)
    try:
        result = run_cli(
            "register-batch", "--moving", str(scans), "--out", str(tmp_path / "out"), "--no-qc", *scene.common
        )
    finally:
        quality_path(scene.weights).unlink()
    assert result.rc == 0, result.err
    row = next(csv.DictReader((tmp_path / "out" / "batch_summary.csv").open()))
    assert row["status"] == "ok" and "probably failed" in row["warning"]
    assert float(row["failure_probability"]) > 0.99 and float(row["predicted_dice"]) == pytest.approx(0.61)
    assert "WARNING" in result.out


def test_load_model_can_leave_a_stale_quality_model_out(scene):
    """python -m monai_probreg.fitting fits a new quality model with the command line's loading: a stale one must not
    stop it."""
    from monai_probreg.registration.model import load_model
    from monai_probreg.utils.errors import InputError

    path = _stale_quality_model(scene.weights)
    try:
        with pytest.raises(InputError, match="refit"):
            load_model(scene.bundle)
        assert load_model(scene.bundle, quality=False).quality is None
    finally:
        path.unlink()
    assert load_model(scene.bundle).quality is None  # no sidecar: none either way


def test_with_refinement_the_estimate_reads_the_networks_registration(scene):
    """quality.py, "Whose features": with --refine the features are those of the network's own registration (the
    same as with --refine 0) and the refined answer's are stored beside them; without, there is no second set."""
    summaries = {}
    for steps in ("0", "3"):
        out = scene.root / f"witness_{steps}"
        result = _register(scene, out, -20.0, "--refine", steps, "--no-qc")
        assert result.rc == 0, result.err
        summaries[steps] = json.loads((out / "summary.json").read_text())["quality"]
    network, refined = summaries["0"], summaries["3"]
    assert network["answer_features"] is None
    assert refined["features"] == pytest.approx(network["features"], abs=1e-6)
    assert refined["answer_features"] is not None
    assert refined["answer_features"]["displacement_mm"] != pytest.approx(refined["features"]["displacement_mm"])
    # the hand-made quality model records no refinement (fitted on the network's own registrations)
    assert network["refinement_differs_from_fit"] == {}
    run = json.loads((scene.root / "witness_3" / "summary.json").read_text())["model"]["refinement"]
    expected = {k: [v, run[k]] for k, v in RefinementSettings().as_dict().items() if run[k] != v}
    assert refined["refinement_differs_from_fit"] == expected and expected["num_iterations"] == [0, 3]


@pytest.mark.parametrize("steps", ["0", "3"])
def test_the_entropy_feature_takes_the_quality_models_own_calibration(scene, steps):
    """A quality model that records the calibration of its fit's entropy gets the entropy under it, not under the
    calibration in use (the tiny bundle's is raw): scaling every velocity std by 0.5 lowers the mean velocity entropy
    by exactly 3 log 2 nats (three components), and leaves every other feature and the uncertainty maps as they were."""
    results = {}
    for name, calibration in (("in_use", None), ("halved", {"std_scale": 0.5, "bias_fraction": 0.0})):
        out = scene.root / f"entropy_{name}_{steps}"
        result = _register(scene, out, -20.0, "--refine", steps, "--no-qc", entropy_calibration=calibration)
        assert result.rc == 0, result.err
        results[name] = json.loads((out / "summary.json").read_text())
    in_use, halved = (results[n]["quality"]["features"] for n in ("in_use", "halved"))
    assert halved["entropy"] == pytest.approx(in_use["entropy"] - 3 * math.log(2), abs=1e-4)
    assert {k: v for k, v in halved.items() if k != "entropy"} == pytest.approx(
        {k: v for k, v in in_use.items() if k != "entropy"}, abs=1e-6
    )
    assert results["halved"]["uncertainty"] == results["in_use"]["uncertainty"]
    if steps != "0":  # the refined answer's features follow the same rule (summary.json matches the bundle's record)
        answers = [results[n]["quality"]["answer_features"]["entropy"] for n in ("in_use", "halved")]
        assert answers[1] == pytest.approx(answers[0] - 3 * math.log(2), abs=1e-4)


def test_the_raw_posterior_keeps_an_estimate_that_records_its_calibration(scene):
    """--raw-uncertainty: a quality model that records its entropy's calibration still estimates, with that
    calibration (halved std: 3 log 2 nats below the raw entropy); one that does not was fitted on the calibrated
    posterior and is left out."""
    summaries = {}
    for name, extra, recorded in (
        ("raw_recorded", ["--raw-uncertainty"], {"std_scale": 0.5, "bias_fraction": 0.0}),
        ("raw_unrecorded", ["--raw-uncertainty"], None),
        ("in_use", [], None),  # the tiny bundle has no calibration sidecar: the calibration in use is the raw one
    ):
        out = scene.root / name
        result = _register(scene, out, 20.0, *extra, "--refine", "0", "--no-qc", entropy_calibration=recorded)
        assert result.rc == 0, result.err
        summaries[name] = json.loads((out / "summary.json").read_text())
    assert summaries["raw_unrecorded"]["quality"] is None and summaries["raw_unrecorded"]["warning"] is None
    recorded = summaries["raw_recorded"]
    assert recorded["warning"]  # this hand-made model always warns
    entropy = summaries["in_use"]["quality"]["features"]["entropy"]
    assert recorded["quality"]["features"]["entropy"] == pytest.approx(entropy - 3 * math.log(2), abs=1e-4)


def test_a_pair_of_two_contrasts_gets_no_estimate_and_says_why(scene):
    """--contrast other: the models (fitted on pairs of one contrast, another contrast among their failures) are not
    applied, even one that always warns: no stage, "quality": null, no warning; summary.json and the printed line
    say why. With --contrast same the same model warns (the test above)."""
    from monai_probreg.registration.quality_estimate import NO_QUALITY_OTHER_CONTRAST

    out = scene.root / "other_contrast"
    result = _register(scene, out, 20.0, "--contrast", "other")
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["quality"] is None and summary["warning"] is None
    assert summary["quality_not_estimated"] == NO_QUALITY_OTHER_CONTRAST
    assert summary["model"]["contrast"] == "other"
    assert "quality" not in summary["timings_s"]
    assert "warning:" not in result.err
    assert "no quality estimate (--contrast other)" in result.out


def test_weights_without_a_quality_model_say_so(scene):
    from monai_probreg.registration.quality_estimate import NO_QUALITY_MODEL

    out = scene.root / "no_model"
    result = run_cli("register", "--moving", str(scene.moving), "--out", str(out), *scene.common)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["quality"] is None
    assert summary["quality_not_estimated"] == f"{NO_QUALITY_MODEL}: no model.quality.json beside {scene.weights}"
    assert summary["model"]["contrast"] == "same" and summary["warning"] is None
    assert "no quality estimate (no quality model)" in result.out
