"""Same input, same output: ``monai-probreg register`` twice on the same scan and options writes the same files.

Run with 2 threads, where ITK's multi-threaded Mattes metric would otherwise sum in thread order
(monai_probreg.spatial.affine's docstring).
"""

from __future__ import annotations

import json
from pathlib import Path

import itk
import numpy as np
import pytest
from conftest import BUNDLE_DIR, FAST_AFFINE, FIXED_LPS, moved_phantom, run_cli, save_lps, tiny_bundle

from monai_probreg.spatial.physical import affine_from_itk, apply_affine, grid_points
from monai_probreg.utils.provenance import file_sha256

_COMPARED = (
    "affine.tfm",
    "warp.nii.gz",
    "inverse_warp.nii.gz",
    "warped.nii.gz",
    "warped_label.nii.gz",
    "jacobian.nii.gz",
    "displacement_std.nii.gz",
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("repro")
    case = moved_phantom([-9.0, 11.0, 6.0], [3.0, 4.0, -2.0])
    fixed = save_lps(root / "fixed.nii.gz", case.image, FIXED_LPS)
    fixed_label = save_lps(root / "fixed_label.nii.gz", case.labels, FIXED_LPS)
    moving = save_lps(root / "moving.nii.gz", np.round(case.moved * 2500 + 100).astype(np.int16), case.grid)
    moving_label = save_lps(root / "moving_label.nii.gz", case.moved_labels.astype(np.uint8), case.grid)
    bundle = tiny_bundle(root / "bundle", BUNDLE_DIR)
    return (
        case,
        root,
        [
            "--moving",
            str(moving),
            "--moving-label",
            str(moving_label),
            "--fixed",
            str(fixed),
            "--fixed-label",
            str(fixed_label),
            "--bundle-root",
            str(bundle),
            "--samples",
            "2",
            "--no-qc",
            *FAST_AFFINE,
        ],
    )


def _register(scene, name: str, *extra: str) -> tuple[Path, dict]:
    _, root, args = scene
    out = root / name
    result = run_cli("register", *args, "--out", str(out), *extra, threads=2)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    summary.pop("timings_s")
    return out, summary


def test_the_same_run_twice_writes_the_same_files(scene):
    first, first_summary = _register(scene, "first")
    second, second_summary = _register(scene, "second")
    for name in _COMPARED:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    assert first_summary == second_summary


def test_summary_records_what_reproduces_the_run(scene):
    _, summary = _register(scene, "record", "--seed", "3")
    record = summary["reproducibility"]
    assert record["seed"] == 3 and record["affine_seed"] == 3 and record["deterministic_affine"] is True
    assert summary["affine"]["settings"]["seed"] == 3 and summary["uncertainty"]["seed"] == 3
    assert record["weights_sha256"] == file_sha256(summary["model"]["model_file"])
    for library in ("monai-probreg", "torch", "monai", "itk", "numpy", "nibabel"):
        assert record["versions"][library], library


def test_another_seed_still_recovers_the_transform(scene):
    case = scene[0]
    brain = grid_points(case.image.shape, FIXED_LPS)[case.labels > 0]
    for seed in ("0", "7"):
        out, summary = _register(scene, f"seed{seed}", "--seed", seed)
        affine = affine_from_itk(itk.transformread(str(out / "affine.tfm"))[0])
        error = np.linalg.norm(apply_affine(affine, brain) - apply_affine(case.truth, brain), axis=-1)
        assert error.mean() < 0.4 and error.max() < 0.8, seed  # the accuracy check of test_main's round trip
        assert summary["dice"]["mean"] > 0.85, seed


def test_nondeterministic_affine_is_recorded(scene):
    _, summary = _register(scene, "fast", "--affine-backend", "itk", "--nondeterministic-affine")
    assert summary["reproducibility"]["deterministic_affine"] is False
    assert summary["affine"]["settings"]["deterministic"] is False
