"""benchmarks/failure_detection.py, failure_set.py and robustness.py: the cases, the header turn and the perturbations."""

from __future__ import annotations

import json
import math

import nibabel as nib
import numpy as np
import pytest
import torch
from bench_helpers import load_benchmark
from conftest import BUNDLE_DIR, make_tiny_dataset, tiny_bundle

from monai_probreg.uncertainty.quality import failed
from monai_probreg.uncertainty.quality_features import QualityFeatures

detection = load_benchmark("failure_detection")
failure_set = load_benchmark("failure_set")
robustness = load_benchmark("robustness")


def test_cases_never_pair_a_scan_with_itself_and_cover_every_perturbation():
    ids = ["A", "B", "C", "D"]
    for training in (True, False):
        cases = detection.cases_for(ids, 0, training)
        assert all(c["moving"] != c["fixed"] for c in cases)
        assert {c["perturbation"] for c in cases} == {detection.NORMAL, *failure_set.PERTURBATIONS}
        assert len({c["seed"] for c in cases}) == len(cases)
    validation = detection.cases_for(ids, 0, False)
    normal = [c for c in validation if c["perturbation"] == detection.NORMAL]
    assert len(normal) == len(ids) * len(ids)  # every ordered pair and every subject to the atlas


def test_a_turned_header_turns_the_world_and_keeps_the_voxels(tmp_path):
    data = np.arange(4 * 6 * 5, dtype=np.int16).reshape(4, 6, 5)
    affine = np.diag([1.5, 1.0, 2.0, 1.0])
    affine[:3, 3] = [10.0, -20.0, 5.0]
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "scan.nii.gz")
    out = detection.turned_header(tmp_path / "scan.nii.gz", 180.0, tmp_path / "turned.nii.gz")
    turned = nib.load(out)
    assert np.array_equal(np.asanyarray(turned.dataobj), data)
    centre = affine @ np.r_[1.5, 2.5, 2.0, 1.0]
    assert np.allclose(turned.affine @ np.r_[1.5, 2.5, 2.0, 1.0], centre)  # about the grid centre
    corner, turned_corner = affine @ np.r_[0, 0, 0, 1.0], turned.affine @ np.r_[0, 0, 0, 1.0]
    assert np.allclose(turned_corner[:2] - centre[:2], -(corner[:2] - centre[:2]))  # R and A flip, S stays
    assert math.isclose(turned_corner[2], corner[2])


@pytest.mark.parametrize("name", list(failure_set.PERTURBATIONS))
def test_failure_perturbations_keep_the_grid_and_move_labels_only_for_turns(name):
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in (40, 44, 36)], indexing="ij")
    image = (1 - ((axes[0] - 0.2) ** 2 + (axes[1] + 0.1) ** 2 + axes[2] ** 2)).clamp(0, 1)[None, None]  # off-centre
    label = (axes[0] > 0.3).to(torch.int16)[None, None]  # an asymmetric label: a turn must move it
    out_image, out_label = failure_set.PERTURBATIONS[name](image, label, torch.Generator().manual_seed(0))
    assert out_image.shape == image.shape and out_label.shape == label.shape and out_label.dtype == label.dtype
    assert not torch.equal(out_image, image)
    assert torch.equal(out_label, label) != name.startswith("turn")


@pytest.mark.parametrize("name", [*robustness.PERTURBATIONS, "all"])
def test_robustness_perturbations_are_seeded_and_scaled(name):
    image = torch.rand((1, 1, 20, 24, 16), generator=torch.Generator().manual_seed(0))
    out = robustness.perturb(image, name, 3)
    assert out.shape == image.shape and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    assert torch.equal(out, robustness.perturb(image, name, 3))
    assert not torch.equal(out, image)


def test_robustness_conditions_subset_keeps_the_full_runs_order_and_refuses_unknown_names():
    assert robustness.select_conditions(None) == robustness.ALL_CONDITIONS
    chosen = robustness.select_conditions(["all:both", "clean", "noise"])
    assert chosen == [("clean", "none"), ("noise", "moving"), ("noise", "fixed"), ("noise", "both"), ("all", "both")]
    for bad in (["glare"], ["all:sideways"]):
        with pytest.raises(SystemExit, match="--conditions: expected NAME"):
            robustness.select_conditions(bad)


