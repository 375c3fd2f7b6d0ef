"""monai_probreg.fitting.quality_cases and failure_set: the cases of a split, the perturbations, the resumable log."""

from __future__ import annotations

import json

import pytest
import torch

from monai_probreg.fitting import quality_cases as qc
from monai_probreg.fitting.failure_set import PERTURBATIONS
from monai_probreg.fitting.self_cases import SELF_PERTURBATIONS
from monai_probreg.utils.errors import InputError

LOG = "quality.json"


def test_cases_pair_a_scan_with_itself_only_in_self_cases_and_cover_every_perturbation():
    ids = ["A", "B", "C", "D"]
    for training in (True, False):
        cases = [c for c in qc.cases_for(ids, 0, training) if c["perturbation"] not in SELF_PERTURBATIONS]
        assert all(c["moving"] != c["fixed"] for c in cases)
        assert {c["perturbation"] for c in cases} == {qc.NORMAL, *PERTURBATIONS}
        assert len({c["seed"] for c in cases}) == len(cases)
    validation = qc.cases_for(ids, 0, False)
    normal = [c for c in validation if c["perturbation"] == qc.NORMAL]
    assert len(normal) == len(ids) * len(ids)  # every ordered pair and every subject to the atlas


@pytest.mark.parametrize("name", list(PERTURBATIONS))
def test_failure_perturbations_keep_the_grid_and_move_labels_only_for_turns(name):
    axes = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in (40, 44, 36)], indexing="ij")
    image = (1 - ((axes[0] - 0.2) ** 2 + (axes[1] + 0.1) ** 2 + axes[2] ** 2)).clamp(0, 1)[None, None]  # off-centre
    label = (axes[0] > 0.3).to(torch.int16)[None, None]  # an asymmetric label: a turn must move it
    out_image, out_label = PERTURBATIONS[name](image, label, torch.Generator().manual_seed(0))
    assert out_image.shape == image.shape and out_label.shape == label.shape and out_label.dtype == label.dtype
    assert not torch.equal(out_image, image)
    assert torch.equal(out_label, label) != name.startswith("turn")


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
    path = tmp_path / "out" / LOG
    first = qc.RecordLog(path, HEADER)
    qc.logged_cases("train", CASES[:1], _record, first)  # stopped after one registration
    assert json.loads(path.read_text())["header"] == HEADER
    resumed = qc.RecordLog(path, HEADER, resume=True)
    assert resumed.reused == 1
    ran = []
    records = qc.logged_cases("train", CASES, lambda case: ran.append(case) or _record(case), resumed)
    assert ran == CASES[1:] and records == [_record(c) for c in CASES]
    # another split with the same cases is not the same registration
    assert qc.RecordLog(path, HEADER, resume=True).get("val", CASES[0]) is None


def test_a_log_of_other_settings_is_refused_and_without_resume_replaced(tmp_path):
    path = tmp_path / LOG
    qc.logged_cases("train", CASES, _record, qc.RecordLog(path, HEADER))
    other = {**HEADER, "refinement": {"num_iterations": 0}}
    with pytest.raises(InputError, match=r"refinement.*num_iterations.*10.*num_iterations.*0"):
        qc.RecordLog(path, other, resume=True)
    fresh = qc.RecordLog(path, other)  # no --resume: starts empty, replaces the old log at its first record
    assert fresh.reused == 0 and fresh.get("train", CASES[0]) is None
    qc.logged_cases("train", CASES[:1], _record, fresh)
    assert json.loads(path.read_text())["header"]["refinement"] == {"num_iterations": 0}
    assert len(json.loads(path.read_text())["records"]) == 1


def test_an_unreadable_log_is_refused_with_its_name(tmp_path):
    path = tmp_path / LOG
    path.write_text('{"header": {"seed": 0}, "recor')  # cut short by a full disk
    with pytest.raises(InputError, match=rf"{LOG}: expected a log of registrations .* got an unreadable file"):
        qc.RecordLog(path, HEADER, resume=True)
    assert qc.RecordLog(path, HEADER).reused == 0  # without --resume it is replaced
