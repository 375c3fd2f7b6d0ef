"""monai_probreg.fitting.command_cases: the header turn, and each scan through the whole command as it is and turned."""

from __future__ import annotations

import math
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from conftest import BUNDLE_DIR, make_tiny_dataset, tiny_bundle

from monai_probreg.fitting import command_cases as command
from monai_probreg.fitting.quality_cases import RecordLog
from monai_probreg.uncertainty.quality import failed
from monai_probreg.uncertainty.quality_features import QualityFeatures
from monai_probreg.utils.errors import InputError

LOG = "quality.json"
HEADER = {"weights_sha256": "ab", "refinement": {"num_iterations": 10}, "seed": 0, "train_ids": ["S12"]}


def test_a_turned_header_turns_the_world_and_keeps_the_voxels(tmp_path):
    data = np.arange(4 * 6 * 5, dtype=np.int16).reshape(4, 6, 5)
    affine = np.diag([1.5, 1.0, 2.0, 1.0])
    affine[:3, 3] = [10.0, -20.0, 5.0]
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "scan.nii.gz")
    out = command.turned_header(tmp_path / "scan.nii.gz", 180.0, tmp_path / "turned.nii.gz")
    turned = nib.load(out)
    assert np.array_equal(np.asanyarray(turned.dataobj), data)
    centre = affine @ np.r_[1.5, 2.5, 2.0, 1.0]
    assert np.allclose(turned.affine @ np.r_[1.5, 2.5, 2.0, 1.0], centre)  # about the grid centre
    corner, turned_corner = affine @ np.r_[0, 0, 0, 1.0], turned.affine @ np.r_[0, 0, 0, 1.0]
    assert np.allclose(turned_corner[:2] - centre[:2], -(corner[:2] - centre[:2]))  # R and A flip, S stays
    assert math.isclose(turned_corner[2], corner[2])


def test_command_cases_register_each_scan_as_it_is_and_turned(tmp_path):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    records = command.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3)
    assert [r["perturbation"] for r in records] == list(command.COMMAND_NAMES)
    assert command.COMMAND_NAMES == ("command", "command_turn90", "command_turn180")
    for r in records:
        assert (r["moving"], r["fixed"], r["seed"], r["dice_identity"]) == ("T01", "atlas", 3, 0.5)
        assert set(r["features"]) == set(QualityFeatures._fields)
        assert all(math.isfinite(v) for v in r["features"].values())
        assert r["failed"] == failed(r["dice"], r["dice_before"], 0.5)
    assert records[0]["dice_before"] > 0.5  # as it is: the affine stage finds the phantom
    # the command's default path refines (inference.yaml), so each record has the refined answer's features too;
    # --refine 0 gives the network alone and none
    assert all(set(r["answer_features"]) == set(QualityFeatures._fields) for r in records)
    plain = command.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3, refine=0)
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
    assert command.turned_inputs(scan, labels, 0, tmp_path) == (scan, labels)
    turned, turned_labels = command.turned_inputs(scan, labels, 90, tmp_path)
    assert turned != scan and turned_labels != labels
    assert np.allclose(nib.load(turned).affine, nib.load(turned_labels).affine)
    assert not np.allclose(nib.load(turned).affine, affine)
    assert command.turned_inputs(scan, None, 180, tmp_path)[1] is None


def test_command_cases_compute_the_entropy_with_the_calibration_given(tmp_path):
    """The records' entropy feature is computed with the calibration the quality model will record (the tiny bundle
    has none: raw); halving the std lowers it by exactly 3 log 2 nats and changes no other feature."""
    from monai_probreg.uncertainty.calibration import Calibration

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    common = (dataset, ["T01"], bundle, None, {"T01": 0.5})
    plain = command.command_cases(*common, seed=3, refine=0)
    halved = command.command_cases(*common, seed=3, refine=0, entropy_calibration=Calibration(0.5, 0.0))
    for a, b in zip(plain, halved):
        assert b["features"]["entropy"] == pytest.approx(a["features"]["entropy"] - 3 * math.log(2), abs=1e-4)
        others = {k: v for k, v in b["features"].items() if k != "entropy"}
        assert others == pytest.approx({k: v for k, v in a["features"].items() if k != "entropy"}, abs=1e-6)


