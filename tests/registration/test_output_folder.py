"""monai_probreg.registration.output_folder: the output folder is written all or nothing."""

from __future__ import annotations

import pytest

from monai_probreg.registration.output_files import OUTPUT_FILES, OUTPUTS_README
from monai_probreg.registration.output_folder import check_output_dir, staged_output_dir
from monai_probreg.utils.errors import InputError


def test_new_folder_appears_complete(tmp_path):
    out = tmp_path / "a" / "b"  # missing parents are created
    with staged_output_dir(out) as stage:
        (stage / "warped.nii.gz").write_text("x")
        assert not out.exists()  # nothing visible until the end
    assert [p.name for p in out.iterdir()] == ["warped.nii.gz"]
    assert [p.name for p in out.parent.iterdir()] == ["b"]  # no staging folder left


def test_failure_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with staged_output_dir(out) as stage:
            (stage / "warped.nii.gz").write_text("x")
            raise RuntimeError("model failed")
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_an_earlier_run_intact(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "warped.nii.gz").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with staged_output_dir(out, overwrite=True) as stage:
            (stage / "warped.nii.gz").write_text("new")
            raise KeyboardInterrupt
    assert (out / "warped.nii.gz").read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_overwrite_replaces_our_files_and_keeps_others(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "displacement_std.nii.gz").write_text("from a run with --samples")
    (out / "notes.txt").write_text("the user's")
    with staged_output_dir(out, overwrite=True) as stage:
        (stage / "warped.nii.gz").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "warped.nii.gz"]


def test_non_empty_folder_needs_overwrite(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "x").write_text("")
    with pytest.raises(InputError, match="not empty; pass --overwrite"):
        check_output_dir(tmp_path / "out")
    check_output_dir(tmp_path / "out", overwrite=True)
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="is a file"):
        check_output_dir(tmp_path / "file", overwrite=True)


def test_readme_lists_every_output():
    assert all(name in OUTPUTS_README for name in OUTPUT_FILES)