def test_command_cases_register_each_scan_as_it_is_and_turned(tmp_path):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    records = detection.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3)
    assert [r["perturbation"] for r in records] == list(detection.COMMAND_NAMES)
    assert detection.COMMAND_NAMES == ("command", "command_turn90", "command_turn180")
    for r in records:
        assert (r["moving"], r["fixed"], r["seed"], r["dice_identity"]) == ("T01", "atlas", 3, 0.5)
        assert set(r["features"]) == set(QualityFeatures._fields)
        assert all(math.isfinite(v) for v in r["features"].values())
        assert r["failed"] == failed(r["dice"], r["dice_before"], 0.5)
    assert records[0]["dice_before"] > 0.5  # as it is: the affine stage finds the phantom
    # the command's default path refines (inference.yaml), so each record has the refined answer's features too;
    # --refine 0 gives the network alone and none
    assert all(set(r["answer_features"]) == set(QualityFeatures._fields) for r in records)
    plain = detection.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3, refine=0)
    assert all(r["answer_features"] is None for r in plain)
    for a, b in zip(plain, records):  # the estimate reads the network's registration either way
        assert a["features"] == pytest.approx(b["features"], abs=1e-6)


def test_turned_inputs_give_the_labels_the_scans_turned_header(tmp_path):
    affine = np.diag([1.5, 1.0, 2.0, 1.0])
    affine[:3, 3] = [10.0, -20.0, 5.0]
    scan = tmp_path / "S9.nii.gz"
    labels = tmp_path / "S9_labels.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((4, 6, 5), np.float32), affine), scan)
    nib.save(nib.Nifti1Image(np.ones((4, 6, 5), np.int16), affine), labels)
    assert detection.turned_inputs(scan, labels, 0, tmp_path) == (scan, labels)
    turned, turned_labels = detection.turned_inputs(scan, labels, 90, tmp_path)
    assert turned != scan and turned_labels != labels
    assert np.allclose(nib.load(turned).affine, nib.load(turned_labels).affine)
    assert not np.allclose(nib.load(turned).affine, affine)
    assert detection.turned_inputs(scan, None, 180, tmp_path)[1] is None


def test_robustness_refine_adds_a_refined_row_per_model(tmp_path):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=2, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    assert (
        robustness.main(
            [
                "--dataset-dir",
                str(dataset),
                "--bundle-root",
                str(bundle),
                "--subjects",
                "T01",
                "T02",
                "--conditions",
                "clean",
                "--refine",
                "2",
                "--label",
                "net",
                "--out-dir",
                str(tmp_path / "out"),
                "--name",
                "r",
            ]
        )
        == 0
    )
    result = json.loads((tmp_path / "out" / "r.json").read_text())
    assert result["methods"] == ["affine_alone", "net", "net + refine 2"]
    assert result["refinement"]["num_iterations"] == 2
    assert len(result["records"]) == 4 and all(0 <= r["net + refine 2"] <= 1 for r in result["records"])
    with pytest.raises(SystemExit, match="--refine must be >= 0"):
        robustness.main(["--refine", "-1"])


def test_command_cases_compute_the_entropy_with_the_calibration_given(tmp_path):
    """The records' entropy feature is computed with the calibration the quality model will record (the tiny bundle
    has none: raw); halving the std lowers it by exactly 3 log 2 nats and changes no other feature."""
    from monai_probreg.uncertainty.calibration import Calibration

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    common = (dataset, ["T01"], bundle, None, {"T01": 0.5})
    plain = detection.command_cases(*common, seed=3, refine=0)
    halved = detection.command_cases(*common, seed=3, refine=0, entropy_calibration=Calibration(0.5, 0.0))
    for a, b in zip(plain, halved):
        assert b["features"]["entropy"] == pytest.approx(a["features"]["entropy"] - 3 * math.log(2), abs=1e-4)
        others = {k: v for k, v in b["features"].items() if k != "entropy"}
        assert others == pytest.approx({k: v for k, v in a["features"].items() if k != "entropy"}, abs=1e-6)


def test_records_that_do_not_name_their_calibration_are_refused(tmp_path):
    records = tmp_path / "records.json"
    records.write_text(json.dumps({"refinement": {}, "train_records": [], "val_records": []}))
    with pytest.raises(SystemExit, match="entropy_calibration"):
        detection.main(["--records", str(records), "--out-dir", str(tmp_path / "out")])


