"""benchmarks/failure_detection.py and robustness.py: records refused, the shipped model's records, robustness's
perturbations (the cases, the header turn and the failure set: tests/fitting)."""

from __future__ import annotations

import json

import pytest
import torch
from bench_helpers import load_benchmark
from conftest import BUNDLE_DIR, make_tiny_dataset, tiny_bundle

detection = load_benchmark("failure_detection")
robustness = load_benchmark("robustness")


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


def test_the_shipped_quality_model_records_the_calibration_its_records_were_made_with():
    """The shipped sidecar's entropy_calibration is the one the committed records' entropy feature was computed with:
    S12 -> atlas is registered again (the network's own registration, what the feature reads) and its entropy
    recomputed under it (real data: skipped without LPBA40; 1.453 stored, under bundle 0.20.0's calibration, std_scale
    1.477; bundle 0.18.0's (0.491, 0.237) gives 0.842, 0.19.0's (1.791, 0) 2.031)."""
    from bench_helpers import REPO
    from common import DEFAULT_DATASET, bundle_parser

    from monai_probreg.fitting.quality_cases import load_scans, run_case
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
    scans = load_scans(DEFAULT_DATASET, ["S12"], int(evaluate.get_parsed_content("divisor")))
    again = run_case(network, Calibration(**model.entropy_calibration), scans, case)
    assert again["features"]["entropy"] == pytest.approx(stored["features"]["entropy"], abs=0.01)  # bf16 or fp32


def test_records_that_do_not_name_their_calibration_are_refused(tmp_path):
    records = tmp_path / "records.json"
    records.write_text(json.dumps({"refinement": {}, "train_records": [], "val_records": []}))
    with pytest.raises(SystemExit, match="entropy_calibration"):
        detection.main(["--records", str(records), "--out-dir", str(tmp_path / "out")])
