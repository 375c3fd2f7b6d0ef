"""benchmarks/peak_memory.py: the peak of a fresh process as the kernel counts it, and a clean skip without the maps
(the real run is the benchmark itself)."""

from __future__ import annotations

import sys

from bench_helpers import load_benchmark

peak_memory = load_benchmark("peak_memory")


def test_the_peak_of_a_process_that_holds_200_mb_is_counted():
    """A child that touches 200 MB: its peak resident memory is at least that, and the wall time is positive."""
    held = 200 * 1024**2
    gigabytes, seconds = peak_memory.peak_rss(
        [sys.executable, "-c", f"b = bytearray({held}); b[::4096] = b'1' * len(b[::4096])"]
    )
    assert gigabytes >= held / 1e9 and seconds > 0


def test_without_the_label_maps_it_skips(tmp_path, capsys):
    assert peak_memory.main(["--label-maps", str(tmp_path / "none"), "--out-dir", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().out.startswith("skipped:")
    assert not (tmp_path / "out").exists()