def test_the_shipped_quality_model_records_the_calibration_its_records_were_made_with():
    """The shipped sidecar's entropy_calibration is the one the committed records' entropy feature was computed with:
    S12 -> atlas is registered again (the network's own registration, what the feature reads) and its entropy
    recomputed under it (real data: skipped without LPBA40; 1.453 stored, under bundle 0.20.0's calibration, std_scale
    1.477; bundle 0.18.0's (0.491, 0.237) gives 0.842, 0.19.0's (1.791, 0) 2.031)."""
    from bench_helpers import REPO
    from common import DEFAULT_DATASET, bundle_parser

    from monai_probreg.uncertainty.calibration import Calibration
    from monai_probreg.uncertainty.quality import load_quality_model
    from monai_probreg.weights.loading import load_weights

    if not DEFAULT_DATASET.is_dir():
        pytest.skip(f"LPBA40 not found at {DEFAULT_DATASET}")
    weights = REPO / "bundle" / "models" / "model.pt"
    records = json.loads((REPO / "benchmarks" / "results" / "failure_detection.json").read_text())
    model = load_quality_model(weights)
    assert records["entropy_calibration"] == model.entropy_calibration
    case = {"moving": "S12", "fixed": "atlas", "perturbation": "none", "seed": 0}
    stored = next(r for r in records["train_records"] if all(r[k] == v for k, v in case.items()))
    evaluate = bundle_parser(REPO / "bundle", ["evaluate.yaml"], {"dataset_dir": str(DEFAULT_DATASET)})
    network = load_weights(evaluate.get_parsed_content("network_def", lazy=False), weights, "cpu")
    scans = detection.load_scans(DEFAULT_DATASET, ["S12"], int(evaluate.get_parsed_content("divisor")))
    again = detection.run_case(network, Calibration(**model.entropy_calibration), scans, case)
    assert again["features"]["entropy"] == pytest.approx(stored["features"]["entropy"], abs=0.01)  # bf16 or fp32


HEADER = {"weights_sha256": "ab", "refinement": {"num_iterations": 10}, "seed": 0, "train_ids": ["S12"]}
CASES = [{"moving": "S12", "fixed": "atlas", "perturbation": p, "seed": i} for i, p in enumerate(("none", "blank"))]


def _record(case: dict) -> dict:
    return {
        **case,
        "dice": 0.7,
        "dice_identity": 0.5,
        "failed": False,
        "features": {"ncc_before": 0.1, "ncc_after": 0.9},
    }


def test_a_resumed_log_registers_only_the_cases_it_lacks(tmp_path):
    path = tmp_path / "out" / detection.PARTIAL_LOG
    first = detection.RecordLog(path, HEADER)
    detection.logged_cases("train", CASES[:1], _record, first)  # stopped after one registration
    assert json.loads(path.read_text())["header"] == HEADER
    resumed = detection.RecordLog(path, HEADER, resume=True)
    assert resumed.reused == 1
    ran = []
    records = detection.logged_cases("train", CASES, lambda case: ran.append(case) or _record(case), resumed)
    assert ran == CASES[1:] and records == [_record(c) for c in CASES]
    # another split with the same cases is not the same registration
    assert detection.RecordLog(path, HEADER, resume=True).get("val", CASES[0]) is None


def test_a_log_of_other_settings_is_refused_and_without_resume_replaced(tmp_path):
    path = tmp_path / detection.PARTIAL_LOG
    detection.logged_cases("train", CASES, _record, detection.RecordLog(path, HEADER))
    other = {**HEADER, "refinement": {"num_iterations": 0}}
    with pytest.raises(SystemExit, match=r"refinement.*num_iterations.*10.*num_iterations.*0"):
        detection.RecordLog(path, other, resume=True)
    fresh = detection.RecordLog(path, other)  # no --resume: starts empty, replaces the old log at its first record
    assert fresh.reused == 0 and fresh.get("train", CASES[0]) is None
    detection.logged_cases("train", CASES[:1], _record, fresh)
    assert json.loads(path.read_text())["header"]["refinement"] == {"num_iterations": 0}
    assert len(json.loads(path.read_text())["records"]) == 1


def test_command_cases_take_logged_registrations_from_the_log(tmp_path, monkeypatch):
    import monai_probreg.cli.pipeline as pipeline

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    path = tmp_path / "out" / detection.PARTIAL_LOG
    common = (dataset, ["T01"], bundle, None, {"T01": 0.5})
    first = detection.command_cases(*common, seed=3, refine=0, log=detection.RecordLog(path, HEADER))

    def no_registration(*args, **kwargs):
        raise AssertionError("a logged case was registered again")

    monkeypatch.setattr(pipeline, "register_scan", no_registration)
    again = detection.command_cases(*common, seed=3, refine=0, log=detection.RecordLog(path, HEADER, resume=True))
    assert again == first and len(again) == len(detection.COMMAND_NAMES)
    with pytest.raises(AssertionError, match="registered again"):  # another seed is another case
        detection.command_cases(*common, seed=4, refine=0, log=detection.RecordLog(path, HEADER, resume=True))


def test_command_cases_refuse_a_refinement_changed_since_the_run_started(tmp_path):
    """The whole-command cases load the model (inference.yaml) when they start, late in a run: if the configs changed
    since the run's log was begun, their records would be of other settings than the rest."""
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    started = {**HEADER, "command_refinement": {"num_iterations": 99}}
    log = detection.RecordLog(tmp_path / detection.PARTIAL_LOG, started)
    with pytest.raises(SystemExit, match=r"num_iterations.*99"):
        detection.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3, log=log)
