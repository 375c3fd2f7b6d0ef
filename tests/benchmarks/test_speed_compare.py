"""benchmarks/speed_compare.py on the tiny synthetic dataset with random weights: the wiring, never the speed.

Pins that every method runs in its own process and comes back with times, peak memory and (trained rows) scores,
that ratios are taken against ours (mean) of the same run, that a failed or skipped method keeps a row saying why,
and the JSON / PNG outputs. No time is asserted (the targets are shown by the benchmark, not tested).
"""

from __future__ import annotations

import json
import math

import pytest
from bench_helpers import load_benchmark
from conftest import bundle_with_random_model

speed_compare = load_benchmark("speed_compare")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    from bench_helpers import REPO

    from monai_probreg import ProbRegNet
    from monai_probreg.weights.settings import write_network_settings

    root = bundle_with_random_model(tmp_path_factory.mktemp("bundle"), REPO / "bundle", network_size=(16, 16, 16))
    # as shipped: the settings sidecar next to the weights, so the trained row passes the settings check with the
    # trained grid and only then scales it with the padded input
    write_network_settings(root / "models" / "model.pt", ProbRegNet(network_size=(16, 16, 16)))
    return root


def test_runs_each_method_in_its_own_process_and_writes_json_and_png(tmp_path, tiny_dataset, bundle, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    out = tmp_path / "out"
    code = speed_compare.main(
        [
            "--dataset-dir",
            str(tiny_dataset),
            "--bundle-root",
            str(bundle),
            "--subjects",
            "T01",
            "T02",
            "--size",
            "32",
            "32",
            "48",
            "--methods",
            "ours_mean",
            "ours_mean_no_reuse",
            "ours_trained",
            "--repeats",
            "1",
            "--threads",
            "1",
            "--override",
            "network_size=[16,16,16]",
            "--out-dir",
            str(out),
        ]
    )
    assert code == 0
    report = json.loads((out / "speed_compare.json").read_text())
    assert (out / "speed_compare.png").stat().st_size > 0
    assert report["settings"]["size"] == [32, 32, 48] and report["settings"]["native_grid"] == [32, 32, 32]
    rows = {row["key"]: row for row in report["rows"]}
    assert set(rows) == {"ours_mean", "ours_mean_no_reuse", "ours_trained"}
    assert all(r["status"] == "ok" for r in rows.values())
    # ours as monai-probreg and the bundle run it (freed memory kept for reuse), and the same without that lever
    reuse = {key: report["results"][key]["memory_reuse"] for key in rows}
    assert reuse == {"ours_mean": True, "ours_mean_no_reuse": False, "ours_trained": True}
    assert rows["ours_mean"]["ratio_to_ours"] == 1.0
    for row in rows.values():
        assert row["median_s"] > 0 and row["peak_rss_gb"] > 0 and row["threads"] == 1
    for key in rows:  # the timed runs' peak, the scoring after them excluded; the process's peak kept apart
        result = report["results"][key]
        assert result["peak_rss_scope"] == "timed runs only"
        assert 0 < result["peak_rss_mb"] <= result["process_peak_rss_mb"]
    trained = report["results"]["ours_trained"]
    # network grid scaled with the input (16^3 for the native 32^3 -> 16 x 16 x 24 for 32 x 32 x 48), rounded to
    # a multiple of the divisor 16
    assert trained["network_size"] == [16, 16, 32]
    assert set(trained["times_s"]) == {"T01", "T02"} and all(len(t) == 1 for t in trained["times_s"].values())
    for scores in trained["scores"].values():
        assert 0 <= scores["mean_dice"] <= 1 and scores["num_folding"] == 0
        assert scores["max_abs_diff_vs_fp32_voxels"] < 0.05  # random weights: displacements ~1e-4 voxels
    assert 0 <= rows["ours_trained"]["mean_dice"] <= 1


def test_rows_keep_failures_and_ratios_come_from_the_same_run():
    results = {
        "ours_mean": {"status": "ok", "median_s": 0.5, "peak_rss_mb": 1024.0, "threads": 2, "scores": {}},
        "voxelmorph": {"status": "ok", "median_s": 10.0, "peak_rss_mb": 4096.0, "threads": 2, "scores": {}},
        "ants": {"status": "skipped: antspyx not installed"},
    }
    rows = speed_compare.summarise(results, k=10)
    assert [r["key"] for r in rows] == ["ours_mean", "voxelmorph", "ants"]  # table order, whatever came first
    assert rows[1]["ratio_to_ours"] == 20.0 and rows[1]["peak_rss_gb"] == 4.0
    assert rows[0]["mean_dice"] is None
    table = speed_compare.markdown(rows)
    assert "| ANTs SyN" in table and "skipped: antspyx not installed" in table
    assert "| MONAI VoxelMorph() (untrained) | 10 | 20.0 | 4.00 | – | – | 2 |" in table
    without_ours = speed_compare.summarise({"voxelmorph": results["voxelmorph"]}, k=10)
    assert without_ours[0]["ratio_to_ours"] is None and not math.isnan(without_ours[0]["median_s"])
