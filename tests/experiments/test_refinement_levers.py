"""experiments/refinement_levers.py: variants parsed from the command line, the identity cases' score on a known field,
and the script end to end on tiny FreeSurfer-labelled phantoms named like SynthSeg's training maps (no LPBA40): one
row per variant, a finer grid run, the identity case scored."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import FIXED_LPS, asymmetric_phantom, load_script, save_lps

from monai_probreg.registration.output_folder import write_field

levers = load_script("experiments", "refinement_levers")


def test_only_training_label_maps_and_subjects_are_used():
    maps = {name for pair in levers.SYNTH_PAIRS for name in pair.split(":")}
    assert all(int(name[-2:]) <= 10 for name in maps)  # 11-12: the generalisation benchmark's; 13-20: left alone
    subjects = {s for pair in levers.LPBA40_PAIRS for s in pair.split(":")}
    assert not subjects & {"S11", "S14", "S16", "S21", "S28", "S29"}  # train.yaml's val_ids
    assert not set(levers.IDENTITY_SCANS) & {"S11", "S14", "S16", "S21", "S28", "S29"}
    assert all(int(name[-2:]) <= 10 for name in levers.IDENTITY_MAPS)


def test_the_identity_score_is_the_median_displacement_inside_the_mask(tmp_path):
    """A field of (3, 4, 0) mm (length 5) inside the mask, (30, 40, 0) outside, on a grid whose three axes differ in
    length (a RAS array): the score is 5, read in the mask's index order; a mask of another shape is refused."""
    shape = (6, 5, 4)
    mask = np.zeros(shape, bool)
    mask[1:4, 2:5, 1:3] = True
    field = np.where(mask[..., None], [3.0, 4.0, 0.0], [30.0, 40.0, 0.0]).astype(np.float32)
    field[1, 2, 1] = [6.0, 8.0, 0.0]  # one voxel of 10 mm inside: the median keeps 5
    path = write_field(tmp_path / "warp.nii.gz", field, FIXED_LPS)
    assert levers.invented_displacement_mm(path, mask) == pytest.approx(5.0, abs=1e-6)
    with pytest.raises(ValueError, match="expected a field of shape"):
        levers.invented_displacement_mm(path, mask.transpose(2, 1, 0))


def test_the_script_runs_every_variant_on_the_pairs_it_finds(tmp_path):
    maps = tmp_path / "maps"
    maps.mkdir()
    for n, name in enumerate(levers.SYNTH_PAIRS[0].split(":")):
        _, labels = asymmetric_phantom((40, 44, 36), seed=n)
        fs = np.zeros((56, 60, 52), np.int16)
        fs[8:48, 8:52, 8:44] = np.select([labels == 1, labels == 2, labels == 3, labels == 4], [2, 41, 12, 507], 0)
        save_lps(maps / f"{name}.nii.gz", fs, FIXED_LPS)
    out = tmp_path / "out"
    argv = ["--label-maps", str(maps), "--dataset-dir", str(tmp_path / "none"), "--threads", "1"]
    argv += ["--out-dir", str(out), "--variants", "network", "c=num_iterations:2"]
    argv += ["f=num_iterations:2,velocity_grid_factor:2"]
    assert levers.main(argv) == 0
    result = json.loads((out / "refinement_levers.json").read_text())
    assert set(result["rows"]) == {"network", "c", "f"}
    for row in result["rows"].values():
        assert len(row["per_pair"]) == 2 and row["lpba40"] is None and 0.0 < row["synthetic"] <= 1.0
        assert list(row["identity_mm"]) == ["identity synth 01"] and 0.0 <= row["identity"] < 20.0
    assert result["rows"]["network"]["refine_s"] == 0.0 and result["rows"]["f"]["refine_s"] > 0.0
    assert "| f |" in result["markdown"] and "identity: invented mm" in result["markdown"]
