"""monai_probreg.engines.quality_check: the record is JSON-ready, and weights without a quality model give none."""

from __future__ import annotations

import json
import math

import torch

from monai_probreg.engines.quality_check import QualityCheck
from monai_probreg.uncertainty.quality import QualityEstimate, quality_record
from monai_probreg.uncertainty.quality_features import QualityFeatures


def test_a_record_without_a_finite_prediction_is_valid_json():
    features = QualityFeatures(*([math.nan] * len(QualityFeatures._fields)))
    record = quality_record(features, QualityEstimate(math.nan, 1.0, "not finite"))
    assert record["predicted_dice"] is None and record["failure_probability"] == 1.0
    assert set(record["features"]) == set(QualityFeatures._fields)
    json.loads(json.dumps(record, allow_nan=False))  # no NaN anywhere: strict JSON


def test_weights_without_a_quality_model_give_no_estimate(tmp_path):
    weights = tmp_path / "model.pt"
    torch.save({"w": torch.zeros(1)}, weights)
    check = QualityCheck(torch.nn.Identity(), weights)
    assert not check.enabled and check("A", None, {}) is None
    assert not QualityCheck(torch.nn.Identity(), weights, calibrate=False).enabled
