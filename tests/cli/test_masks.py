"""Cost-function masks (``--fixed-mask``, ``--moving-mask``; ANTs' ``-x [fixedMask,movingMask]``): a bright artefact
in one image pulls the unmasked affine off the known transform, the masked one recovers it (both backends for the
moving mask); the command records the masks and refuses a bad one with one line, writing nothing."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import (
    BUNDLE_DIR,
    FAST_AFFINE,
    FAST_AFFINE_SETTINGS,
    FIXED_LPS,
    moved_phantom,
    one_error_line,
    run_cli,
    save_lps,
    tiny_bundle,
)

from monai_probreg.spatial.affine import AffineSettings, align
from monai_probreg.spatial.physical import apply_affine, grid_points
from monai_probreg.spatial.transform_files import read_affine_file
from monai_probreg.spatial.volume_io import Volume

QUICK = ["--no-qc", "--no-inverse", "--no-maps", "--refine", "2"]  # the refinement runs (masked), briefly
ARTEFACT_RADIUS = 8.0  # voxels of the image it is in
ARTEFACT_BRIGHTNESS = 5.0  # times the phantom's ~1 peak: a bright non-brain part (fat, a vessel, a marker)
ARTEFACT_CENTRE = (0.25, 0.5, 0.5)  # fractions of the grid: over the brain's edge
PULLED_OFF_MM = 3.0  # the unmasked affine's mean error over the brain, at least (measured: 11.9 mm)
RECOVERED_MM = (0.3, 0.5)  # the masked one's mean and max, at most (measured: 0.09, 0.15 mm; the voxels: ~1 mm)
# ITK's backend: its Mattes histogram spans the whole moving image's range, the artefact's included, and it drops the
# points outside the mask (measured: 0.45, 0.79 mm, against 11.9 unmasked)
RECOVERED_ITK_MM = (0.8, 1.2)
FIXED_ARTEFACT_RADIUS = 10.0
FIXED_ARTEFACT_CENTRE = (0.3, 0.5, 0.5)
PULLED_OFF_FIXED_MM = (0.45, 1.0)  # mean and max, at least (measured: 0.56, 1.33 mm; masked: 0.09, 0.15)


def _blob(shape: tuple[int, ...]) -> np.ndarray:
    grid = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    centre = [f * n for f, n in zip(ARTEFACT_CENTRE, shape)]
    return sum(((x - c) / ARTEFACT_RADIUS) ** 2 for x, c in zip(grid, centre)) < 1


@pytest.fixture(scope="module")
def case() -> SimpleNamespace:
    moved = moved_phantom([10.0, -8.0, 12.0], [4.0, -3.0, 2.5])
    blob = _blob(moved.moved.shape)
    return SimpleNamespace(
        **vars(moved),
        brain=grid_points(moved.image.shape, FIXED_LPS)[moved.labels > 0],
        blob=blob,
        with_artefact=np.where(blob, ARTEFACT_BRIGHTNESS, moved.moved).astype(np.float32),
    )


def _errors(matrix: np.ndarray, case: SimpleNamespace) -> np.ndarray:
    return np.linalg.norm(apply_affine(matrix, case.brain) - apply_affine(case.truth, case.brain), axis=-1)


@pytest.mark.parametrize("backend", ["torch", "itk"])
def test_a_moving_mask_over_an_artefact_recovers_the_affine_it_pulls_off(case, backend):
    settings = (
        FAST_AFFINE_SETTINGS
        if backend == "torch"
        else AffineSettings(**{**FAST_AFFINE_SETTINGS.as_dict(), "backend": "itk"})
    )
    fixed = Volume(case.image, FIXED_LPS, "fixed")
    moving = Volume(case.with_artefact, case.grid, "moving")
    plain = _errors(align(fixed, moving, settings).matrix, case)
    masked = _errors(align(fixed, moving, settings, moving_mask=Volume(~case.blob, case.grid, "mask")).matrix, case)
    assert plain.mean() > PULLED_OFF_MM, plain.mean()
    recovered = RECOVERED_MM if backend == "torch" else RECOVERED_ITK_MM
    assert masked.mean() < recovered[0] and masked.max() < recovered[1], (masked.mean(), masked.max())


def test_a_fixed_mask_over_an_artefact_recovers_the_affine_it_pulls_off(case):
    """The artefact in the fixed image instead (larger and nearer the centre: a fixed artefact pulls less, its
    samples' bins being fixed): the sample points are drawn outside it."""
    grid = np.meshgrid(*[np.arange(n) for n in case.image.shape], indexing="ij")
    centre = [f * n for f, n in zip(FIXED_ARTEFACT_CENTRE, case.image.shape)]
    blob = sum(((x - c) / FIXED_ARTEFACT_RADIUS) ** 2 for x, c in zip(grid, centre)) < 1
    fixed = Volume(np.where(blob, ARTEFACT_BRIGHTNESS, case.image).astype(np.float32), FIXED_LPS, "fixed")
    moving = Volume(case.moved, case.grid, "moving")
    plain = _errors(align(fixed, moving, FAST_AFFINE_SETTINGS).matrix, case)
    mask = Volume(~blob, FIXED_LPS, "mask")
    masked = _errors(align(fixed, moving, FAST_AFFINE_SETTINGS, fixed_mask=mask).matrix, case)
    assert plain.mean() > PULLED_OFF_FIXED_MM[0] and plain.max() > PULLED_OFF_FIXED_MM[1], (plain.mean(), plain.max())
    assert masked.mean() < RECOVERED_MM[0] and masked.max() < RECOVERED_MM[1], (masked.mean(), masked.max())


# ------------------------------------------------------------------------------------------------ the command line
@pytest.fixture(scope="module")
def scene(case, tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("masks")
    moving = np.round(case.with_artefact * 3000 + 200).astype(np.int16)
    return SimpleNamespace(
        root=root,
        bundle=tiny_bundle(root / "bundle", BUNDLE_DIR),
        fixed=save_lps(root / "fixed.nii.gz", case.image, FIXED_LPS),
        moving=save_lps(root / "moving.nii.gz", moving, case.grid),
        fixed_mask=save_lps(root / "fixed_mask.nii.gz", (case.labels > 0).astype(np.uint8), FIXED_LPS),
        moving_mask=save_lps(root / "moving_mask.nii.gz", (~case.blob).astype(np.uint8), case.grid),
        # ANTs' rule: any nonzero voxel is inside (a probability or label map as a mask)
        moving_mask_valued=save_lps(root / "moving_mask_7.nii.gz", (~case.blob) * np.float32(7.5), case.grid),
    )


def _register(scene, out: Path, *extra: str):
    argv = ["register", "--moving", str(scene.moving), "--out", str(out), "--fixed", str(scene.fixed)]
    return run_cli(*argv, "--bundle-root", str(scene.bundle), *FAST_AFFINE, *QUICK, *extra)


def test_register_with_masks_records_them_and_recovers_the_affine(case, scene, tmp_path):
    """Both masks through the command: summary.json names them with the fraction inside, the brain mask is the
    fixed mask dilated; a mask of other nonzero values (7.5) is the same mask (the same affine.tfm)."""
    masks = ["--fixed-mask", str(scene.fixed_mask), "--moving-mask"]
    first = _register(scene, tmp_path / "a", *masks, str(scene.moving_mask))
    assert first.rc == 0, first.err
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["masks"]["fixed"] == {
        "path": str(scene.fixed_mask.resolve()),
        "fraction_inside": round(float((case.labels > 0).mean()), 4),
    }
    assert summary["masks"]["moving"]["fraction_inside"] == round(float((~case.blob).mean()), 4)
    assert summary["model"]["brain_mask"]["support"] == "--fixed-mask"
    assert _errors(read_affine_file(tmp_path / "a" / "affine.tfm"), case).mean() < RECOVERED_MM[0]
    second = _register(scene, tmp_path / "b", *masks, str(scene.moving_mask_valued))
    assert second.rc == 0, second.err
    assert (tmp_path / "a" / "affine.tfm").read_bytes() == (tmp_path / "b" / "affine.tfm").read_bytes()


def test_without_masks_the_summary_says_none(scene, tmp_path):
    result = _register(scene, tmp_path / "out")
    assert result.rc == 0, result.err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["masks"] == {"fixed": None, "moving": None}


def test_register_batch_takes_a_fixed_mask_and_a_folder_of_moving_masks(scene, tmp_path):
    scans, masks = tmp_path / "scans", tmp_path / "masks"
    scans.mkdir()
    masks.mkdir()
    for name in ("sub01", "sub02"):
        (scans / f"{name}.nii.gz").write_bytes(scene.moving.read_bytes())
    (masks / "sub01.nii.gz").write_bytes(scene.moving_mask.read_bytes())  # sub02 has none: registered without
    out = tmp_path / "out"
    argv = ["register-batch", "--moving", str(scans), "--out", str(out), "--fixed", str(scene.fixed), "--quiet"]
    argv += ["--bundle-root", str(scene.bundle), "--fixed-mask", str(scene.fixed_mask), "--moving-mask-dir", str(masks)]
    result = run_cli(*argv, *FAST_AFFINE, *QUICK)
    assert result.rc == 0, result.err
    assert {row["status"] for row in csv.DictReader((out / "batch_summary.csv").open())} == {"ok"}
    one, two = (json.loads((out / name / "summary.json").read_text())["masks"] for name in ("sub01", "sub02"))
    assert one["moving"]["path"] == str((masks / "sub01.nii.gz").resolve()) and two["moving"] is None
    assert one["fixed"]["path"] == two["fixed"]["path"] == str(scene.fixed_mask.resolve())


# ---------------------------------------------------------------------------------- bad input: one test each
def _fails(scene, tmp_path, *argv: str) -> str:
    """register expected to fail: exit status 1, one error line (returned), no output folder."""
    out = tmp_path / "out"
    return one_error_line(_register(scene, out, *argv), out)


def test_bad_mask_on_another_grid(scene, tmp_path):
    """The moving scan's mask given as the fixed image's: another grid."""
    line = _fails(scene, tmp_path, "--fixed-mask", str(scene.moving_mask))
    assert "--fixed-mask" in line and scene.moving_mask.name in line and "is not on the grid of --fixed" in line
    assert "resample the mask onto its image" in line


def test_bad_empty_mask(scene, case, tmp_path):
    path = save_lps(tmp_path / "empty.nii.gz", np.zeros(case.moved.shape, np.uint8), case.grid)
    line = _fails(scene, tmp_path, "--moving-mask", str(path))
    assert "--moving-mask" in line and "empty.nii.gz" in line
    assert "expected a mask with at least one nonzero voxel (inside), got none" in line


def test_bad_unreadable_mask(scene, tmp_path):
    path = tmp_path / "broken.nii.gz"
    path.write_bytes(b"not a nifti file at all")
    line = _fails(scene, tmp_path, "--moving-mask", str(path))
    assert "--moving-mask" in line and "broken.nii.gz" in line


def test_bad_missing_mask(scene, tmp_path):
    line = _fails(scene, tmp_path, "--fixed-mask", str(tmp_path / "nope.nii.gz"))
    assert "--fixed-mask" in line and "nope.nii.gz" in line and "no such file" in line
