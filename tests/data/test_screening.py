"""monai_probreg.data.screening: failure markers, the filtering loader, failed.csv and the exit status."""

from __future__ import annotations

import pytest
from monai.data import DataLoader
from monai.transforms import Lambda

from monai_probreg.data.screening import (
    FAILED_KEY,
    InputFailures,
    SkipBadInputs,
    SkipFailedBatches,
    input_error_in,
    read_failures,
)
from monai_probreg.utils.errors import InputError


def _check(item: dict) -> dict:
    if item["id"] == "bad":
        raise InputError("moving image 'bad.nii.gz': expected a complete image file, got a truncated one")
    if item["id"] == "bug":
        raise KeyError("not an input problem")
    return {**item, "value": 1.0}


def test_input_error_is_found_through_wrapping():
    try:
        try:
            raise InputError("x: expected a, got b")
        except InputError as inner:
            raise RuntimeError("applying transform") from inner
    except RuntimeError as outer:
        assert isinstance(input_error_in(outer), InputError)
    assert input_error_in(ValueError("plain")) is None


def test_bad_items_become_markers_and_are_recorded():
    data = [{"id": "a"}, {"id": "bad"}, {"id": "c"}]
    dataset = SkipBadInputs(data, transform=Lambda(_check))
    assert dataset[1] == {
        "id": "bad",
        FAILED_KEY: str(InputError("moving image 'bad.nii.gz': expected a complete image file, got a truncated one")),
    }
    failures = InputFailures()
    batches = list(SkipFailedBatches(DataLoader(dataset, batch_size=1), failures))
    assert [b["id"] for b in batches] == [["a"], ["c"]]
    assert failures.items == [("bad", dataset[1][FAILED_KEY])]


def test_other_exceptions_are_not_swallowed():
    dataset = SkipBadInputs([{"id": "bug"}], transform=Lambda(_check))
    with pytest.raises(Exception) as info:
        dataset[0]
    assert input_error_in(info.value) is None


def test_finish_writes_failed_csv_and_exits_1(tmp_path, capsys):
    failures = InputFailures()
    failures.add("S01", "moving image 'S01.nii.gz': expected finite voxels, got 3 NaN")
    with pytest.raises(SystemExit) as info:
        failures.finish(tmp_path)
    assert info.value.code == 1
    assert read_failures(tmp_path / "failed.csv") == failures.items
    assert "S01" in capsys.readouterr().out
    failures.finish(tmp_path / "elsewhere", exit_on_failure=False)  # no exit, still written
    assert (tmp_path / "elsewhere" / "failed.csv").is_file()


def test_finish_without_failures_removes_a_stale_file(tmp_path):
    (tmp_path / "failed.csv").write_text("id,reason\nold,stale\n")
    InputFailures().finish(tmp_path)
    assert not (tmp_path / "failed.csv").exists()
    assert read_failures(tmp_path / "failed.csv") == []
