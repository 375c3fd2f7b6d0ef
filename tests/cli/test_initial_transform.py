"""``--initial-transform``: an earlier registration's affine (ANTs' ``-r``), fixed -> moving, as the affine stage's
start or as the affine itself, on the asymmetric phantom moved by a known rigid transform (conftest's
``moved_phantom``), with a random-weights model (the deformation is ~0: what is tested is the affine and the files)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import itk
import nibabel as nib
import numpy as np
import pytest
from conftest import (
    BUNDLE_DIR,
    FAST_AFFINE,
    FIXED_LPS,
    moved_phantom,
    one_error_line,
    run_cli,
    save_lps,
    tiny_bundle,
)

from monai_probreg.registration.output_folder import write_transform
from monai_probreg.spatial.physical import affine_to_itk, apply_affine, grid_points
from monai_probreg.spatial.transform_files import read_affine_file

# the parts of a registration these tests do not look at, left out to keep them fast
QUICK = ["--no-qc", "--no-inverse", "--no-maps", "--refine", "0"]
SAME = 1e-9  # mm or parameter units: the same transform, up to the rounding of writing and reading it back


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("initial")
    case = moved_phantom([10.0, -8.0, 12.0], [4.0, -3.0, 2.5])
    s = SimpleNamespace(
        root=root,
        truth=case.truth,
        brain=grid_points(case.image.shape, FIXED_LPS)[case.labels > 0],
        bundle=tiny_bundle(root / "bundle", BUNDLE_DIR),
        fixed=save_lps(root / "fixed.nii.gz", case.image, FIXED_LPS),
        moving=save_lps(root / "moving.nii.gz", np.round(case.moved * 3000 + 200).astype(np.int16), case.grid),
    )
    # ANTs' *GenericAffine.mat of the known transform, written by ITK (MATLAB format), centred on the brain as ANTs
    # centres its affine: the file's parameters are not the matrix's offset
    s.ants_mat = root / "moving_0GenericAffine.mat"
    itk.transformwrite([affine_to_itk(s.truth, s.brain.mean(0))], str(s.ants_mat))
    return s


def _register(scene, out: Path, *extra: str, moving: Path | None = None):
    argv = ["register", "--moving", str(moving or scene.moving), "--out", str(out), "--fixed", str(scene.fixed)]
    return run_cli(*argv, "--bundle-root", str(scene.bundle), *QUICK, *extra)


def _tfm_values(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(Parameters, FixedParameters) of an ITK text transform file."""
    fields = dict(line.split(":", 1) for line in path.read_text().splitlines() if ":" in line)
    return np.array(fields["Parameters"].split(), float), np.array(fields["FixedParameters"].split(), float)


def _affine_summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())["affine"]


def _errors(matrix: np.ndarray, truth: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(apply_affine(matrix, points) - apply_affine(truth, points), axis=-1)


def test_as_affine_round_trip_gives_the_same_affine_tfm(scene, tmp_path):
    """A registration's affine.tfm fed back with ``as-affine``: the same affine.tfm (matrix, translation and centre),
    the same transform in summary.json, no stage run, and the file and the use recorded."""
    first = _register(scene, tmp_path / "first", *FAST_AFFINE)
    assert first.rc == 0, first.err
    previous = tmp_path / "first" / "affine.tfm"
    again = _register(
        scene, tmp_path / "again", "--initial-transform", str(previous), "--initial-transform-use", "as-affine"
    )
    assert again.rc == 0, again.err
    for mine, theirs in zip(_tfm_values(tmp_path / "again" / "affine.tfm"), _tfm_values(previous)):
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=SAME)
    summary, before = _affine_summary(tmp_path / "again"), _affine_summary(tmp_path / "first")
    assert summary["matrix_fixed_to_moving_lps"] == before["matrix_fixed_to_moving_lps"]
    assert summary["stages"] == [] and summary["settings"] is None
    assert summary["initial_transform"]["path"] == str(previous.resolve())
    assert summary["initial_transform"]["use"] == "as-affine" and before["initial_transform"] is None


def test_ants_mat_as_affine_is_exactly_the_transform(scene, tmp_path):
    out = tmp_path / "out"
    result = _register(scene, out, "--initial-transform", str(scene.ants_mat), "--initial-transform-use", "as-affine")
    assert result.rc == 0, result.err
    np.testing.assert_allclose(read_affine_file(out / "affine.tfm"), scene.truth, rtol=0, atol=SAME)
    _, centre = _tfm_values(out / "affine.tfm")
    np.testing.assert_allclose(centre, scene.brain.mean(0), rtol=0, atol=SAME)  # the .mat's own centre kept
    summary = _affine_summary(out)
    assert summary["matrix_fixed_to_moving_lps"] == np.round(scene.truth, 6).tolist()
    assert summary["initial_transform"]["use"] == "as-affine" and summary["stages"] == []


