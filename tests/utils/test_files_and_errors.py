"""Tests of the atomic writer, the temporary-name pattern, file stems and one-line error quoting."""

from __future__ import annotations

from pathlib import Path

import pytest

from monai_probreg.utils.errors import InputError, UntrustedFileError, check_integer, first_line
from monai_probreg.utils.files import (
    PARTIAL_FILE,
    atomic_write,
    file_stem,
    parallel_writes,
    remove_partial_files,
    write_text,
)


def test_atomic_write_replaces_the_file_only_when_complete(tmp_path):
    target = tmp_path / "sub" / "scores.csv"
    write_text(target, "old")
    seen = []

    def write(tmp: str) -> None:
        seen.append((Path(tmp).name, target.read_text()))  # the old file is intact while the new one is written
        Path(tmp).write_text("new")

    atomic_write(target, write)
    assert target.read_text() == "new"
    assert seen[0][1] == "old" and PARTIAL_FILE.fullmatch(seen[0][0]) and seen[0][0].endswith(".csv")
    assert sorted(p.name for p in target.parent.iterdir()) == ["scores.csv"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "model.pt"
    write_text(target, "old")

    def fail(tmp: str) -> None:
        Path(tmp).write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, fail)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["model.pt"]
    assert remove_partial_files(tmp_path) == []


@pytest.mark.parametrize("threads", [1, 3])
def test_parallel_writes_run_every_writer_while_the_body_goes_on(tmp_path, threads):
    import threading

    started = threading.Event()  # the first writer waits for the body: writers and body overlap with threads

    def writer(index: int) -> None:
        if index == 0 and threads > 1:
            assert started.wait(timeout=30)
        write_text(tmp_path / f"{index}.txt", str(index))

    with parallel_writes(threads) as submit:
        for index in range(5):
            submit(lambda index=index: writer(index))
        started.set()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{i}.txt" for i in range(5)]


@pytest.mark.parametrize("threads", [1, 2])
def test_parallel_writes_raise_a_writers_error_after_all_writers_finished(tmp_path, threads):
    import time

    def slow() -> None:
        time.sleep(0.2)
        write_text(tmp_path / "slow.txt", "done")

    def failing() -> None:
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"), parallel_writes(threads) as submit:
        submit(slow)
        submit(failing)  # threads: finishes first, raised only once the slow one is done
    assert (tmp_path / "slow.txt").read_text() == "done"  # not left running into a folder the caller removes


def test_parallel_writes_wait_for_the_writers_when_the_body_fails(tmp_path):
    import time

    def slow() -> None:
        time.sleep(0.2)
        write_text(tmp_path / "slow.txt", "done")

    with pytest.raises(RuntimeError, match="figure"), parallel_writes(2) as submit:
        submit(slow)
        raise RuntimeError("figure failed")
    assert (tmp_path / "slow.txt").read_text() == "done"


@pytest.mark.parametrize(
    "name, stem",
    [
        ("S01.nii.gz", "S01"),
        ("a.b.nii", "a.b"),
        ("scan.nrrd", "scan"),
        ("x.mha", "x"),
        ("notes.txt", "notes"),
        ("S01_image.nii.gz", "S01_image"),
    ],
)
def test_file_stem_strips_the_image_suffix(name, stem):
    assert file_stem(Path("/data") / name) == stem


def test_first_line_quotes_the_first_non_blank_line_within_the_limit():
    assert first_line(ValueError("\n  bad header  \nmore")) == "bad header"
    assert first_line(KeyError()) == "KeyError"
    assert first_line(ValueError("x" * 500)) == "x" * 160
    assert first_line(ValueError("x" * 500), limit=None) == "x" * 500


def test_input_error_is_a_value_error_and_untrusted_an_input_error():
    assert issubclass(InputError, ValueError) and issubclass(UntrustedFileError, InputError)


@pytest.mark.parametrize("value", [0, 3, 10**9])
def test_check_integer_returns_an_integer_at_or_above_the_minimum(value):
    assert check_integer("steps", value, 0) == value


@pytest.mark.parametrize("value", [True, False, 2.0, "2", None, -1])
def test_check_integer_names_the_setting_the_minimum_and_the_value(value):
    with pytest.raises(ValueError, match=rf"^steps must be an integer >= 0; got {value!r}$".replace("(", r"\(")):
        check_integer("steps", value, 0)


def test_library_versions_name_the_packages_own_version(monkeypatch):
    """monai-probreg's entry is the running code's __version__, not its install metadata (stale in an editable
    install after a release)."""
    from importlib import metadata

    import monai_probreg
    from monai_probreg.utils import provenance

    real = metadata.version
    monkeypatch.setattr(provenance.metadata, "version", lambda name: "0.0.1" if name == "monai-probreg" else real(name))
    versions = provenance.library_versions()
    assert versions["monai-probreg"] == monai_probreg.__version__ and versions["torch"] == real("torch")
