"""monai_probreg.engines.quality_check: the record is JSON-ready, and weights without a quality model give none."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from monai_probreg.engines.quality_check import QualityCheck
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.engines.registration import register_pair
from monai_probreg.networks.probreg_net import ProbRegNet
from monai_probreg.uncertainty.quality import QualityEstimate, QualityModel, quality_record
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
    recorded = dataclasses.replace(_neutral_model(), entropy_calibration={"std_scale": 1.0, "bias_fraction": 0.0})
    assert QualityCheck(torch.nn.Identity(), weights, calibrate=False, quality_model=recorded).enabled
    assert not QualityCheck(torch.nn.Identity(), weights, calibrate=False, quality_model=_neutral_model()).enabled


def _neutral_model() -> QualityModel:
    n = len(QualityFeatures._fields)
    return QualityModel(list(QualityFeatures._fields), [-1e9] * n, [1e9] * n, [0.0] * n, [1.0] * n, [0.0] * n, 0.6,
                        [0.0] * n, -20.0)  # fmt: skip


def _pair_inputs(size: int = 16):
    g = torch.Generator().manual_seed(0)
    fixed = torch.nn.functional.avg_pool3d(torch.rand(1, 1, size, size, size, generator=g), 3, 1, 1)
    moving = torch.roll(fixed, shifts=(1, -2, 1), dims=(2, 3, 4))
    return moving, fixed


def test_a_refined_workflow_reads_the_networks_own_registration():
    """quality.py, "Whose features": with refinement, the features are those of the network's registration (computed
    again without refinement) and the refined pair's are the answer's; without, the pair's own and no answer."""
    torch.manual_seed(0)
    net = ProbRegNet(network_size=(16, 16, 16), enc_channels=(4, 8, 8, 8), dec_channels=(8, 8, 8, 8, 4)).eval()
    moving, fixed = _pair_inputs()
    targets = {"moving": moving, "fixed": fixed}
    refinement = RefinementSettings(num_iterations=5, lncc_kernel_size=3, learning_rate=0.5)
    network_pair = register_pair(net, moving, fixed)
    refined_pair = register_pair(net, moving, fixed, refinement)
    weights = "unused.pt"
    plain = QualityCheck(net, weights, quality_model=_neutral_model())("A", network_pair, targets)
    refined = QualityCheck(net, weights, quality_model=_neutral_model(), refinement=refinement)(
        "A", refined_pair, targets
    )
    assert plain["answer_features"] is None
    assert refined["features"] == pytest.approx(plain["features"], abs=1e-6)
    assert refined["answer_features"]["displacement_mm"] != pytest.approx(plain["features"]["displacement_mm"])
    off = QualityCheck(net, weights, quality_model=_neutral_model(), refinement=RefinementSettings())
    assert off("A", network_pair, targets)["answer_features"] is None  # 0 steps: the network's answer itself


def test_the_entropy_feature_takes_the_quality_models_own_calibration():
    """A quality model that records its fit's calibration gets the entropy under it, whatever the workflow's
    std_scale / bias_fraction; one that does not gets the workflow's (here: halving the std lowers the mean velocity
    entropy by 3 log 2 nats, three components)."""
    import dataclasses

    torch.manual_seed(0)
    net = ProbRegNet(network_size=(16, 16, 16), enc_channels=(4, 8, 8, 8), dec_channels=(8, 8, 8, 8, 4)).eval()
    moving, fixed = _pair_inputs()
    pair, targets = register_pair(net, moving, fixed), {"moving": moving, "fixed": fixed}
    recorded = dataclasses.replace(_neutral_model(), entropy_calibration={"std_scale": 1.0, "bias_fraction": 0.0})

    def entropy(model: QualityModel, std_scale: float) -> float:
        return QualityCheck(net, "unused.pt", std_scale, quality_model=model)("A", pair, targets)["features"]["entropy"]

    assert entropy(recorded, 0.5) == pytest.approx(entropy(recorded, 1.0), abs=1e-6)
    assert entropy(_neutral_model(), 0.5) == pytest.approx(entropy(_neutral_model(), 1.0) - 3 * math.log(2), abs=1e-4)
