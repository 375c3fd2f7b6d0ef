"""The quality estimate in the bundle: evaluate.yaml's scores.csv and summary.json, inference.yaml's quality.json.

Random weights, so the quality model is made by hand (all weights 0, an intercept that always or never warns): what
is tested is the plumbing; the estimate is tested in tests/uncertainty and scored by benchmarks/failure_detection.py.
"""

from __future__ import annotations

import csv
import json
import logging

import pytest
from bundle_fixtures import infer_workflow

from monai_probreg.uncertainty.quality import QualityModel, quality_path, save_quality_model
from monai_probreg.uncertainty.quality_features import QualityFeatures

pytestmark = pytest.mark.usefixtures("single_thread")
N = len(QualityFeatures._fields)


@pytest.fixture
def always_warns(bundle):
    weights = bundle / "models" / "model.pt"
    save_quality_model(
        QualityModel(
            list(QualityFeatures._fields), [-1e9] * N, [1e9] * N, [0.0] * N, [1.0] * N, [0.0] * N, 0.42, [0.0] * N, 20.0
        ),
        weights,
    )
    yield weights
    quality_path(weights).unlink()


def test_evaluate_adds_the_estimate_and_the_warnings(tmp_path, tiny_dataset, bundle, always_warns, caplog):
    wf = infer_workflow("evaluate.yaml", bundle, tiny_dataset, tmp_path / "out")
    with caplog.at_level(logging.WARNING):
        wf.run()
    wf.finalize()
    rows = list(csv.DictReader((tmp_path / "out" / "scores.csv").open()))
    assert len(rows) == 3
    for row in rows:
        assert float(row["predicted_dice"]) == pytest.approx(0.42) and float(row["failure_probability"]) > 0.99
        assert "probably failed" in row["warning"]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["quality"]["num_warnings"] == 3 and summary["quality"]["predicted_dice"]["mean"] == pytest.approx(
        0.42
    )
    assert [w["id"] for w in summary["quality"]["warnings"]] == [r["id"] for r in rows]
    assert sum("WARNING" in r.getMessage() for r in caplog.records) == 3


def test_evaluate_without_the_estimate(tmp_path, tiny_dataset, bundle, always_warns):
    wf = infer_workflow("evaluate.yaml", bundle, tiny_dataset, tmp_path / "out", quality_estimate=False)
    wf.run()
    wf.finalize()
    header = next(csv.reader((tmp_path / "out" / "scores.csv").open()))
    assert "predicted_dice" not in header and "warning" not in header
    assert "quality" not in json.loads((tmp_path / "out" / "summary.json").read_text())


def test_inference_writes_quality_json_per_subject(tmp_path, tiny_dataset, bundle, always_warns):
    wf = infer_workflow("inference.yaml", bundle, tiny_dataset, tmp_path / "out", outputs=["warped"], num_samples=0)
    wf.run()
    wf.finalize()
    for sid in ("T01", "T02", "T03"):
        record = json.loads((tmp_path / "out" / sid / "quality.json").read_text())
        assert record["failure_probability"] > 0.99 and "probably failed" in record["warning"]
        assert set(record["features"]) == set(QualityFeatures._fields)
