"""benchmarks/maps_speed.py: a baseline source without the package is refused before anything runs."""

from __future__ import annotations

import pytest
from bench_helpers import load_benchmark

maps_speed = load_benchmark("maps_speed")


def test_a_baseline_source_without_the_package_is_refused(tmp_path):
    dataset = tmp_path / "dataset"
    (dataset / "images").mkdir(parents=True)
    with pytest.raises(SystemExit, match="no monai_probreg package there"):
        maps_speed.main(
            [
                "--dataset-dir",
                str(dataset),
                "--baseline-source",
                str(tmp_path / "empty"),
                "--out-dir",
                str(tmp_path / "out"),
            ]
        )
    assert not (tmp_path / "out").exists()
