"""benchmarks/register_real_scan.py: its wiring on the tiny synthetic dataset (random weights), the missing-dataset
exit, and (opt-in) the real-data target of the issue on LPBA40.

The real-data test runs only with ``MONAI_PROBREG_REAL_DATA=1`` and ``../shared/data/lpba40`` present (about three
minutes on 2 CPU cores): a subject moved out of atlas space must come back with a mean Dice within 0.02 of the same
subject given aligned, and ITK must reproduce our warped image from the written field.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from bench_helpers import load_benchmark
from conftest import tiny_bundle

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "benchmarks" / "register_real_scan.py"
LPBA40 = REPO.parent / "shared" / "data" / "lpba40"


register_real_scan = load_benchmark("register_real_scan")


@pytest.fixture(autouse=True)
def _one_itk_thread(monkeypatch, single_thread):
    monkeypatch.setenv("ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS", "1")  # main() sets it; monkeypatch restores it
    monkeypatch.setenv("OMP_NUM_THREADS", "1")


def test_wiring_on_the_tiny_dataset(tmp_path, tiny_dataset, capsys):
    """Structure, not accuracy: a random model and a spherical phantom (rotation not identifiable: none applied)."""
    bundle = tiny_bundle(tmp_path / "bundle", REPO / "bundle")
    argv = [
        "--dataset-dir",
        str(tiny_dataset),
        "--subject",
        "T01",
        "--bundle-root",
        str(bundle),
        "--threads",
        "1",
        "--max-rotation",
        "0",
        "--max-translation",
        "2",
        "--out-dir",
        str(tmp_path / "out"),
        "--no-ants",
        "--in-process",
        "--extra",
        "--affine-levels",
        "2",
        "1",
    ]
    assert register_real_scan.main(argv) == 0
    result = json.loads((tmp_path / "out" / "register_real_scan.json").read_text())
    dice = result["mean_dice"]
    assert all(0 <= dice[k] <= 1 for k in ("aligned_bundle_path", "aligned_command", "misaligned_command"))
    assert result["itk_reproduction"]["max_abs_diff"] <= 1e-5 * result["itk_reproduction"]["intensity_range"]
    assert result["itk_reproduction"]["label_mismatches"] == 0
    assert result["timings_s"]["command_wall"] > result["timings_s"]["total"] > 0
    assert "moved - aligned" in capsys.readouterr().out
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["register_real_scan.json"]  # no image data


@pytest.mark.skipif(os.environ.get("MONAI_PROBREG_REAL_DATA") != "1", reason="set MONAI_PROBREG_REAL_DATA=1 to run")
@pytest.mark.skipif(not LPBA40.is_dir(), reason=f"LPBA40 not found at {LPBA40}")
def test_real_scan_comes_back_to_the_atlas(tmp_path):
    model_file = Path(os.environ.get("MONAI_PROBREG_MODEL_FILE", REPO / "bundle" / "models" / "model.pt"))
    if not model_file.is_file():
        pytest.skip(f"no trained weights at {model_file} (set MONAI_PROBREG_MODEL_FILE)")
    argv = ["--model-file", str(model_file), "--out-dir", str(tmp_path), "--threads", str(os.cpu_count() or 1)]
    assert register_real_scan.main(argv) == 0
    result = json.loads((tmp_path / "register_real_scan.json").read_text())
    assert abs(result["mean_dice"]["misaligned_minus_aligned_command"]) <= 0.02
    assert result["affine_consistency_mm"]["mean"] < 1.0
    reproduction = result["itk_reproduction"]
    assert reproduction["max_abs_diff"] <= 1e-5 * reproduction["intensity_range"]
