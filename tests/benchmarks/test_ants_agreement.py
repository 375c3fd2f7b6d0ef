"""benchmarks/ants_agreement.py: the disagreement of two fields by hand, its table, and a clean skip without the moving
scan (the real run is the benchmark itself; the fields are read by monai_probreg.spatial.volume_io.read_field)."""

from __future__ import annotations

import numpy as np
import pytest
from bench_helpers import load_benchmark

ants_agreement = load_benchmark("ants_agreement")


def test_two_fields_disagree_by_the_length_of_their_difference_inside_the_mask():
    ours = np.zeros((4, 5, 6, 3))
    theirs = ours.copy()
    theirs[..., 0] = 3.0  # 3 mm apart along the first axis
    theirs[..., 1] = 4.0  # and 4 along the second: 5 mm apart everywhere
    inside = np.zeros((4, 5, 6), bool)
    inside[1:3, 1:4, 2:5] = True
    theirs[~inside] = 100.0  # outside the mask: not counted
    result = ants_agreement.field_disagreement(ours, theirs, inside)
    assert result == {"median_mm": pytest.approx(5.0), "p95_mm": pytest.approx(5.0)}


def test_the_median_and_percentile_follow_the_distances():
    ours = np.zeros((1, 1, 20, 3))
    theirs = ours.copy()
    theirs[0, 0, :, 2] = np.arange(20)  # distances 0..19 mm
    result = ants_agreement.field_disagreement(ours, theirs, np.ones((1, 1, 20), bool))
    assert result["median_mm"] == pytest.approx(9.5) and result["p95_mm"] == pytest.approx(np.percentile(range(20), 95))


@pytest.mark.parametrize(
    ("ours", "theirs", "inside", "match"),
    [
        ((4, 5, 6, 3), (4, 5, 7, 3), (4, 5, 6), "one grid"),
        ((4, 5, 6, 3), (4, 5, 6, 3), (4, 5, 7), "one grid"),
        ((4, 5, 6, 3), (4, 5, 6, 3), None, "no voxel"),
    ],
)
def test_fields_of_two_grids_or_an_empty_mask_are_refused(ours, theirs, inside, match):
    mask = np.zeros((4, 5, 6), bool) if inside is None else np.ones(inside, bool)
    with pytest.raises(ValueError, match=match):
        ants_agreement.field_disagreement(np.zeros(ours), np.zeros(theirs), mask)


def test_the_table_names_each_rows_options():
    result = {
        "moving": "t2.nii.gz",
        "fixed": "mni.nii.gz",
        "rows": {"other-matched": {"median_mm": 1.234, "p95_mm": 5.678, "wall_s": 12.0}},
    }
    table = "\n".join(ants_agreement.markdown(result))
    assert "| --contrast other --match-contrast | 1.23 | 5.68 | 12.0 |" in table


def test_without_the_moving_scan_it_skips(tmp_path, capsys):
    missing = tmp_path / "none.nii.gz"
    assert ants_agreement.main(["--moving", str(missing), "--out-dir", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().out.strip() == f"skipped: no {missing}"
    assert not (tmp_path / "out").exists()
