"""monai_probreg.registration.output_folder: the output folder is written all or nothing."""

from __future__ import annotations

import weakref

import numpy as np
import pytest

from monai_probreg.metrics.jacobian import JacobianStats
from monai_probreg.registration import output_folder
from monai_probreg.registration.compose import Composed
from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_files import OUTPUT_FILES, OUTPUTS_README
from monai_probreg.registration.output_folder import check_output_dir, output_writers, staged_output_dir
from monai_probreg.spatial.affine import AffineResult
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.volume_io import Volume
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


def _composed_fields(shape=(5, 4, 3)) -> Composed:
    """A Composed of a registration's outputs on a small grid, whose fields only it holds."""
    rng = np.random.default_rng(0)
    warp, inverse = (rng.standard_normal((*shape, 3)).astype(np.float32) for _ in range(2))
    maps = {"warped": rng.random(shape, dtype=np.float32)}
    labels = {"warped_label": np.ones(shape, np.uint8)}
    return Composed(warp, inverse, maps, labels, None, JacobianStats(0, 0.0, 0.1))


def test_the_fields_are_written_one_after_the_other_each_let_go_once_written(tmp_path, monkeypatch):
    """One writer writes both fields in turn (each holds two copies of its file while it is written), and a field its
    writer alone holds is freed before the next is written; then the other files, largest first."""
    composed = _composed_fields()
    fields = [weakref.ref(composed.inverse_warp), weakref.ref(composed.warp)]
    image = Volume(np.zeros((5, 4, 3), np.float32), np.eye(4))
    fixed = FixedSpace(image, None, ModelGrid.for_volume(image, 1), image.array)
    affine = AffineResult(np.eye(4), np.zeros(3), np.eye(4), [])
    options = RegistrationOptions(affine=None, qc=False)
    alive_at_each_write = []

    def write_field(path, field, index_to_lps):
        alive_at_each_write.append((path.name, [ref() is not None for ref in fields]))

    monkeypatch.setattr(output_folder, "write_field", write_field)
    writers = output_writers(tmp_path, fixed, image, affine, composed, options)
    composed.warp = composed.inverse_warp = None  # as register_scan does: the writers hold the fields
    writers.pop(0)()
    assert alive_at_each_write == [("inverse_warp.nii.gz", [True, True]), ("warp.nii.gz", [False, True])]
    assert [ref() for ref in fields] == [None, None]
    for write in writers:
        write()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["affine.tfm", "warped.nii.gz", "warped_label.nii.gz"]
