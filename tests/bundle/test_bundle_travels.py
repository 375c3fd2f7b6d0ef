"""The bundle travels: copied out of this repository into an empty folder (with the package installed, as
metadata.json's required_packages_version names it), inference runs there on a tiny synthetic pair from the bundle's
own default data folder, and ``monai.bundle.load`` of the copy gives the shipped default weights."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import torch
from conftest import BUNDLE_DIR, make_tiny_dataset
from monai.bundle import ConfigParser, load


def _copy(tmp_path):
    target = tmp_path / "elsewhere" / "probreg_bundle"
    shutil.copytree(BUNDLE_DIR, target, ignore=shutil.ignore_patterns("runs", "__pycache__"))
    return target


def test_no_config_points_outside_the_bundle_by_default():
    for config in sorted((BUNDLE_DIR / "configs").glob("*.yaml")):
        code = [line.split("#", 1)[0] for line in config.read_text().splitlines()]  # comments may cite commands
        assert not [line for line in code if "/../" in line], f"{config.name} reaches outside the bundle by default"
    metadata = ConfigParser.load_config_file(str(BUNDLE_DIR / "configs" / "metadata.json"))
    assert "monai-probreg" in metadata["required_packages_version"]  # the package its configs import


def test_a_copied_bundle_runs_inference_from_its_own_data_folder(tmp_path):
    bundle = _copy(tmp_path)
    make_tiny_dataset(bundle / "data", num_subjects=1, shape=(32, 32, 32))  # the configs' default dataset_dir
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "monai.bundle",
        "run",
        "--config_file",
        "configs/inference.yaml",
        "--bundle_root",
        ".",
        "--output_dir",
        str(out),
        "--num_workers",
        "0",
        "--num_samples",
        "2",
    ]
    done = subprocess.run(
        cmd, cwd=bundle, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert done.returncode == 0, done.stderr[-3000:]
    written = sorted(p.name for p in (out / "T01").iterdir())
    assert "warped.nii.gz" in written and "displacement.nii.gz" in written


def test_monai_bundle_load_of_the_copy_gives_the_default_weights(tmp_path):
    bundle = _copy(tmp_path)
    state = load(bundle.name, bundle_dir=str(bundle.parent), model_file="models/model.pt", device="cpu")
    shipped = torch.load(BUNDLE_DIR / "models" / "model.pt", map_location="cpu", weights_only=True)
    assert state.keys() == shipped.keys() and all(torch.equal(state[k], shipped[k]) for k in shipped)
