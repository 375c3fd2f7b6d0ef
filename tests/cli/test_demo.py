"""``monai-probreg demo`` (and the bundle's demo.yaml) end to end on a small template, with a random-weights model:
the pipeline, the scores and the files, not the shipped model's accuracy (README: the demo on the MNI template)."""

from __future__ import annotations

import json
from pathlib import Path

import itk
import nibabel as nib
import numpy as np
import pytest
from conftest import BUNDLE_DIR, FAST_AFFINE, FIXED_LPS, asymmetric_phantom, run_cli, save_lps, tiny_bundle
from monai.bundle import ConfigParser

from monai_probreg.registration.output_files import OUTPUT_FILES
from monai_probreg.spatial.volume_io import read_image
from monai_probreg.uncertainty.calibration import calibration_path, save_calibration

EXPECTED = {
    "warped.nii.gz",
    "warp.nii.gz",
    "inverse_warp.nii.gz",
    "affine.tfm",
    "jacobian.nii.gz",
    "entropy.nii.gz",
    "displacement_std.nii.gz",
    "subject.nii.gz",
    "true_warp.nii.gz",
    "qc.png",
    "summary.json",
    "README.txt",
}


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("demo")
    image, labels = asymmetric_phantom((40, 44, 36))
    template = np.where(labels > 0, np.clip(image, 0.05, None) * 200, 0).astype(np.float32)  # skull-stripped
    path = save_lps(root / "template.nii.gz", template, FIXED_LPS @ np.diag([1.5, 1.5, 1.5, 1.0]))
    bundle = tiny_bundle(root / "bundle", BUNDLE_DIR)
    return root, path, bundle


def _demo(setup, out: Path, *extra: str):
    _root, template, bundle = setup
    return run_cli(
        "demo",
        "--fixed",
        str(template),
        "--out",
        str(out),
        "--bundle-root",
        str(bundle),
        "--samples",
        "2",
        *FAST_AFFINE,
        *extra,
    )


@pytest.fixture(scope="module")
def result(setup):
    out = setup[0] / "out"
    run = _demo(setup, out, "--seed", "3")
    assert run.rc == 0, run.err
    return out, run, json.loads((out / "summary.json").read_text())


def test_the_demo_scores_the_registration_against_the_known_transform(result):
    _out, run, summary = result
    demo = summary["demo"]
    assert demo["seed"] == 3 and demo["before"]["median_mm"] > 2.0
    # random weights deform almost nothing: the gain is the affine stage's (the rigid part of the truth), and what
    # is left is about the drawn deformation
    assert demo["after"]["median_mm"] < demo["before"]["median_mm"] - 1.0
    assert demo["after"]["median_mm"] == pytest.approx(demo["affine_only"]["median_mm"], abs=0.3)
    assert 0.0 <= demo["coverage"] <= 1.0 and demo["coverage_level"] == 0.95
    assert demo["truth_inverse_error_mm"] < 0.1  # a tenth of a millimetre on 1.5 mm voxels
    assert "after registration" in run.out and "interval" in run.out


def test_the_coverage_reads_the_calibrations_intervals(result, setup):
    """The same seed with a sidecar whose intervals are Student-t with 1 dof (std_scale 1, as the raw posterior): the
    same registration and std, scored with the wider Cauchy intervals (12.7 std at 95%, not 1.96)."""
    out, _, gaussian = result
    weights = setup[2] / "models" / "model.pt"
    save_calibration(weights, 1.0, interval_dof=1.0)
    try:
        run = _demo(setup, out.with_name("out_cauchy"), "--seed", "3")
        assert run.rc == 0, run.err
        cauchy = json.loads((out.with_name("out_cauchy") / "summary.json").read_text())
    finally:
        calibration_path(weights).unlink()
    assert gaussian["demo"]["interval_dof"] is None and cauchy["demo"]["interval_dof"] == 1.0
    assert cauchy["model"]["posterior_interval_dof"] == 1.0 and gaussian["model"]["posterior_interval_dof"] is None
    assert cauchy["model"]["posterior_interval_95_half_width_std"] == pytest.approx(12.7062, abs=1e-4)  # tan(0.475 pi)
    assert gaussian["model"]["posterior_interval_95_half_width_std"] == pytest.approx(1.96, abs=1e-4)
    assert cauchy["demo"]["after"] == gaussian["demo"]["after"]
    assert "interval (Student-t, 1 dof): covers" in run.out and "interval: covers" not in run.out
    assert cauchy["demo"]["coverage"] > gaussian["demo"]["coverage"]


