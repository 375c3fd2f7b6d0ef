"""python -m monai_probreg.fitting: both sidecars from one command (a tiny bundle, random weights), nothing written by a
run stopped part-way, which ``--resume`` goes on from; each argument that cannot be used refused in one line."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import BUNDLE_DIR, make_tiny_dataset, tiny_bundle

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting import command, stages
from monai_probreg.fitting.calibration_probes import RESIDUAL_WEIGHTS, SUBJECT_PROBE_TEMPLATES
from monai_probreg.fitting.error_cases import ERROR_MODEL_TEMPLATES
from monai_probreg.fitting.subject_probe import SUBJECT_SEED
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.error_model import ERROR_FEATURES

REPO = Path(__file__).resolve().parents[2]
LPBA40 = REPO.parent / "shared" / "data" / "lpba40"
ERROR = "python -m monai_probreg.fitting: error: "


def fitting_bundle(root: Path) -> Path:
    """:func:`tiny_bundle` (the UNet at 16^3, which evaluate.yaml inherits from inference.yaml) whose evaluate.yaml
    registers on the network's own mean (random weights refined on a 16^3 blob leave sampled spreads at 0, which no
    calibration fit accepts), while inference.yaml (the subject probe and the whole-command cases) refines 2 steps."""
    tiny_bundle(root, BUNDLE_DIR)
    inference = root / "configs" / "inference.yaml"
    inference.write_text(re.sub(r"^refine_iterations: \d+", "refine_iterations: 2", inference.read_text(), flags=re.M))
    evaluate = root / "configs" / "evaluate.yaml"
    evaluate.write_text(evaluate.read_text() + "refine_iterations: 0\n")  # an overlay's override, as a user writes it
    return root


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A dataset of 4 subjects (T01, T02 validation; T03, T04 train) and the fitting bundle, read only."""
    root = tmp_path_factory.mktemp("fitting")
    return make_tiny_dataset(root / "data", num_subjects=4, shape=(32, 36, 28)), fitting_bundle(root / "bundle")


def arguments(dataset: Path, bundle: Path, out: Path, *extra: str) -> list[str]:
    """The smallest fit: 2 validation subjects, 1 deformation, 2 samples, 1 subject-probe template, 1 training
    subject of the quality model."""
    return [
        *("--dataset-dir", str(dataset), "--bundle-root", str(bundle), "--subjects", "T01", "T02"),
        *("--deformations", "1", "--samples", "2", "--subject-probe", "1", "--train-subjects", "1"),
        *("--out-dir", str(out), *extra),
    ]


def test_one_command_writes_both_sidecars_and_a_stopped_run_resumes(setup, tmp_path, monkeypatch, single_thread):
    dataset, bundle = setup
    out = tmp_path / "sidecars"
    weights = bundle / "models" / "model.pt"

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:  # stopped after the calibration: nothing is written, its fit is logged
        patch.setattr(command, "fit_quality_stage", stopped)
        assert command.main(arguments(dataset, bundle, out)) == 130
    assert not list(out.glob("*.json")) and not list(weights.parent.glob("*.json"))
    logged = json.loads((out / "model.fitting" / stages.CALIBRATION_LOG).read_text())
    assert logged["header"]["subjects"] == ["T01", "T02"] and logged["header"]["training_subjects"] == ["T03", "T04"]

    def registered_again(*args, **kwargs):
        raise AssertionError("the logged calibration was fitted again")

    monkeypatch.setattr(stages, "calibration_probes", registered_again)
    assert command.main(arguments(dataset, bundle, out, "--resume")) == 0

    calibration = json.loads((out / "model.calibration.json").read_text())
    quality = json.loads((out / "model.quality.json").read_text())
    assert not (out / "model.fitting").exists()  # the logs go once the sidecars are whole
    assert not list(weights.parent.glob("*.json"))  # --out-dir: the weights' folder untouched
    # the calibration: a two-number fit (and its dof) on both probes, around the network's mean (evaluate.yaml), with
    # the residual term's weight chosen among the fit's
    assert calibration["std_scale"] > 0 and 0 <= calibration["bias_fraction"] < float("inf")
    assert calibration["residual_weight"] in RESIDUAL_WEIGHTS
    assert calibration["interval_dof"] is None or calibration["interval_dof"] > 0
    assert calibration["fitted_on"] == ["T01", "T02", f"T03 (subject probe, seed {SUBJECT_SEED})"]
    assert calibration["num_samples"] == 2 and calibration["refinement"] == {}
    # the error model: fitted first, on the training subject after the subject probe's (T04), for the package's features
    assert len(calibration["error_model"]) == len(ERROR_FEATURES) + 1
    assert calibration["error_features"] == list(ERROR_FEATURES)
    assert logged["header"]["error_model_templates"] == ERROR_MODEL_TEMPLATES
    # the quality model: fitted on the training subject, its entropy feature under the calibration just fitted
    assert quality["fitted_on"] == ["T03"]
    assert quality["entropy_calibration"] == {k: calibration[k] for k in ("std_scale", "bias_fraction")}
    assert quality["weights_sha256"] == calibration["weights_sha256"] == logged["header"]["weights_sha256"]
    # next to the weights, the command line uses both
    from monai_probreg.registration.model import load_model

    for sidecar in out.glob("*.json"):
        shutil.copy(sidecar, weights.parent / sidecar.name)
    model = load_model(bundle)
    assert (model.std_scale, model.bias_fraction) == (calibration["std_scale"], calibration["bias_fraction"])
    assert model.quality is not None and model.quality.fitted_on == ["T03"]


