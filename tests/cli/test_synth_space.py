"""The synthetic-head training folder (monai_probreg.cli.synth_space): a label map rendered T1-like on its own grid,
moved onto the template through the command's affine stage, hidden outside the template's brain mask."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
from conftest import FAST_AFFINE_SETTINGS, FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.cli.synth_space import SYNTH_ATLAS_NAME, main, render_head, to_synth_space
from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.label_synthesis import T1_LIKE
from monai_probreg.spatial.volume_io import Volume

FAST = FAST_AFFINE_SETTINGS


def _freesurfer_phantom() -> tuple[np.ndarray, np.ndarray]:
    """The asymmetric phantom's labels as FreeSurfer structures (white matter, cortex, a ventricle, putamen) and a
    'skull' shell of an extra-cerebral label around it; the template is the brain alone, as MNI152 is."""
    image, labels = asymmetric_phantom((40, 44, 36))
    fs = np.zeros_like(labels)
    for phantom, freesurfer in ((1, 2), (2, 3), (3, 12), (4, 4)):
        fs[labels == phantom] = freesurfer
    return np.where(labels > 0, np.clip(image, 0.05, None), 0).astype(np.float32), fs


def test_render_head_follows_the_t1_table_and_keeps_the_grid():
    _, fs = _freesurfer_phantom()
    volume = Volume(fs.astype(np.int32), FIXED_LPS)
    head = render_head(volume, seed=1)
    assert head.shape == volume.shape and np.array_equal(head.index_to_lps, volume.index_to_lps)
    means = {v: float(head.array[fs == v].mean()) for v in (2, 3, 4, 12)}
    assert sorted(means, key=means.get) == sorted((2, 3, 4, 12), key=T1_LIKE.get)  # the table's order survives
    assert np.array_equal(render_head(volume, seed=1).array, head.array)  # seeded: the same rendering twice


def test_the_folder_holds_the_label_maps_on_the_template_grid_after_the_affine_stage(tmp_path):
    """Each label map is the template's anatomy shifted by a known translation: after the affine stage its labels
    land back on the template's (the shift recovered from the rendering, not the header copied)."""
    image, fs = _freesurfer_phantom()
    template = save_lps(tmp_path / "template.nii.gz", image * 100, FIXED_LPS)
    maps = tmp_path / "maps"
    maps.mkdir()
    for sid, shift in (("seg_a", (3.0, -2.0, 0.0)), ("seg_b", (-2.0, 0.0, 3.0))):
        moved = FIXED_LPS.copy()
        moved[:3, 3] += shift
        save_lps(maps / f"{sid}.nii.gz", fs, moved)
    out = to_synth_space([maps / "seg_a.nii.gz", maps / "seg_b.nii.gz"], tmp_path / "out", template, FAST)
    index = index_dataset(out)
    assert index.ids == ["seg_a", "seg_b"] and sorted(index.labels) == ["seg_a", "seg_b"]
    assert index.atlas_image.name == f"{SYNTH_ATLAS_NAME}_image.nii.gz" and index.atlas_label is None
    reference = nib.load(template)
    for sid in index.ids:
        moved_image, moved_label = nib.load(index.images[sid]), nib.load(index.labels[sid])
        assert moved_image.shape == reference.shape and np.allclose(moved_image.affine, reference.affine)
        agree = np.asarray(moved_label.dataobj) == fs
        assert agree.mean() > 0.97, f"{sid}: labels back on the template at {agree.mean():.3f}"


def test_the_command_refuses_ids_it_cannot_find(tmp_path, capsys):
    (tmp_path / "maps").mkdir()
    save_lps(tmp_path / "maps" / "seg_a.nii.gz", np.ones((4, 4, 4), np.int16), FIXED_LPS)
    with pytest.raises(SystemExit):
        main(["--label-maps", str(tmp_path / "maps"), "--out-dir", str(tmp_path / "out"), "--ids", "seg_z"])
    assert "seg_z" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_no_label_map_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="at least one"):
        to_synth_space([], tmp_path / "out")
