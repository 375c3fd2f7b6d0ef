"""monai_probreg.fitting.self_cases: a training subject onto itself and onto a near copy (almost nothing to register),
on the bundle path (cases_for, run_case) and the fit's range they give (fit_on_records)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting import quality_cases as qc
from monai_probreg.fitting import quality_fit
from monai_probreg.fitting import self_cases as sc
from monai_probreg.fitting.failure_set import PERTURBATIONS
from monai_probreg.fitting.quality_cases import record_features
from monai_probreg.metrics.scores import score_pair
from monai_probreg.networks.probreg_net import ProbRegNet
from monai_probreg.uncertainty.calibration import RAW
from monai_probreg.uncertainty.quality_features import QualityFeatures

pytestmark = pytest.mark.usefixtures("single_thread")

IDS = ["A", "B", "C", "D"]
SHAPE = (32, 32, 32)  # a multiple of the UNet's 16: no padding
SMALL = {"enc_channels": (4, 8, 8, 8), "dec_channels": (8, 8, 8, 8, 4)}  # a fast random network
NCC = QualityFeatures._fields.index("ncc_before")
LNCC = QualityFeatures._fields.index("lncc_before")


def _scan(seed: int = 0) -> dict:
    """A textured off-centre 'brain' in [0, 1] (1, 1, *SHAPE) with three labels (two halves and an inner blob)."""
    g = torch.Generator().manual_seed(seed)
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in SHAPE], indexing="ij")
    r2 = (axes[0] - 0.1) ** 2 + (axes[1] + 0.05) ** 2 + axes[2] ** 2
    inside, inner = r2 < 0.5, r2 < 0.1
    texture = 0.1 * torch.sin(6 * axes[0]) * torch.cos(5 * axes[1]) + 0.02 * torch.rand(SHAPE, generator=g)
    image = (0.5 * inside + 0.3 * inner + texture * inside).clamp(0, 1)
    label = torch.zeros(SHAPE, dtype=torch.int16)
    label[inside & (axes[0] < 0.1)], label[inside & (axes[0] >= 0.1)], label[inner] = 21, 22, 181
    return {"image": image[None, None].float(), "label": label[None, None], "spacing": [1.0, 1.0, 1.0]}


def test_self_cases_are_made_for_training_subjects_only_and_last():
    training, validation = qc.cases_for(IDS, 7, True), qc.cases_for(IDS, 7, False)
    own = [c for c in training if c["moving"] == c["fixed"]]
    assert [(c["moving"], c["perturbation"]) for c in own] == [(i, n) for i in IDS for n in sc.SELF_PERTURBATIONS]
    assert training[-len(own) :] == own  # last: every other case keeps the seed it had without them
    assert [c["seed"] for c in training] == list(range(7, 7 + len(training)))
    assert not any(c["moving"] == c["fixed"] or c["perturbation"] in sc.SELF_PERTURBATIONS for c in validation)
    assert {c["perturbation"] for c in training} == {qc.NORMAL, *PERTURBATIONS, *sc.SELF_PERTURBATIONS}


def test_the_validation_split_gets_no_self_case_on_either_path(monkeypatch):
    """split_records asks the whole command for self cases (training=True) on the training split only."""
    asked = {}

    def fake_command_cases(*args, self_cases=False, **kwargs):
        asked[args[5]] = self_cases  # keyed by the seed
        return []

    monkeypatch.setattr(quality_fit, "command_cases", fake_command_cases)
    outcome = {"dice": 0.7, "dice_identity": 0.5, "failed": False, "features": {"ncc_before": 0.5, "ncc_after": 0.6}}
    monkeypatch.setattr(quality_fit, "run_case", lambda network, calibration, scans, case, refinement: case | outcome)
    log = qc.RecordLog(None, {})
    command = quality_fit.CommandSetup(None, None)
    for split, seed in (("train", 0), ("val", 1)):
        records = quality_fit.split_records(split, IDS, seed, None, RAW, {}, None, log, command)
        assert any(r["moving"] == r["fixed"] for r in records) is (split == "train")
    assert asked == {0: True, 1: False}


def test_a_near_copy_is_seeded_small_and_moves_image_and_labels():
    scan = _scan()
    image, label = scan["image"], scan["label"]
    out, moved = sc.near_copy(image, label, torch.Generator().manual_seed(3))
    again, _ = sc.near_copy(image, label, torch.Generator().manual_seed(3))
    other, _ = sc.near_copy(image, label, torch.Generator().manual_seed(4))
    assert torch.equal(out, again) and not torch.equal(out, other)
    assert out.shape == image.shape and moved.shape == label.shape and moved.dtype == label.dtype
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    dice = score_pair(None, moved, label).mean_dice  # the Dice of no registration: near, not equal, to 1
    assert 0.8 < dice < sc.SELF_DICE
    assert sc.SELF_PERTURBATIONS[sc.SELF](image, label, None) == (image, label)


def test_a_rigid_motion_is_seeded_and_within_its_ranges():
    centre = np.array([10.0, -20.0, 30.0])
    motion = sc.rigid_motion(torch.Generator().manual_seed(5), centre)
    assert np.array_equal(motion, sc.rigid_motion(torch.Generator().manual_seed(5), centre))
    rotation = motion[:3, :3]
    assert np.allclose(rotation.T @ rotation, np.eye(3)) and math.isclose(np.linalg.det(rotation), 1.0)
    degrees = math.degrees(math.acos((np.trace(rotation) - 1) / 2))
    assert sc.SELF_TURN_DEGREES[0] <= degrees <= sc.SELF_TURN_DEGREES[1]
    shift = np.linalg.norm(motion[:3, :3] @ centre + motion[:3, 3] - centre)  # the centre moves by the shift only
    assert sc.SELF_SHIFT_MM[0] <= shift <= sc.SELF_SHIFT_MM[1]


def test_a_scan_onto_itself_has_dice_1_before_and_after_and_did_not_fail():
    """The bundle path's self case, refined with the similarity guard (the shipped default): no registration and the
    registration both have Dice 1, so it did not fail (the failure definition's margin of a perfect overlap), and
    its features sit at the identity corner; the near copy's Dice of no registration is below 1."""
    torch.manual_seed(0)
    network = ProbRegNet(spatial_dims=3, **SMALL).eval()
    scans = {"A": _scan()}
    refinement = RefinementSettings(num_iterations=2, learning_rate=0.1, similarity_guard=True)
    own, near = (
        qc.run_case(network, RAW, scans, {"moving": "A", "fixed": "A", "perturbation": name, "seed": 0}, refinement)
        for name in (sc.SELF, sc.NEAR_COPY)
    )
    assert (own["moving"], own["fixed"], own["perturbation"]) == ("A", "A", sc.SELF)
    assert own["dice_identity"] == sc.SELF_DICE and own["dice"] == sc.SELF_DICE and own["failed"] is False
    assert own["features"]["ncc_before"] == pytest.approx(1.0, abs=1e-6)
    assert own["features"]["lncc_before"] == pytest.approx(1.0, abs=1e-3)
    assert near["perturbation"] == sc.NEAR_COPY and near["dice_identity"] < sc.SELF_DICE
    assert near["features"]["ncc_before"] < own["features"]["ncc_before"]


def _records(n: int, rng: np.random.Generator, identity_side: bool) -> list[dict]:
    """Synthetic training records: normal pairs (NCC 0.2-0.7, a few mm of displacement) or, ``identity_side``, pairs
    with nothing to register (NCC and local NCC before 1, under a mm, Dice 1, not failed)."""
    out = []
    for k in range(n):
        u = rng.uniform(size=len(QualityFeatures._fields))
        if identity_side:
            f = [
                1.0,
                0.97 + 0.02 * u[1],
                1.0,
                0.9 + 0.07 * u[3],
                -0.5 + 0.3 * u[4],
                0.3 + 0.7 * u[5],
                0.05 + 0.15 * u[6],
                0,
            ]
            dice, fail = sc.SELF_DICE, False
        else:
            ncc = 0.2 + 0.5 * u[0]
            f = [
                ncc,
                ncc + 0.1 * u[1],
                0.1 + 0.3 * u[2],
                0.2 + 0.3 * u[3],
                1.5 * u[4],
                2 + 10 * u[5],
                0.5 + 0.4 * u[6],
                0,
            ]
            dice = 0.3 + 0.5 * f[1] + 0.02 * rng.normal()
            fail = bool(dice < 0.45)
        kind = sc.SELF if identity_side else qc.NORMAL
        features = dict(zip(QualityFeatures._fields, f))
        out.append({"moving": f"S{k}", "perturbation": kind, "features": features, "dice": dice, "failed": fail})
    return out


def test_a_fit_with_self_cases_reaches_the_identity_corner_and_tells_near_identical_pairs_apart():
    """Without self cases two near-identical pairs lie beyond the range on one corner and get the same estimate to
    the last digit (the defect); with them the range reaches NCC 1 and the failure model, which has seen the corner,
    gives each its own low probability. The Dice regression is fitted without them (its normal-pair predictions are
    those of the fit without self cases), where fitted with them it would move them (what ruins its ranking)."""
    rng = np.random.default_rng(0)
    normal = _records(60, rng, identity_side=False)
    own = _records(12, rng, identity_side=True)
    pairs = [  # e.g. the template onto itself and a scan onto its moved copy, through the command
        QualityFeatures(0.998, 0.985, 0.99, 0.95, -0.3, 0.6, 0.1, 0.0),
        QualityFeatures(0.994, 0.975, 0.98, 0.93, -0.2, 0.9, 0.15, 0.0),
    ]
    before = quality_fit.fit_on_records(normal, None, RAW)
    assert before.estimate(pairs[0])[:2] == before.estimate(pairs[1])[:2]  # (predicted Dice, failure probability)
    model = quality_fit.fit_on_records(normal + own, None, RAW)
    assert model.high[NCC] == pytest.approx(1.0) and model.high[LNCC] == pytest.approx(1.0)
    assert model.dice_high[NCC] == before.high[NCC] and model.dice_range == before.dice_range
    first, second = (model.estimate(p) for p in pairs)
    assert first.failure_probability != second.failure_probability
    assert max(first.failure_probability, second.failure_probability) < model.threshold  # good pairs: no warning
    normal_dice = model.predict(record_features(normal))[0]
    np.testing.assert_allclose(normal_dice, before.predict(record_features(normal))[0], atol=1e-3)
    everything = quality_fit.fit_quality_model(
        record_features(normal + own), [r["dice"] for r in normal + own], [r["failed"] for r in normal + own]
    )
    assert np.abs(everything.predict(record_features(normal))[0] - normal_dice).max() > 0.01
