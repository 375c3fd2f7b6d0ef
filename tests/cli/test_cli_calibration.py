"""The command line applies the calibration stored next to the weights by default; --raw-uncertainty turns it off;
a sidecar fitted for other weights is refused with a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import FIXED_LPS, asymmetric_phantom, save_lps, tiny_bundle

from monai_probreg.cli.main import main
from monai_probreg.spatial.volume_io import read_image
from monai_probreg.uncertainty.calibration import calibration_path, save_calibration
from monai_probreg.uncertainty.error_model import ERROR_FEATURES
from monai_probreg.uncertainty.residual import residual_form

BUNDLE = Path(__file__).resolve().parents[2] / "bundle"
SCALE = 4.0
BIAS_FRACTION = 2000.0  # large: the random network's mean velocity is ~5e-4 of its posterior std
RESIDUAL_WEIGHT = 1e4  # large: the random network's posterior variance is ~1e-3 velocity voxels^2


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_calibration")
    image, _ = asymmetric_phantom()
    bundle = tiny_bundle(root / "bundle", BUNDLE)
    weights = bundle / "models" / "model.pt"  # the configs' default model_file
    save_calibration(weights, SCALE, ["synthetic"], 2)
    fixed = save_lps(root / "fixed.nii.gz", image.astype(np.float32), FIXED_LPS)
    moving = save_lps(root / "moving.nii.gz", (image * 400 + 20).astype(np.float32), FIXED_LPS)
    return root, bundle, weights, fixed, moving


def _register(scene, name: str, *extra: str, moving: Path | None = None) -> tuple[int, dict, np.ndarray]:
    root, bundle, _, fixed, scene_moving = scene
    moving = moving or scene_moving
    out = root / name
    threads = torch.get_num_threads()
    try:
        rc = main(
            [
                "register",
                "--moving",
                str(moving),
                "--fixed",
                str(fixed),
                "--bundle-root",
                str(bundle),
                "--out",
                str(out),
                "--no-affine",
                "--no-qc",
                "--samples",
                "4",
                "--threads",
                "1",
                "--quiet",
                *extra,
            ]
        )
    finally:
        torch.set_num_threads(threads)
    if rc != 0:
        return rc, {}, np.zeros(0)
    summary = json.loads((out / "summary.json").read_text())
    return rc, summary, read_image(out / "displacement_std.nii.gz").array


def test_calibrated_by_default_raw_on_request(scene):
    rc, summary, calibrated = _register(scene, "calibrated")
    assert rc == 0 and summary["model"]["posterior_std_scale"] == SCALE
    # this sidecar was fitted around the network's mean ({}); the run refines as the configs do by default
    assert summary["model"]["calibration_refinement_differs_from_fit"] == {
        "num_iterations": [0, 20],
        "learning_rate": [0.1, 0.06],  # the shipped 0.3 on the tiny bundle's 16^3 grid (conftest.tiny_bundle)
        "posterior_weight": [1.0, 0.25],
        "image_grid_factor": [1, 2],
        "coarse_iterations": [0, 18],
        "similarity_guard": [False, True],
    }
    rc, summary, raw = _register(scene, "raw", "--raw-uncertainty")
    assert rc == 0 and summary["model"]["posterior_std_scale"] == 1.0
    assert summary["model"]["calibration_refinement_differs_from_fit"] is None
    weights = scene[2]
    fitted = summary["model"]["refinement"]  # the configs' default refinement
    save_calibration(weights, SCALE, ["synthetic"], 2, refinement=fitted)
    try:
        rc, summary, _ = _register(scene, "calibrated_around_this")
        assert rc == 0 and summary["model"]["calibration_refinement_differs_from_fit"] == {}
        rc, summary, _ = _register(scene, "network_alone", "--refine", "0")
        assert rc == 0 and summary["model"]["calibration_refinement_differs_from_fit"] == {
            "num_iterations": [20, 0],
            "coarse_iterations": [18, 0],
        }
    finally:
        save_calibration(weights, SCALE, ["synthetic"], 2)
    # the first-order map, std scaled by 4 in velocity: the displacement std grows by 4 (the interpolation of the
    # written map onto the scan's grid apart)
    ratio = np.median(calibrated[raw > 0] / raw[raw > 0])
    assert ratio == pytest.approx(SCALE, rel=0.02)


def test_sidecar_of_other_weights_is_refused(scene, capsys):
    _, _, weights, _, _ = scene
    record = calibration_path(weights).read_text()
    try:
        calibration_path(weights).write_text(record.replace('"weights_sha256": "', '"weights_sha256": "0'))
        rc, _, _ = _register(scene, "mismatch")
        assert rc != 0
        assert "SHA-256" in capsys.readouterr().err
    finally:
        calibration_path(weights).write_text(record)


def test_bias_fraction_reaches_the_written_maps(scene):
    """A sidecar with a bias fraction (std_scale 1): the summary records it and the displacement std widens where
    the random network's mean velocity is long (the same map otherwise). The network's mean, not refined:
    on this scene the similarity guard gives the refined deformation up (a zero mean, nothing to widen)."""
    _, _, weights, _, _ = scene
    record = calibration_path(weights).read_text()
    try:
        save_calibration(weights, 1.0, ["synthetic"], 2, bias_fraction=BIAS_FRACTION)
        rc, summary, biased = _register(scene, "biased", "--refine", "0")
        assert rc == 0 and summary["model"]["posterior_bias_fraction"] == BIAS_FRACTION
        assert summary["model"]["posterior_std_scale"] == 1.0
    finally:
        calibration_path(weights).write_text(record)
    rc, _, raw = _register(scene, "raw_for_bias", "--raw-uncertainty", "--refine", "0")
    assert rc == 0
    inside = raw > 0
    assert np.median(biased[inside] / raw[inside]) > 1.2


def test_the_residual_term_reaches_the_written_maps(scene):
    """A sidecar with a residual weight (std_scale 1): the summary records it, and the displacement std widens where
    the registered images differ (the same map otherwise; the network's mean, as above)."""
    root, _, weights, _, _ = scene
    image, _ = asymmetric_phantom()
    unlike = image.astype(np.float32).copy()
    half = unlike.shape[0] // 2
    unlike[:half] = unlike[:half].max() - unlike[:half]  # the first half of axis 0 inverted: unlike the fixed image
    moving = save_lps(root / "unlike.nii.gz", unlike, FIXED_LPS)
    record = calibration_path(weights).read_text()
    try:
        save_calibration(weights, 1.0, ["synthetic"], 2, residual_weight=RESIDUAL_WEIGHT)
        rc, summary, widened = _register(scene, "residual", "--refine", "0", moving=moving)
        assert rc == 0 and summary["model"]["posterior_residual_weight"] == RESIDUAL_WEIGHT
        assert summary["model"]["posterior_residual_form"] == residual_form()
        assert summary["model"]["posterior_term"] == "residual"
        assert summary["model"]["displacement_std"] == "first order"
    finally:
        calibration_path(weights).write_text(record)
    rc, summary, raw = _register(scene, "raw_for_residual", "--raw-uncertainty", "--refine", "0", moving=moving)
    assert rc == 0 and summary["model"]["posterior_residual_weight"] == 0.0
    assert summary["model"]["posterior_residual_form"] is None and summary["model"]["posterior_term"] is None
    inside = raw > 0
    assert np.median(widened[inside] / raw[inside]) > 1.2


def test_an_error_model_reaches_the_written_maps(scene):
    """A sidecar with an error model: the summary says the term reads it, and the std follows its prediction: an
    error model of the fixed intensity alone (exp(4 intensity)) widens the posterior where the fixed image is bright
    against one of the intercept alone, the same map otherwise."""
    root, _, weights, _, _ = scene
    names = list(ERROR_FEATURES)
    bright = [0.0] * (len(names) + 1)
    bright[names.index("fixed intensity")] = 4.0
    flat = [0.0] * (len(names) + 1)
    record = calibration_path(weights).read_text()
    stds = {}
    try:
        for name, model in (("bright", bright), ("flat", flat)):
            save_calibration(weights, 1.0, ["synthetic"], 2, residual_weight=RESIDUAL_WEIGHT, error_model=model)
            rc, summary, stds[name] = _register(scene, f"error_model_{name}", "--refine", "0")
            assert rc == 0 and summary["model"]["posterior_term"] == "error model"
    finally:
        calibration_path(weights).write_text(record)
    image, _ = asymmetric_phantom()
    ratio = stds["bright"] / np.maximum(stds["flat"], 1e-12)
    inside = stds["flat"] > 0
    brightest = inside & (image >= np.percentile(image[inside], 90))
    darkest = inside & (image <= np.percentile(image[inside], 10))
    assert np.median(ratio[brightest]) > 1.2 * np.median(ratio[darkest])


def test_student_t_intervals_are_recorded_and_raw_on_request_is_gaussian(scene):
    """A sidecar with Student-t intervals (3 dof): the summary records the dof and the 95% half-width (3.18 std);
    --raw-uncertainty gives the raw posterior's Gaussian intervals (1.96)."""
    _, _, weights, _, _ = scene
    record = calibration_path(weights).read_text()
    try:
        save_calibration(weights, SCALE, ["synthetic"], 2, interval_dof=3.0)
        rc, summary, _ = _register(scene, "student_t")
        assert rc == 0 and summary["model"]["posterior_interval_dof"] == 3.0
        assert summary["model"]["posterior_interval_95_half_width_std"] == pytest.approx(3.1824, abs=1e-4)
        rc, summary, _ = _register(scene, "student_t_raw", "--raw-uncertainty")
        assert rc == 0 and summary["model"]["posterior_interval_dof"] is None
        assert summary["model"]["posterior_interval_95_half_width_std"] == pytest.approx(1.96, abs=1e-4)
    finally:
        calibration_path(weights).write_text(record)