def test_the_sidecars_record_the_refinement_they_were_fitted_for(tmp_path):
    weights = tmp_path / "model.pt"
    torch.save({"w": torch.zeros(1)}, weights)
    fitted = stages.FittedCalibration(Calibration(1.2, 0.1, 3.0), ["S11", "S12 (subject probe, seed 1000)"], 16)
    refinement = RefinementSettings(num_iterations=10)
    written = stages.write_sidecars(weights, tmp_path / "out", fitted, None, refinement)
    assert written == [tmp_path / "out" / "model.calibration.json"]
    record = json.loads(written[0].read_text())
    assert record["refinement"] == refinement.as_dict() and record["interval_dof"] == 3.0
    assert (record["std_scale"], record["bias_fraction"], record["num_samples"]) == (1.2, 0.1, 16)
    none = stages.write_sidecars(weights, tmp_path / "raw", fitted, None, RefinementSettings(num_iterations=0))
    assert json.loads(none[0].read_text())["refinement"] == {}  # the network's own mean


BAD = {  # name: (arguments replacing the good ones, the message expected)
    "no deformation": (["--deformations", "0"], "--deformations: expected 1 to 100, got 0"),
    "beyond the seed stride": (["--deformations", "101"], "--deformations: expected 1 to 100, got 101"),
    "one sample": (["--samples", "1"], "--samples: expected >= 2, got 1"),
    "negative subject probe": (["--subject-probe", "-1"], "--subject-probe: expected >= 0, got -1"),
    "negative error-model templates": (
        ["--error-model-templates", "-1"],
        "--error-model-templates: expected >= 0, got -1",
    ),
    "no training subject": (["--train-subjects", "0"], "--train-subjects: expected >= 1, got 0"),
    "no thread": (["--threads", "0"], "--threads: expected >= 1, got 0"),
    "missing dataset": (["--dataset-dir", "{tmp}/nowhere"], "--dataset-dir '{tmp}/nowhere': expected a dataset folder"),
    "missing native folder": (["--native-dir", "{tmp}/nowhere"], "--native-dir '{tmp}/nowhere': expected a folder"),
    "output folder is a file": (["--out-dir", "{tmp}/file"], "--out-dir '{tmp}/file': expected a folder, got a file"),
    "work folder is a file": (["--work-dir", "{tmp}/file"], "--work-dir '{tmp}/file': expected a folder, got a file"),
    "bundle without configs": (["--bundle-root", "{tmp}"], "--bundle-root '{tmp}': expected a bundle with configs/"),
    "missing weights": (["--model-file", "{tmp}/no.pt"], "--model-file '{tmp}/no.pt': expected a weights file"),
    "not weights": (["--model-file", "{tmp}/file"], "--model-file '{tmp}/file': "),
    "other weights": (
        ["--model-file", "{tmp}/other.pt"],
        "--model-file '{tmp}/other.pt': expected weights of evaluate",
    ),
    "unknown subject": (
        ["--subjects", "T01", "T09"],
        "--subjects: expected labelled subjects of '{data}', got ['T09']",
    ),
    "all subjects validation": (
        ["--subjects", "T01", "T02", "T03", "T04"],
        "--dataset-dir '{data}': expected training subjects besides",
    ),
}