def test_the_outputs_are_complete_and_read_by_itk(result):
    out, _, summary = result
    assert {p.name for p in out.iterdir()} == EXPECTED
    assert set(summary["outputs"]) == EXPECTED and EXPECTED <= set(OUTPUT_FILES)
    for name in EXPECTED:
        if name.endswith(".nii.gz"):  # ITK sizes are index order; the subject (the moving grid) is stored as "PIR"
            size = tuple(itk.imread(str(out / name)).GetLargestPossibleRegion().GetSize())
            moving_grid = name in ("subject.nii.gz", "inverse_warp.nii.gz")
            assert size == ((44, 36, 40) if moving_grid else (40, 44, 36)), name
    assert read_image(out / "subject.nii.gz", "subject").axcodes == "PIR"
    assert summary["moving"]["path"] == str((out / "subject.nii.gz").resolve())


def test_the_true_warp_file_holds_the_scored_truth(result, setup):
    out, _, summary = result
    truth, warp = (np.asarray(nib.load(out / name).dataobj) for name in ("true_warp.nii.gz", "warp.nii.gz"))
    assert truth.shape == warp.shape == (40, 44, 36, 1, 3)  # ITK's vector layout, as warp.nii.gz
    brain = read_image(setup[1], "template").array > 0
    norms = np.linalg.norm(truth[:, :, :, 0], axis=-1)[brain]
    assert np.median(norms) == pytest.approx(summary["demo"]["before"]["median_mm"], abs=1e-3)
    errors = np.linalg.norm(warp[:, :, :, 0] - truth[:, :, :, 0], axis=-1)[brain]
    assert np.median(errors) == pytest.approx(summary["demo"]["after"]["median_mm"], abs=1e-3)


def test_without_samples_there_is_no_coverage(setup):
    out = setup[0] / "no_samples"
    run = run_cli(
        "demo",
        "--fixed",
        str(setup[1]),
        "--out",
        str(out),
        "--bundle-root",
        str(setup[2]),
        "--samples",
        "0",
        "--no-qc",
        "--no-inverse",
        *FAST_AFFINE,
    )
    assert run.rc == 0, run.err
    assert json.loads((out / "summary.json").read_text())["demo"]["coverage"] is None
    assert "needs --samples" in run.out


def test_a_missing_template_is_an_error_and_writes_nothing(setup):
    out = setup[0] / "missing"
    run = run_cli("demo", "--fixed", str(setup[0] / "nope.nii.gz"), "--out", str(out))
    assert run.rc == 1 and "--fixed" in run.err and "no such file" in run.err and not out.exists()


def test_the_bundle_config_runs_the_same_demo(setup, result):
    root, template, bundle = setup
    out = root / "bundle_out"
    parser = ConfigParser()
    parser.read_config(str(BUNDLE_DIR / "configs" / "demo.yaml"))
    parser.update({"bundle_root": str(bundle), "out_dir": str(out), "template": str(template), "seed": 3, "samples": 2})
    parser.get_parsed_content("run")
    ours = json.loads((out / "summary.json").read_text())["demo"]
    assert ours["seed"] == 3 and ours["before"] == result[2]["demo"]["before"]  # the same subject was drawn
    assert ours["after"]["median_mm"] < ours["before"]["median_mm"]
