"""The bundle's loading path on a dataset with one damaged file. inference.yaml / evaluate.yaml: the damaged subject
is skipped and listed (failed.csv, summary.json) with the package's one-line InputError naming the file, every other
subject is processed, and the run ends with exit status 1. train.yaml: the run stops with that InputError (MONAI
wraps it; its cause chain holds it) before the first step. Never a reader's traceback or silently wrong voxels.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from monai.bundle import ConfigWorkflow
from rel_helpers import flip_byte, save, truncate

from monai_probreg.fitting.stages import config_files
from monai_probreg.utils.errors import InputError

pytestmark = pytest.mark.usefixtures("single_thread")
ROOT = Path(__file__).resolve().parents[2]


def _damaged_copy(dataset: Path, folder: Path, damage) -> tuple[Path, Path]:
    copy = folder / "data"
    shutil.copytree(dataset, copy)
    return copy, damage(copy)


def _input_error(call) -> InputError:
    with pytest.raises(Exception) as info:
        call()
    chain, error = [], info.value
    while error is not None:
        chain.append(error)
        error = error.__cause__ or error.__context__
    found = [e for e in chain if isinstance(e, InputError)]
    assert found, [f"{type(e).__name__}: {str(e)[:200]}" for e in chain]
    assert "\n" not in str(found[0])
    return found[0]


def _nifti_voxels(path: Path) -> np.ndarray:
    import nibabel as nib

    return np.asarray(nib.load(path).dataobj)


@pytest.mark.parametrize(
    "config, damage, words",
    [
        ("inference.yaml", lambda d: truncate(d / "images" / "T01.nii.gz", 0.6), "truncated"),
        ("inference.yaml", lambda d: flip_byte(d / "images" / "T01.nii.gz", 0.5), "corrupt"),
        (
            "evaluate.yaml",
            lambda d: save(
                d / "labels" / "T01.nii.gz", _nifti_voxels(d / "labels" / "T01.nii.gz") * 0.5, np.diag([-1.0, -1, 1, 1])
            ),
            "non-integer",
        ),
        ("evaluate.yaml", lambda d: truncate(d / "images" / "T01.nii.gz", 0.6), "truncated"),
    ],
)
def test_infer_workflows_skip_and_report_the_damaged_subject(tmp_path, tiny_dataset, bundle, config, damage, words):
    dataset, damaged = _damaged_copy(tiny_dataset, tmp_path, damage)
    out = tmp_path / "out"
    wf = ConfigWorkflow(
        config_file=[str(f) for f in config_files(bundle, [config])],
        workflow_type="infer",
        logging_file=False,
        bundle_root=str(bundle),
        dataset_dir=str(dataset),
        output_dir=str(out),
        network_size=[16, 16, 16],
        num_workers=0,
    )
    wf.initialize()
    wf.run()
    with pytest.raises(SystemExit) as info:
        wf.finalize()
    assert info.value.code == 1
    rows = list(csv.DictReader((out / "failed.csv").open()))
    assert [r["id"] for r in rows] == ["T01"]
    assert str(damaged) in rows[0]["reason"] and words in rows[0]["reason"] and "\n" not in rows[0]["reason"]
    if config == "inference.yaml":
        assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["T02", "T03"]  # the others were processed
        assert not (out / "T01").exists()  # nothing half-written for the damaged subject
    else:
        assert [r["id"] for r in csv.DictReader((out / "scores.csv").open())] == ["T02", "T03"]
        summary = json.loads((out / "summary.json").read_text())
        assert summary["num_subjects"] == 2 and summary["num_failed"] == 1
        assert summary["failed"] == [{"id": "T01", "reason": rows[0]["reason"]}]


def test_every_subject_damaged_writes_no_scores_and_fails(tmp_path, tiny_dataset, bundle):
    def truncate_all(d: Path) -> Path:
        for path in sorted((d / "images").glob("*.nii.gz")):
            truncate(path, 0.6)
        return d

    dataset, _ = _damaged_copy(tiny_dataset, tmp_path, truncate_all)
    out = tmp_path / "out"
    wf = ConfigWorkflow(
        config_file=[str(f) for f in config_files(bundle, ["evaluate.yaml"])],
        workflow_type="infer",
        logging_file=False,
        bundle_root=str(bundle),
        dataset_dir=str(dataset),
        output_dir=str(out),
        network_size=[16, 16, 16],
        num_workers=0,
    )
    wf.initialize()
    wf.run()
    with pytest.raises(SystemExit):
        wf.finalize()
    assert [r["id"] for r in csv.DictReader((out / "failed.csv").open())] == ["T01", "T02", "T03"]
    assert not (out / "summary.json").exists()


def test_a_clean_run_leaves_no_failed_file(tmp_path, tiny_dataset, bundle):
    out = tmp_path / "out"
    out.mkdir()
    (out / "failed.csv").write_text("id,reason\nT09,from an earlier run\n")  # stale: must not survive
    wf = ConfigWorkflow(
        config_file=[str(f) for f in config_files(bundle, ["evaluate.yaml"])],
        workflow_type="infer",
        logging_file=False,
        bundle_root=str(bundle),
        dataset_dir=str(tiny_dataset),
        output_dir=str(out),
        network_size=[16, 16, 16],
        num_workers=0,
    )
    wf.initialize()
    wf.run()
    wf.finalize()  # no SystemExit
    assert not (out / "failed.csv").exists()
    assert json.loads((out / "summary.json").read_text())["num_failed"] == 0


def test_training_refuses_a_nan_scan_before_the_first_step(tmp_path, tiny_dataset):
    def nan_scan(d: Path) -> Path:
        data = _nifti_voxels(d / "images" / "T03.nii.gz").astype(np.float32)
        data[5, 6, 7] = np.nan
        return save(d / "images" / "T03.nii.gz", data, np.diag([-1.0, -1, 1, 1]))

    dataset, damaged = _damaged_copy(tiny_dataset, tmp_path, nan_scan)
    wf = ConfigWorkflow(
        config_file=str(ROOT / "bundle" / "configs" / "train.yaml"),
        workflow_type="train",
        logging_file=False,
        bundle_root=str(ROOT / "bundle"),
        dataset_dir=str(dataset),
        ckpt_dir=str(tmp_path / "ckpt"),
        output_dir=str(tmp_path / "runs"),
        network_size=[32, 32, 32],
        val_ids=["T01"],
        num_workers=0,
        max_epochs=1,
    )
    error = _input_error(lambda: (wf.initialize(), wf.run()))
    assert str(damaged) in str(error) and "1 NaN" in str(error)
    assert not list((tmp_path / "ckpt").glob("*.pt"))