def test_ants_mat_as_start_ends_near_it(scene, tmp_path):
    """``start`` (the default): the rigid and affine stages run from the .mat's transform and stay near it (well
    under the 0.9-1.4 mm voxels over the object, as from the centre-of-mass start; tests/spatial/test_affine.py)."""
    out = tmp_path / "out"
    result = _register(scene, out, "--initial-transform", str(scene.ants_mat), *FAST_AFFINE)
    assert result.rc == 0, result.err
    errors = _errors(read_affine_file(out / "affine.tfm"), scene.truth, scene.brain)
    assert errors.mean() < 0.4 and errors.max() < 0.8
    summary = _affine_summary(out)
    assert [stage["name"] for stage in summary["stages"]] == ["rigid", "affine"]
    assert summary["initial_transform"]["use"] == "start" and summary["settings"]["backend"] == "torch"
    np.testing.assert_allclose(summary["initial_transform"]["matrix_fixed_to_moving_lps"], scene.truth, atol=1e-6)


def test_register_batch_reads_a_folder_of_transforms_one_per_scan(scene, tmp_path):
    """A folder of transforms named like the scans: each scan gets its own; a scan without one is that scan's
    failure (one line naming the folder and the scan), the other is registered."""
    scans, transforms = tmp_path / "scans", tmp_path / "transforms"
    scans.mkdir()
    transforms.mkdir()
    shutil.copy(scene.moving, scans / "sub01.nii.gz")
    shutil.copy(scene.moving, scans / "sub02.nii.gz")
    shutil.copy(scene.ants_mat, transforms / "sub01.mat")
    out = tmp_path / "out"
    argv = ["register-batch", "--moving", str(scans), "--out", str(out), "--fixed", str(scene.fixed)]
    argv += ["--bundle-root", str(scene.bundle), "--initial-transform", str(transforms)]
    result = run_cli(*argv, "--initial-transform-use", "as-affine", "--quiet", *QUICK)
    assert result.rc == 1, result.err
    rows = {row["scan"]: row for row in csv.DictReader((out / "batch_summary.csv").open())}
    assert rows["sub01"]["status"] == "ok" and rows["sub02"]["status"] == "failed"
    assert "transforms" in rows["sub02"]["error"] and "'sub02'" in rows["sub02"]["error"]
    np.testing.assert_allclose(read_affine_file(out / "sub01" / "affine.tfm"), scene.truth, rtol=0, atol=SAME)
    assert _affine_summary(out / "sub01")["initial_transform"]["path"] == str((transforms / "sub01.mat").resolve())
    assert not (out / "sub02").exists()


# ---------------------------------------------------------------------------------- bad input: one test each
def _fails(scene, tmp_path, *argv: str) -> str:
    """register expected to fail: exit status 1, one error line (returned), no output folder."""
    out = tmp_path / "out"
    return one_error_line(_register(scene, out, *argv), out)


def test_bad_missing_initial_transform(scene, tmp_path):
    line = _fails(scene, tmp_path, "--initial-transform", str(tmp_path / "nope.mat"))
    assert "--initial-transform" in line and "nope.mat" in line and "no such file" in line


def test_bad_unreadable_initial_transform(scene, tmp_path):
    """FSL's flirt writes its .mat as text: not ITK's MATLAB format (nor FSL's convention)."""
    path = tmp_path / "flirt.mat"
    path.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    line = _fails(scene, tmp_path, "--initial-transform", str(path))
    assert "flirt.mat" in line and "not an ITK/ANTs transform file" in line


def test_bad_bspline_initial_transform(scene, tmp_path):
    path = tmp_path / "bspline.tfm"
    itk.transformwrite([itk.BSplineTransform[itk.D, 3, 3].New()], str(path))
    line = _fails(scene, tmp_path, "--initial-transform", str(path))
    assert "bspline.tfm" in line and "expected one linear 3-D transform" in line and "BSplineTransform" in line


def test_bad_displacement_field_as_initial_transform(scene, tmp_path):
    path = tmp_path / "warp.nii.gz"
    field = nib.Nifti1Image(np.zeros((4, 4, 4, 1, 3), np.float32), np.eye(4))
    field.header.set_intent("vector")
    nib.save(field, path)
    line = _fails(scene, tmp_path, "--initial-transform", str(path))
    assert "warp.nii.gz" in line and "expected an affine transform file" in line


def test_bad_two_dimensional_initial_transform(scene, tmp_path):
    path = tmp_path / "slice.mat"
    itk.transformwrite([itk.AffineTransform[itk.D, 2].New()], str(path))
    line = _fails(scene, tmp_path, "--initial-transform", str(path))
    assert "slice.mat" in line and "got a 2-D transform" in line


def test_bad_singular_initial_transform(scene, tmp_path):
    flat = np.eye(4)
    flat[2, 2] = 0.0  # every point onto one plane
    path = write_transform(tmp_path / "flat.tfm", flat)
    line = _fails(scene, tmp_path, "--initial-transform", str(path))
    assert "flat.tfm" in line and "expected an invertible matrix, got a singular one" in line


def test_bad_initial_transform_with_no_affine(scene, tmp_path):
    line = _fails(scene, tmp_path, "--initial-transform", str(scene.ants_mat), "--no-affine")
    assert "--initial-transform" in line and scene.ants_mat.name in line and "--no-affine" in line


def test_bad_initial_transform_use_without_a_transform(scene, tmp_path):
    line = _fails(scene, tmp_path, "--initial-transform-use", "as-affine")
    assert "--initial-transform-use" in line and "expected --initial-transform" in line
