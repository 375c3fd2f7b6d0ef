"""benchmarks/refinement_levers.py: variants parsed from the command line, and the script end to end on tiny
FreeSurfer-labelled phantoms named like SynthSeg's training maps (no LPBA40): one row per variant, a finer grid run."""

from __future__ import annotations

import json

import numpy as np
from bench_helpers import load_benchmark
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

levers = load_benchmark("refinement_levers")


def test_only_training_label_maps_and_subjects_are_used():
    maps = {name for pair in levers.SYNTH_PAIRS for name in pair.split(":")}
    assert all(int(name[-2:]) <= 10 for name in maps)  # 11-12: the generalisation benchmark's; 13-20: left alone
    subjects = {s for pair in levers.LPBA40_PAIRS for s in pair.split(":")}
    assert not subjects & {"S11", "S14", "S16", "S21", "S28", "S29"}  # train.yaml's val_ids


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
    assert result["rows"]["network"]["refine_s"] == 0.0 and result["rows"]["f"]["refine_s"] > 0.0
    assert "| f |" in result["markdown"]