def test_command_cases_take_logged_registrations_from_the_log(tmp_path, monkeypatch):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    path = tmp_path / "out" / LOG
    common = (dataset, ["T01"], bundle, None, {"T01": 0.5})
    first = command.command_cases(*common, seed=3, refine=0, log=RecordLog(path, HEADER))

    def no_registration(*args, **kwargs):
        raise AssertionError("a logged case was registered again")

    monkeypatch.setattr(command, "register_scan", no_registration)
    again = command.command_cases(*common, seed=3, refine=0, log=RecordLog(path, HEADER, resume=True))
    assert again == first and len(again) == len(command.COMMAND_NAMES)
    with pytest.raises(AssertionError, match="registered again"):  # another seed is another case
        command.command_cases(*common, seed=4, refine=0, log=RecordLog(path, HEADER, resume=True))


def test_command_cases_refuse_a_refinement_changed_since_the_run_started(tmp_path):
    """The whole-command cases load the model (inference.yaml) when they start, late in a run: if the configs changed
    since the run's log was begun, their records would be of other settings than the rest."""
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    started = {**HEADER, "command_refinement": {"num_iterations": 99}}
    log = RecordLog(tmp_path / LOG, started)
    with pytest.raises(InputError, match=r"num_iterations.*99"):
        command.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3, log=log)


def test_a_training_subject_goes_through_the_command_onto_itself_with_its_header_moved(tmp_path):
    """``self_cases``: after the three atlas cases, the scan onto itself, its header (and its labels') moved by a
    seeded rigid motion that the affine stage undoes: no registration is the scan itself (Dice 1), the affine alone
    finds the motion back, and the record's failure follows the definition; without it (validation) there is none."""
    from monai_probreg.fitting.self_cases import SELF_DICE

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, shape=(32, 36, 28))
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    records = command.command_cases(dataset, ["T01"], bundle, None, {"T01": 0.5}, seed=3, refine=0, self_cases=True)
    assert [r["perturbation"] for r in records] == [*command.COMMAND_NAMES, command.COMMAND_SELF]
    own = records[-1]
    assert (own["moving"], own["fixed"], own["seed"], own["dice_identity"]) == ("T01", "T01", 3, SELF_DICE)
    # the affine stage undid (some of) the header's motion: its labels overlap more than the moved labels read where
    # they now lie in the world, with no registration. (Not to within a voxel: the affine stage's defaults are a 1 mm
    # brain's, 1/4 of this phantom's grid at the first level; on its near-spherical ellipsoid the rotation is barely
    # in the image, so how much of it is found back varies with the CPU's floating-point paths: 0.84-0.95.)
    assert own["dice_before"] > _header_motion_dice(dataset / "labels" / "T01.nii.gz", own["seed"], tmp_path) + 0.1
    assert own["failed"] == failed(own["dice"], own["dice_before"], SELF_DICE)
    assert set(own["features"]) == set(QualityFeatures._fields)
    assert all(math.isfinite(v) for v in own["features"].values())


def _header_motion_dice(labels: Path, seed: int, folder: Path) -> float:
    """Mean Dice of ``labels`` against themselves with their header moved as the self case moves it (seeded), read
    nearest-neighbour where they lie in the world: the overlap the affine stage starts from (scipy, not our code)."""
    from scipy import ndimage

    _, moved = command._moved_inputs(labels, labels, seed, folder)
    original, shifted = nib.load(labels), nib.load(moved)
    voxel_to_voxel = np.linalg.inv(shifted.affine) @ original.affine  # original voxel -> moved file's voxel
    read = ndimage.affine_transform(np.asarray(shifted.dataobj), voxel_to_voxel, order=0, output_shape=original.shape)
    truth = np.asarray(original.dataobj)
    ids = [v for v in np.unique(truth) if v != 0]
    return float(
        np.mean([2 * ((read == v) & (truth == v)).sum() / ((read == v).sum() + (truth == v).sum()) for v in ids])
    )


def test_a_moved_header_moves_the_world_and_keeps_the_voxels(tmp_path):
    data = np.arange(4 * 6 * 5, dtype=np.int16).reshape(4, 6, 5)
    affine = np.diag([1.5, 1.0, 2.0, 1.0])
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "scan.nii.gz")
    motion = np.eye(4)
    motion[:3, 3] = [1.0, -2.0, 3.0]
    moved = nib.load(command.moved_header(tmp_path / "scan.nii.gz", motion, tmp_path / "moved.nii.gz"))
    assert np.array_equal(np.asanyarray(moved.dataobj), data)
    assert np.allclose(moved.affine, motion @ affine) and np.allclose(moved.get_qform(), motion @ affine)
