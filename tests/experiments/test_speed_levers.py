"""experiments/speed_levers.py on a tiny random pair: every lever, stage and peak is measured and written (never the
speed itself: these sizes say nothing about it)."""

from __future__ import annotations

import json

from conftest import load_script

speed_levers = load_script("experiments", "speed_levers")


def test_synthetic_run_writes_every_measurement(tmp_path, monkeypatch, single_thread):
    monkeypatch.setattr(speed_levers, "MATMUL_SIZE", 32)  # the peak's matmul at its real size takes seconds
    argv = ["--synthetic", "--size", "32", "32", "32", "--repeats", "1", "--samples", "2", "--no-compile"]
    assert speed_levers.main([*argv, "--out-dir", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "speed_levers.json").read_text())
    assert set(result["levers"]) == {
        *speed_levers.LEVER_SETTINGS,
        "all levers, torch.no_grad instead of inference_mode",
    }
    assert all(t > 0 for t in result["levers"].values())
    assert list(result["stages"]["plain"]) == list(result["stages"]["default"])
    assert result["samples"]["k"] == 2 and result["unet_macs"] > 0 and "compile" not in result
    assert result["markdown"].count("\n| ") == len(result["levers"]) + len(result["stages"]["plain"]) + 1
