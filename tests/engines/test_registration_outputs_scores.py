"""monai_probreg.engines.outputs: register one pair, write the NIfTI outputs (geometry, conventions, atomicity), score."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch
from monai.data import MetaTensor

from monai_probreg import ProbRegNet, RegistrationOutput, label_dice
from monai_probreg.data.dataset import index_dataset, labelled_pairs, pair_dicts
from monai_probreg.data.transforms import registration_transforms
from monai_probreg.engines.outputs import (
    DISPLACEMENT_DESCRIPTION,
    OUTPUT_NAMES,
    SAMPLED_NAMES,
    save_nifti,
    write_outputs,
)
from monai_probreg.engines.registration import evaluate_pair, register_pair
from monai_probreg.engines.score_files import summary_table, write_scores
from monai_probreg.metrics.scores import PairScores, score_pair
from monai_probreg.uncertainty.posterior_maps import PosteriorMaps
from monai_probreg.weights.loading import load_weights

LABELS = (21, 22, 181)


pytestmark = pytest.mark.usefixtures("single_thread")


def _identity_net(**kwargs) -> ProbRegNet:
    """A ProbRegNet whose posterior mean is exactly 0 (zeroed mean head): the identity registration."""
    torch.manual_seed(0)
    net = ProbRegNet(network_size=(16, 16, 16), **kwargs)
    with torch.no_grad():
        net.unet.mean_head.weight.zero_()
        net.unet.mean_head.bias.zero_()
    return net


def _output(displacement: torch.Tensor, log_var: float = -4.0) -> RegistrationOutput:
    """A RegistrationOutput of one 3-d pair around ``displacement`` (1, 3, *S); velocity grid = S / 2."""
    size = displacement.shape[2:]
    vel = torch.zeros(1, 3, *(n // 2 for n in size))
    return RegistrationOutput(
        torch.rand(1, 1, *size), displacement, vel, vel, torch.full_like(vel, log_var), None, None
    )


def _box_labels(shape, start: int) -> torch.Tensor:
    """(1, 1, *shape) int16: label 21 in a box [start, start + 6) along axis 0, [3, 9) along axes 1, 2."""
    labels = torch.zeros(1, 1, *shape, dtype=torch.int16)
    labels[0, 0, start : start + 6, 3:9, 3:9] = 21
    labels[0, 0, start : start + 3, 3:9, 3:9] = 22
    return labels


# ---------------------------------------------------------------------------------------------- registering


def test_register_pair_uses_mean_velocity_and_restores_training_mode():
    torch.manual_seed(0)
    net = ProbRegNet(network_size=(16, 16, 16)).train()
    moving, fixed = torch.rand(1, 1, 24, 24, 24), torch.rand(1, 1, 24, 24, 24)
    out = register_pair(net, MetaTensor(moving), MetaTensor(fixed))
    assert net.training, "register_pair must restore the caller's train mode"
    assert torch.equal(out.velocity, out.velocity_mean), "eval mode integrates the posterior mean"
    assert out.displacement.shape == (1, 3, 24, 24, 24)  # native grid, although the UNet ran at 16^3
    assert out.displacement.is_inference() and not isinstance(out.displacement, MetaTensor)
    again = register_pair(net, moving, fixed)
    assert torch.equal(again.displacement, out.displacement), "deterministic: no sampling at inference"


def test_load_weights_round_trip_and_missing_file(tmp_path):
    source = ProbRegNet(network_size=(16, 16, 16))
    torch.save(source.state_dict(), tmp_path / "model.pt")
    net = load_weights(ProbRegNet(network_size=(16, 16, 16)), tmp_path / "model.pt")
    assert not net.training
    for (name, a), (_, b) in zip(source.state_dict().items(), net.state_dict().items()):
        assert torch.equal(a, b), name
    missing = tmp_path / "nowhere" / "model.pt"
    with pytest.raises(FileNotFoundError, match=str(missing)):
        load_weights(ProbRegNet(), missing)


def test_labelled_pairs_says_clearly_when_there_are_no_labels(tmp_path):
    from conftest import make_tiny_dataset

    root = make_tiny_dataset(tmp_path / "unlabelled", num_subjects=2, with_labels=False)
    with pytest.raises(ValueError, match="no labels/<id>.nii.gz matches an image.*needs labels"):
        labelled_pairs(index_dataset(root))


# ---------------------------------------------------------------------------------------------- writing


def test_write_outputs_files_shapes_and_displacement_convention(tmp_path):
    shape = (12, 10, 8)
    disp = torch.zeros(1, 3, *shape)
    for k in range(3):
        disp[:, k] = 0.25 * (k + 1)  # a translation: component k is 0.25 (k + 1) voxels along array axis k
    affine = np.array([[0.0, 0.0, 1.5, -7.0], [-1.0, 0.0, 0.0, 3.0], [0.0, 2.0, 0.0, 11.0], [0.0, 0.0, 0.0, 1.0]])
    labels = _box_labels(shape, 2)
    written = write_outputs(tmp_path, "S99", _output(disp, log_var=-4.0), torch.as_tensor(affine), labels)

    unsampled = [n for n in OUTPUT_NAMES if n not in SAMPLED_NAMES]  # no PosteriorMaps given: no sampled maps
    assert set(written) == set(unsampled)
    assert sorted(p.name for p in (tmp_path / "S99").iterdir()) == sorted(f"{n}.nii.gz" for n in unsampled)
    images = {name: nib.load(path) for name, path in written.items()}
    for name, image in images.items():
        np.testing.assert_allclose(image.affine, affine, atol=1e-6, err_msg=name)  # float32 header: 1e-6
        np.testing.assert_allclose(image.get_qform(), affine, atol=1e-6, err_msg=name)
        assert image.shape == (shape if name != "displacement" else (*shape, 1, 3)), name
    field = images["displacement"]
    assert field.header.get_intent()[0] == "vector"
    assert field.header["descrip"].item().decode() == DISPLACEMENT_DESCRIPTION
    data = field.get_fdata()
    for k in range(3):
        np.testing.assert_array_equal(data[..., 0, k], 0.25 * (k + 1))  # exact: binary fractions in float32
    # a translation has |J| = 1 everywhere (one-sided border differences of a constant are exact)
    np.testing.assert_array_equal(images["jacobian"].get_fdata(), 1.0)
    # entropy of N(0, e^-4) per component, 3 components: 3/2 (log 2 pi e - 4); float32: 1e-5
    np.testing.assert_allclose(images["entropy"].get_fdata(), 1.5 * (math.log(2 * math.pi * math.e) - 4.0), atol=1e-5)
    warped_label = np.asarray(images["warped_label"].dataobj)
    assert warped_label.dtype == np.int16 and set(np.unique(warped_label)) <= {0, 21, 22}


def test_write_outputs_takes_the_calibrated_maps(tmp_path):
    shape = (12, 10, 8)
    maps = PosteriorMaps(torch.full(shape, 2.5), torch.full(shape, 0.75), torch.full(shape, 0.5))
    written = write_outputs(
        tmp_path,
        "S98",
        _output(torch.zeros(1, 3, *shape), log_var=-4.0),
        np.eye(4),
        _box_labels(shape, 2),
        OUTPUT_NAMES,
        maps,
    )
    assert set(written) == set(OUTPUT_NAMES)
    for name, value in (("entropy", 2.5), ("displacement_std", 0.75), ("label_entropy", 0.5)):
        np.testing.assert_array_equal(nib.load(written[name]).get_fdata(), value)
    no_labels = write_outputs(
        tmp_path,
        "S97",
        _output(torch.zeros(1, 3, *shape), log_var=-4.0),
        np.eye(4),
        None,
        OUTPUT_NAMES,
        maps._replace(label_entropy=None),
    )
    assert "label_entropy" not in no_labels and "warped_label" not in no_labels


def test_files_are_written_atomically(tmp_path, monkeypatch):
    target = tmp_path / "out" / "map.nii.gz"
    save_nifti(target, np.zeros((4, 4, 4), np.float32), np.eye(4))
    before = target.read_bytes()

    def fails_half_way(image, filename):
        Path(filename).write_bytes(b"half a NIfTI")
        raise OSError("disk full")

    monkeypatch.setattr(nib, "save", fails_half_way)
    with pytest.raises(OSError, match="disk full"):
        save_nifti(target, np.ones((4, 4, 4), np.float32), np.eye(4))
    assert target.read_bytes() == before, "a failed write must leave the previous file untouched"
    assert [p.name for p in target.parent.iterdir()] == ["map.nii.gz"], "no temporary file may be left behind"


def _write_oblique_dataset(root: Path, shape=(30, 28, 20)) -> np.ndarray:
    """An atlas with permuted, flipped, anisotropic axes (not a multiple of 16: preprocessing pads every axis),
    registered to itself: images/A01 is a copy of the atlas. Returns the atlas affine."""
    affine = np.array([[0.0, 0.0, -1.5, 10.0], [-1.0, 0.0, 0.0, 5.0], [0.0, 2.0, 0.0, -3.0], [0.0, 0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    image = rng.uniform(0.0, 300.0, size=shape).astype(np.float32)
    labels = rng.choice(np.array([0, *LABELS], dtype=np.uint8), size=shape)
    for sub, name, data in (
        ("atlas", "A_image", image),
        ("atlas", "A_label", labels),
        ("images", "A01", image),
        ("labels", "A01", labels),
    ):
        (root / sub).mkdir(parents=True, exist_ok=True)
        nib.save(nib.Nifti1Image(data, affine), root / sub / f"{name}.nii.gz")
    return affine


def test_identity_registration_overlays_the_atlas_in_world_coordinates(tmp_path):
    root = tmp_path / "data"
    _write_oblique_dataset(root)
    item = registration_transforms(with_labels=True)(pair_dicts(index_dataset(root))[0])
    out = register_pair(_identity_net(), item["moving"][None], item["fixed"][None])
    assert float(out.displacement.abs().max()) == 0.0
    written = write_outputs(tmp_path / "out", "A01", out, item["fixed"].affine, item["moving_label"][None])

    atlas_image = nib.load(root / "atlas" / "A_image.nii.gz")
    atlas_label = nib.load(root / "atlas" / "A_label.nii.gz")
    warped, warped_label = nib.load(written["warped"]), nib.load(written["warped_label"])
    assert warped.shape == warped_label.shape == (32, 32, 32)

    # the written affine is the atlas' RAS (closest canonical) affine, shifted by the symmetric padding
    canonical = nib.as_closest_canonical(atlas_image)
    pad_before = [(32 - n) // 2 for n in canonical.shape]
    shift = np.eye(4)
    shift[:3, 3] = -np.asarray(pad_before, dtype=float)
    np.testing.assert_allclose(warped.affine, canonical.affine @ shift, atol=1e-6)  # float32 header: 1e-6

    # every written voxel, mapped through world coordinates into the atlas file, holds the atlas' value there
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in warped.shape], indexing="ij"), -1).reshape(-1, 3)
    world = ijk @ warped.affine[:3, :3].T + warped.affine[:3, 3]
    src = (world - atlas_image.affine[:3, 3]) @ np.linalg.inv(atlas_image.affine[:3, :3]).T
    np.testing.assert_allclose(src, np.round(src), atol=1e-4)  # voxel centres coincide (float32 affine: 1e-4)
    src = np.round(src).astype(int)
    inside = np.all((src >= 0) & (src < np.asarray(atlas_image.shape)), axis=1)
    assert inside.sum() == np.prod(atlas_image.shape), "each atlas voxel appears exactly once"
    i, j, k = src[inside].T
    got_label = np.asarray(warped_label.dataobj).reshape(-1)
    np.testing.assert_array_equal(got_label[inside], np.asarray(atlas_label.dataobj)[i, j, k])
    assert not got_label[~inside].any(), "padding is background"

    raw = atlas_image.get_fdata()
    lo, hi = np.percentile(raw, [0.5, 99.5])
    expected = np.clip((raw - lo) / (hi - lo), 0.0, 1.0)
    got = warped.get_fdata().reshape(-1)
    # float32 percentiles and warp sampling at voxel centres through normalised coordinates: 1e-4
    np.testing.assert_allclose(got[inside], expected[i, j, k], atol=1e-4)
    assert np.abs(got[~inside]).max() == 0.0


# ---------------------------------------------------------------------------------------------- scoring


def test_score_pair_translation_realigns_shifted_labels():
    shape = (16, 12, 12)
    fixed, moving = _box_labels(shape, 4), _box_labels(shape, 6)  # moving = fixed shifted +2 along axis 0
    disp = torch.zeros(1, 3, *shape)
    disp[:, 0] = 2.0  # warped[x] = moving[x + 2]: the box moves back to index 4
    registered = score_pair(disp, moving, fixed, runtime_s=0.5)
    baseline = score_pair(None, moving, fixed)
    assert registered.dice == {21: 1.0, 22: 1.0} and registered.mean_dice == 1.0
    assert (registered.num_folding, registered.percent_folding, registered.std_log_jacobian) == (0, 0.0, 0.0)
    assert registered.runtime_s == 0.5
    assert baseline.dice == label_dice(moving, fixed)
    assert baseline.mean_dice == pytest.approx(sum(baseline.dice.values()) / 2, abs=1e-12) and baseline.mean_dice < 1


def test_score_pair_counts_folding():
    shape = (8, 8, 8)
    disp = torch.zeros(1, 3, *shape)
    disp[0, 0] = -2.0 * torch.arange(8.0).view(8, 1, 1)  # u_0 = -2 x_0: |J| = 1 - 2 = -1 everywhere
    labels = _box_labels(shape, 1)
    scores = score_pair(disp, labels, labels)
    assert scores.num_folding == 8**3 and scores.percent_folding == 100.0


def test_evaluate_pair_identity_model_keeps_the_baseline():
    shape = (16, 16, 16)
    fixed_label, moving_label = _box_labels(shape, 4), _box_labels(shape, 6)
    image = torch.rand(1, 1, *shape)
    registered, baseline = evaluate_pair(_identity_net(), image, image, moving_label, fixed_label)
    assert registered.dice == baseline.dice and registered.num_folding == 0
    assert registered.runtime_s > 0 and baseline.runtime_s == 0
    assert set(registered.dice) == {21, 22}  # the labels present in the fixed (atlas) map


def test_write_scores_csv_summary_and_table(tmp_path):
    rows = [
        ("S01", PairScores({21: 0.8, 22: 0.6}, 0.7, 3, 0.1, 0.2, 1.0), PairScores({21: 0.5, 22: 0.3}, 0.4, 0, 0, 0, 0)),
        ("S02", PairScores({21: 0.9, 22: math.nan}, 0.9, 1, 0.05, 0.3, 2.0), PairScores({21: 0.6}, 0.6, 0, 0, 0, 0)),
    ]
    summary = write_scores(
        tmp_path, rows, {"model_file": "m.pt", "network_size": (16, 16, 16), "device": torch.device("cpu")}
    )
    with open(tmp_path / "scores.csv") as f:
        table = list(csv.DictReader(f))
    assert [r["id"] for r in table] == ["S01", "S02"]
    assert float(table[0]["mean_dice"]) == 0.7 and float(table[1]["mean_dice_no_registration"]) == 0.6
    assert float(table[0]["dice_22"]) == 0.6 and table[1]["dice_22"] == "nan"
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["num_subjects"] == 2
    assert summary["registered"]["mean_dice"] == pytest.approx({"mean": 0.8, "std": 0.1}, abs=1e-12)
    assert summary["no_registration"]["mean_dice"] == pytest.approx({"mean": 0.5, "std": 0.1}, abs=1e-12)
    assert summary["dice_per_label"]["22"] == pytest.approx({"registered": 0.6, "no_registration": 0.3}, abs=1e-12)
    assert summary["config"] == {"model_file": "m.pt", "network_size": [16, 16, 16], "device": "cpu"}
    text = summary_table(summary)
    assert "2 subjects" in text and "0.800 +- 0.100" in text and "0.500 +- 0.100" in text
    with pytest.raises(ValueError, match="no scored subjects"):
        write_scores(tmp_path, [])


def test_write_outputs_only_the_requested_maps(tmp_path):
    out = _output(torch.zeros(1, 3, 6, 6, 6))
    written = write_outputs(
        tmp_path, "S1", out, np.eye(4), _box_labels((6, 6, 6), 0), names=("jacobian", "warped_label")
    )
    assert sorted(p.name for p in (tmp_path / "S1").iterdir()) == ["jacobian.nii.gz", "warped_label.nii.gz"]
    assert set(written) == {"jacobian", "warped_label"}
    assert write_outputs(tmp_path, "S2", out, np.eye(4), None, names=("warped_label",)) == {}  # no labels: skipped
    with pytest.raises(ValueError, match="unknown output names.*'jacobians'"):
        write_outputs(tmp_path, "S3", out, np.eye(4), names=("jacobians",))
