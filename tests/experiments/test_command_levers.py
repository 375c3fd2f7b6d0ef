"""experiments/command_levers.py: each in-process row compares two ways of computing the same thing (tiny sizes)."""

from __future__ import annotations

import gzip

from conftest import load_script

command_levers = load_script("experiments", "command_levers")


def test_in_process_rows_agree_and_time_both_sides(monkeypatch):
    monkeypatch.setattr(command_levers, "ATLAS_SHAPE", (9, 8, 7))
    monkeypatch.setattr(command_levers, "MOVING_SHAPE", (6, 5, 4))
    points = command_levers.point_transform_row(1)
    jacobian = command_levers.jacobian_row(1)
    packed = command_levers.gzip_row(1)
    assert points["max_difference_mm"] < 1e-9 and jacobian["max_difference"] < 1e-4
    assert packed["megabytes"]["raw"] == 6 * 5 * 4 * 3 * 4 / 1e6
    assert all(row["before"] > 0 and row["after"] > 0 for row in (points, jacobian, packed))


def test_isal_writes_a_stream_that_gzip_reads():
    from isal import igzip

    data = bytes(range(256)) * 100
    assert gzip.decompress(igzip.compress(data, command_levers.GZIP_LEVEL, mtime=0)) == data
