"""experiments/lncc_speed.py on tiny grids: one row per size, the two losses agree, the JSON and table are written."""

from __future__ import annotations

import json

import pytest
from conftest import load_script

lncc_speed = load_script("experiments", "lncc_speed")


def test_rows_agree_and_are_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(lncc_speed, "SIZES", {"network grid": (12, 14, 10), "twice finer": (24, 28, 20)})
    assert lncc_speed.main(["--threads", "1", "--repeats", "1", "--out-dir", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "lncc_speed.json").read_text())
    assert list(result["rows"]) == ["network grid", "twice finer"]
    for row in result["rows"].values():
        assert set(row["seconds"]) == {"MONAI", "pooled"} and row["speedup"] > 0
        assert row["value_difference"] < 1e-5
        assert row["gradient_max_difference"] < 1e-4 * row["gradient_max"]
    assert "| twice finer 24x28x20 |" in capsys.readouterr().out


def test_no_repeat_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--repeats must be >= 1; got 0"):
        lncc_speed.main(["--repeats", "0", "--out-dir", str(tmp_path)])
