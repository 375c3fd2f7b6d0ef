"""The bundle's loading path (inference.yaml, evaluate.yaml, train.yaml) on a dataset with one damaged file: the
run stops with the package's one-line InputError naming that file (MONAI wraps it; its cause chain holds it), not
with a reader's traceback or, worse, silently wrong voxels.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from monai.bundle import ConfigWorkflow
from rel_helpers import flip_byte, save, truncate

from monai_probreg.validation import InputError

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


@pytest.mark.parametrize("config, damage, words", [
    ("inference.yaml", lambda d: truncate(d / "images" / "T01.nii.gz", 0.6), "truncated"),
    ("inference.yaml", lambda d: flip_byte(d / "images" / "T01.nii.gz", 0.5), "corrupt"),
    ("evaluate.yaml", lambda d: save(d / "labels" / "T01.nii.gz",
                                     _nifti_voxels(d / "labels" / "T01.nii.gz") * 0.5, np.diag([-1.0, -1, 1, 1])),
     "non-integer"),
])
def test_infer_workflows_name_the_damaged_file(tmp_path, tiny_dataset, bundle, config, damage, words):
    dataset, damaged = _damaged_copy(tiny_dataset, tmp_path, damage)
    wf = ConfigWorkflow(config_file=str(bundle / "configs" / config), workflow_type="infer", logging_file=False,
                        bundle_root=str(bundle), dataset_dir=str(dataset), output_dir=str(tmp_path / "out"),
                        network_size=[16, 16, 16], num_workers=0)
    wf.initialize()
    error = _input_error(wf.run)
    assert str(damaged) in str(error) and words in str(error), str(error)


def test_training_refuses_a_nan_scan_before_the_first_step(tmp_path, tiny_dataset):
    def nan_scan(d: Path) -> Path:
        data = _nifti_voxels(d / "images" / "T03.nii.gz").astype(np.float32)
        data[5, 6, 7] = np.nan
        return save(d / "images" / "T03.nii.gz", data, np.diag([-1.0, -1, 1, 1]))

    dataset, damaged = _damaged_copy(tiny_dataset, tmp_path, nan_scan)
    wf = ConfigWorkflow(config_file=str(ROOT / "bundle" / "configs" / "train.yaml"), workflow_type="train",
                        logging_file=False, bundle_root=str(ROOT / "bundle"), dataset_dir=str(dataset),
                        ckpt_dir=str(tmp_path / "ckpt"), output_dir=str(tmp_path / "runs"), network_size=[32, 32, 32],
                        val_ids=["T01"], num_workers=0, max_epochs=1)
    error = _input_error(lambda: (wf.initialize(), wf.run()))
    assert str(damaged) in str(error) and "1 NaN" in str(error)
    assert not list((tmp_path / "ckpt").glob("*.pt"))
