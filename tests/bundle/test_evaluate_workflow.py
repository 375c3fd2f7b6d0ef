"""bundle/configs/evaluate.yaml end to end on the tiny synthetic dataset, with random weights.

Through ``ConfigWorkflow`` (properties, CSV, summary.json, the printed table, bad inputs) and once through the
documented command line. The no-registration Dice is checked against Dice computed independently from the label
files with numpy; the random near-identity model must score like no registration.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from bundle_fixtures import infer_workflow, root_cause
from conftest import TINY_LABELS, make_tiny_dataset, numpy_mean_dice

pytestmark = pytest.mark.usefixtures("single_thread")


def test_evaluate_scores_every_labelled_subject(tmp_path, tiny_dataset, bundle, capsys):
    # the network alone (refine_iterations 0): the default refinement moves even the random model's field (its pull,
    # 0.25 in units of the untrained posterior's std of about a voxel, is weak); refinement in the evaluator: next test
    wf = infer_workflow("evaluate.yaml", bundle, tiny_dataset, tmp_path / "out", refine_iterations=0)
    assert wf.check_properties() == []  # InferProperties (+ MetaProperties when metadata.json exists), optional IDs
    wf.run()
    wf.finalize()

    with open(tmp_path / "out" / "scores.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["id"] for r in rows] == ["T01", "T02", "T03"]
    for row in rows:
        dice = [float(row["mean_dice"]), float(row["mean_dice_no_registration"])]
        dice += [float(row[f"dice_{lab}"]) for lab in TINY_LABELS]
        assert all(0.0 <= d <= 1.0 for d in dice), row
        # padding and RAS reorientation do not change Dice: the baseline equals numpy on the files (float64: 1e-12)
        assert float(row["mean_dice_no_registration"]) == pytest.approx(
            numpy_mean_dice(tiny_dataset, row["id"]), abs=1e-12
        )
        # random initial weights move voxels by < 1e-4: the nearest-neighbour warp is the identity
        assert float(row["mean_dice"]) == pytest.approx(float(row["mean_dice_no_registration"]), abs=1e-12)
        assert int(row["num_folding"]) == 0 and float(row["runtime_s"]) > 0

    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["num_subjects"] == 3
    mean = summary["registered"]["mean_dice"]["mean"]
    assert 0.0 <= mean <= 1.0 and mean == pytest.approx(np.mean([float(r["mean_dice"]) for r in rows]), abs=1e-12)
    assert 0.0 <= summary["no_registration"]["mean_dice"]["mean"] <= 1.0
    assert set(summary["dice_per_label"]) == {str(lab) for lab in TINY_LABELS}
    assert summary["config"]["model_file"] == str(bundle) + "/models/model.pt"  # the shipped default
    assert summary["config"]["network_size"] == [16, 16, 16]
    assert "3 subjects" in capsys.readouterr().out


def test_evaluate_with_refinement_runs_inside_the_evaluator(tmp_path, tiny_dataset, bundle):
    """refine_iterations > 0: the refinement needs gradients inside MONAI's evaluator (which runs without them); it
    moves the random model's ~0 field (posterior weight 0: the untrained head's log_var would pin it), its settings
    are in summary.json and its time is in the runtime."""
    plain = infer_workflow("evaluate.yaml", bundle, tiny_dataset, tmp_path / "plain")
    plain.run()
    wf = infer_workflow(
        "evaluate.yaml", bundle, tiny_dataset, tmp_path / "refined", refine_iterations=5, refine_posterior_weight=0.0
    )
    wf.run()
    summary = json.loads((tmp_path / "refined" / "summary.json").read_text())
    assert summary["config"]["refinement"]["num_iterations"] == 5
    assert summary["config"]["refinement"]["posterior_weight"] == 0.0
    with open(tmp_path / "plain" / "scores.csv") as f, open(tmp_path / "refined" / "scores.csv") as g:
        plain_rows, refined_rows = list(csv.DictReader(f)), list(csv.DictReader(g))
    assert any(p["mean_dice"] != r["mean_dice"] for p, r in zip(plain_rows, refined_rows))
    assert all(int(r["num_folding"]) == 0 for r in refined_rows)


def test_evaluate_command_line_as_documented(tmp_path, tiny_dataset, bundle):
    """Exactly the documented command with nothing else set (default network_size, workers, device)."""
    cmd = [
        sys.executable,
        "-m",
        "monai.bundle",
        "run",
        "--config_file",
        f"['{bundle / 'configs' / 'inference.yaml'}','{bundle / 'configs' / 'evaluate.yaml'}']",  # overlay after base
        "--bundle_root",
        str(bundle),
        "--dataset_dir",
        str(tiny_dataset),
        "--output_dir",
        str(tmp_path / "out"),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "mean Dice" in done.stdout and "[3/3] T03" in done.stdout + done.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["num_subjects"] == 3 and summary["config"]["network_size"] == [80, 96, 80]


def test_evaluate_without_labels_says_so(tmp_path, bundle):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, with_labels=False)
    wf = infer_workflow("evaluate.yaml", bundle, dataset, tmp_path / "out")
    with pytest.raises(Exception) as info:
        wf.run()
    cause = root_cause(info.value)
    assert isinstance(cause, ValueError) and "evaluation needs labels" in str(cause) and str(dataset) in str(cause)


def test_evaluate_takes_a_pairs_file_with_any_fixed_image(tmp_path, tiny_dataset, bundle):
    pairs = tmp_path / "pairs.csv"
    pairs.write_text(
        "moving,fixed,moving_label,fixed_label,id\n"
        f"{tiny_dataset}/images/T01.nii.gz,{tiny_dataset}/images/T02.nii.gz,"
        f"{tiny_dataset}/labels/T01.nii.gz,{tiny_dataset}/labels/T02.nii.gz,T01_to_T02\n"
        f"{tiny_dataset}/images/T03.nii.gz,{tiny_dataset}/atlas/A01_image.nii.gz,"
        f"{tiny_dataset}/labels/T03.nii.gz,{tiny_dataset}/atlas/A01_label.nii.gz,T03_to_atlas\n"
    )
    wf = infer_workflow(
        "evaluate.yaml", bundle, tmp_path / "no_such_dataset", tmp_path / "pairs", pairs_file=str(pairs)
    )
    wf.run()
    wf.finalize()
    with open(tmp_path / "pairs" / "scores.csv") as f:
        rows = {r["id"]: r for r in csv.DictReader(f)}
    assert list(rows) == ["T01_to_T02", "T03_to_atlas"]
    # the atlas pair scores as it does in the atlas layout
    atlas = infer_workflow("evaluate.yaml", bundle, tiny_dataset, tmp_path / "atlas", subject_ids=["T03"])
    atlas.run()
    atlas.finalize()
    with open(tmp_path / "atlas" / "scores.csv") as f:
        (reference,) = list(csv.DictReader(f))
    for key in ("mean_dice", "mean_dice_no_registration", "num_folding"):
        assert float(rows["T03_to_atlas"][key]) == pytest.approx(float(reference[key]), abs=1e-12)
    summary = json.loads((tmp_path / "pairs" / "summary.json").read_text())
    assert summary["num_subjects"] == 2