@pytest.mark.parametrize("name", list(BAD))
def test_an_argument_that_cannot_be_used_is_refused_in_one_line(setup, tmp_path, capsys, name):
    dataset, bundle = setup
    (tmp_path / "file").write_bytes(b"not what was asked for")
    torch.save({"weight": torch.zeros(1)}, tmp_path / "other.pt")  # a state dict, of another network
    replace, expected = BAD[name]
    replace = [a.format(tmp=tmp_path, data=dataset) for a in replace]
    argv = arguments(dataset, bundle, tmp_path / "out")
    for option in [a for a in replace if a.startswith("--")]:  # the good value out, the bad one in
        at = argv.index(option) if option in argv else None
        if at is not None:
            end = next((i for i in range(at + 1, len(argv)) if argv[i].startswith("--")), len(argv))
            del argv[at:end]
    assert command.main([*argv, *replace]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(ERROR) and "\n" not in err
    assert expected.format(tmp=tmp_path, data=dataset) in err
    assert not (tmp_path / "out").exists()  # nothing written


def test_an_unreadable_log_is_refused_on_resume(setup, tmp_path, capsys):
    dataset, bundle = setup
    log = tmp_path / "work" / stages.CALIBRATION_LOG
    log.parent.mkdir()
    log.write_text("{")
    argv = arguments(dataset, bundle, tmp_path / "out", "--work-dir", str(tmp_path / "work"), "--resume")
    assert command.main(argv) == 1
    assert (
        f"{log}: expected a log of registrations (header and records), got an unreadable file"
        in capsys.readouterr().err
    )


def test_only_quality_refuses_a_calibration_of_other_weights(setup, tmp_path, capsys):
    """--only quality computes the entropy feature with the weights' calibration sidecar: a stale one is refused."""
    dataset, bundle = setup
    weights = tmp_path / "model.pt"
    shutil.copy(bundle / "models" / "model.pt", weights)
    stale = {"std_scale": 1.0, "weights_file": "model.pt", "weights_sha256": "0" * 64}
    (tmp_path / "model.calibration.json").write_text(json.dumps(stale))
    argv = arguments(dataset, bundle, tmp_path / "out", "--model-file", str(weights), "--only", "quality")
    assert command.main(argv) == 1
    err = capsys.readouterr().err
    assert "--only quality:" in err and "fitted for weights with SHA-256 000000000000" in err
    assert "refit the calibration too" in err


def test_the_module_runs_as_a_command(tmp_path):
    missing = tmp_path / "no_such_dataset"
    done = subprocess.run(
        [sys.executable, "-m", "monai_probreg.fitting", "--dataset-dir", str(missing)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 1
    assert (
        done.stderr.strip() == f"{ERROR}--dataset-dir {str(missing)!r}: expected a dataset folder, got no such folder"
    )


def test_the_defaults_are_the_settings_of_the_shipped_sidecars():
    """A refit with the defaults fits the shipped sidecars' cases: the calibration on train.yaml's validation subjects
    and the subject probe of the first training subjects (seeds 1000 on), 16 samples; the quality model on the first
    12 training subjects; both for evaluate.yaml's refinement (real data: skipped without LPBA40)."""
    if not LPBA40.is_dir():
        pytest.skip(f"LPBA40 not found at {LPBA40}")
    from monai_probreg.data.dataset import index_dataset

    parser = command.build_parser()
    args = parser.parse_args(["--dataset-dir", str(LPBA40)])
    models = REPO / "bundle" / "models"
    calibration = json.loads((models / "model.calibration.json").read_text())
    quality = json.loads((models / "model.quality.json").read_text())
    val_ids = [str(i) for i in stages.bundle_parser(REPO / "bundle", ["train.yaml"]).get_parsed_content("val_ids")]
    training = [i for i in index_dataset(LPBA40).ids if i not in val_ids]
    probe = [f"{t} (subject probe, seed {SUBJECT_SEED + n})" for n, t in enumerate(training[:SUBJECT_PROBE_TEMPLATES])]
    assert args.subject_probe == SUBJECT_PROBE_TEMPLATES and calibration["fitted_on"] == val_ids + probe
    assert calibration["num_samples"] == args.samples
    assert quality["fitted_on"] == training[: args.train_subjects]
    shipped = stages.bundle_parser(REPO / "bundle", ["evaluate.yaml"]).get_parsed_content("refinement")
    # each fitted around evaluate.yaml's refinement (a record made before a setting existed ran its default:
    # RefinementSettings.differences); the two sidecars may be fitted at different times, so one may record more
    assert shipped.differences(calibration["refinement"]) == {}
    assert shipped.differences(quality["refinement"]) == {}


def test_no_error_model_templates_fits_the_residual_term(setup, tmp_path, single_thread):
    """``--error-model-templates 0``: no error model is fitted, the sidecar's term reads the pair's residual."""
    dataset, bundle = setup
    out = tmp_path / "sidecars"
    assert command.main(arguments(dataset, bundle, out, "--only", "calibration", "--error-model-templates", "0")) == 0
    calibration = json.loads((out / "model.calibration.json").read_text())
    assert calibration["error_model"] is None and calibration["error_features"] is None
