"""``monai-probreg`` on odd and damaged scans, end to end with a random-weights model (its deformation is ~0, so what
is checked is the geometry, the intensity handling and the errors): correct results for extreme intensity units,
integer data and an extremely anisotropic oblique grid; one line and nothing written for a bad input; a batch that
reports each bad scan with its reason, registers the others and exits 1.
"""

from __future__ import annotations

import csv
import os
from types import SimpleNamespace

import itk
import nibabel as nib
import numpy as np
import pytest
from conftest import (
    BUNDLE_DIR,
    FAST_AFFINE,
    FIXED_LPS,
    OBLIQUE_DIRECTION,
    moved_phantom,
    moved_scan,
    run_cli,
    save_lps,
    tiny_bundle,
)
from rel_helpers import rotation, set_header_dim, truncate
from test_reliability_inputs import CASES

from monai_probreg.spatial.checks import MAX_VOXELS_ENV
from monai_probreg.spatial.physical import (
    affine_from_itk,
    apply_affine,
    displacement_transform,
    grid_points,
    resample_with_itk,
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("reliability_cli")
    case = moved_phantom([8.0, -6.0, 10.0], [3.0, -2.0, 2.0])
    image, labels, truth, moved, moved_labels, grid = (
        case.image,
        case.labels,
        case.truth,
        case.moved,
        case.moved_labels,
        case.grid,
    )
    s = SimpleNamespace(
        root=root,
        truth=truth,
        image=image,
        labels=labels,
        moved=moved,
        grid=grid,
        bundle=tiny_bundle(root / "bundle", BUNDLE_DIR),
        fixed=save_lps(root / "fixed.nii.gz", image, FIXED_LPS),
        fixed_label=save_lps(root / "fixed_label.nii.gz", labels, FIXED_LPS),
        moving_label=save_lps(root / "moving_label.nii.gz", moved_labels.astype(np.uint8), grid),
    )
    s.common = ["--fixed", str(s.fixed), "--bundle-root", str(s.bundle)]
    return s


UNITS = {  # moving intensities as another scanner / tool might store them
    "float32 x 1e-6": lambda m: (m * 1e-6).astype(np.float32),
    "float32 x 1e9": lambda m: (m * 1e9).astype(np.float32),
    "float64, negative": lambda m: m * 4000.0 - 9000.0,
    "uint8": lambda m: np.round(np.clip(m, 0, None) / m.max() * 255).astype(np.uint8),
}


@pytest.mark.parametrize("units", list(UNITS))
def test_intensity_units_do_not_change_the_registration(scene, tmp_path, units):
    """Whatever the units, the recovered transform is the true one (mean error < 0.5 mm over the brain, well under
    the 0.9-1.4 mm voxels, as in test_cli) and Dice after registration > 0.85."""
    moving = save_lps(tmp_path / "moving.nii.gz", UNITS[units](scene.moved), scene.grid)
    result = run_cli(
        "register",
        "--moving",
        str(moving),
        "--moving-label",
        str(scene.moving_label),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(tmp_path / "out"),
        "--no-qc",
        *scene.common,
        *FAST_AFFINE,
    )
    assert result.rc == 0, result.err
    brain = grid_points(scene.image.shape, FIXED_LPS)[scene.labels > 0]
    affine = affine_from_itk(itk.transformread(str(tmp_path / "out" / "affine.tfm"))[0])
    error = np.linalg.norm(apply_affine(affine, brain) - apply_affine(scene.truth, brain), axis=-1)
    assert error.mean() < 0.5, (units, error.mean())
    assert "mean Dice 0.8" in result.out or "mean Dice 0.9" in result.out, result.out


def test_extremely_anisotropic_oblique_scan(scene, tmp_path):
    """A 0.35 x 0.35 x 4 mm grid (ratio 11), rotated 20-30 degrees off every axis, of the unmoved phantom, with
    --no-affine: ITK, applying our warp.nii.gz to the original scan, reproduces our warped.nii.gz, and that matches
    the phantom where the thick slices allow (correlation > 0.9 inside the brain)."""
    direction = rotation((20.0, -25.0, 30.0)) @ OBLIQUE_DIRECTION
    moved, _, grid = moved_scan(scene.image, scene.labels, np.eye(4), (0.35, 0.35, 4.0), direction, (130, 130, 14))
    moving = save_lps(tmp_path / "aniso.nii.gz", moved * 1000.0, grid)
    out = tmp_path / "out"
    result = run_cli("register", "--moving", str(moving), "--out", str(out), "--no-affine", "--no-qc", *scene.common)
    assert result.rc == 0, result.err
    transform = displacement_transform(itk.imread(str(out / "warp.nii.gz")))
    theirs = itk.array_from_image(
        resample_with_itk(itk.imread(str(moving), itk.F), itk.imread(str(scene.fixed), itk.F), transform)
    )
    ours = itk.array_from_image(itk.imread(str(out / "warped.nii.gz"), itk.F))
    np.testing.assert_allclose(theirs, ours, atol=1e-5 * ours.max())  # float32 field and image storage
    warped = ours.transpose(2, 1, 0)  # ITK's array is (k, j, i)
    inside = (scene.labels > 0) & (warped > 0)
    assert np.corrcoef(warped[inside], scene.image[inside])[0, 1] > 0.9
    header = nib.load(out / "inverse_warp.nii.gz")
    np.testing.assert_allclose(header.affine, nib.load(moving).affine, atol=1e-4)  # on the moving grid


FAULTS_VIA_CLI = [
    "truncated .nii.gz",
    "corrupt gzip (one byte flipped)",
    "header size smaller than data (.nii)",
    "zero-sized axis",
    "2-D image",
    "4-D series",
    "NaN voxel",
    "float64 beyond float32",
    "complex voxels",
    "all-zero image",
    "sheared axes",
    "header claims 4096^3 voxels",
]


@pytest.mark.parametrize("name", FAULTS_VIA_CLI)
def test_a_bad_scan_gives_one_line_and_writes_nothing(scene, tmp_path, name):
    case = next(c for c in CASES if c.name == name)
    (tmp_path / "in").mkdir()
    path, _, _ = case.make(tmp_path / "in")
    out = tmp_path / "out"
    result = run_cli("register", "--moving", str(path), "--out", str(out), *scene.common)
    assert result.rc == 1 and "Traceback" not in result.err
    lines = [line for line in result.err.splitlines() if line.startswith("monai-probreg: error:")]
    assert len(lines) == 1 and "--moving" in lines[0] and path.name in lines[0] and case.io in lines[0], result.err
    assert not out.exists()


def test_max_voxels_option_refuses_a_large_scan_and_restores_the_environment(scene, tmp_path):
    before = os.environ.get(MAX_VOXELS_ENV)
    moving = save_lps(tmp_path / "big.nii.gz", scene.moved, scene.grid)  # 70,720 voxels; the fixed image: 63,360
    result = run_cli(
        "register", "--moving", str(moving), "--out", str(tmp_path / "out"), "--max-voxels", "65000", *scene.common
    )
    assert result.rc == 1 and "expected at most 65,000 voxels, got 70,720" in result.err, result.err
    assert os.environ.get(MAX_VOXELS_ENV) == before
    assert (
        run_cli(
            "register", "--moving", str(moving), "--out", str(tmp_path / "o"), "--max-voxels", "0", *scene.common
        ).rc
        == 1
    )


def test_batch_reports_every_bad_scan_and_registers_the_rest(scene, tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    good = {"good_float": scene.moved, "good_int16": np.round(scene.moved * 3000 + 200).astype(np.int16)}
    for sid, data in good.items():
        save_lps(scans / f"{sid}.nii.gz", data, scene.grid)
    truncate(save_lps(scans / "cut.nii.gz", scene.moved, scene.grid), 0.5)
    nan = scene.moved.copy()
    nan[3, 4, 5] = np.nan
    save_lps(scans / "nan.nii.gz", nan, scene.grid)
    save_lps(scans / "blank.nii.gz", np.zeros_like(scene.moved), scene.grid)
    set_header_dim(save_lps(scans / "liar.nii", scene.moved, scene.grid), 3, 20)
    (scans / "notes.nii.gz").write_text("not an image")
    paths = sorted(str(p) for p in scans.iterdir()) + [str(scans / "gone.nii.gz")]  # a missing scan, named
    out = tmp_path / "out"
    result = run_cli("register-batch", "--moving", *paths, "--out", str(out), "--no-affine", "--no-qc", *scene.common)
    assert result.rc == 1 and "Traceback" not in result.err
    assert "6 of 8 scans failed" in result.err
    rows = {row["scan"]: row for row in csv.DictReader((out / "batch_summary.csv").open())}
    expected = {
        "cut": "truncated",
        "nan": "1 NaN",
        "blank": "constant",
        "liar": "dimensions",
        "notes": "corrupt",
        "gone": "no such file",
    }
    for sid, words in expected.items():
        assert rows[sid]["status"] == "failed" and words in rows[sid]["error"] and sid in rows[sid]["error"], rows[sid]
    assert [rows[sid]["status"] for sid in good] == ["ok", "ok"]
    assert sorted(p.name for p in out.iterdir()) == ["batch_summary.csv", *sorted(good)]
    for sid in (*good, *expected):
        assert sid in result.out  # the printed table lists every scan


def test_interrupted_batch_still_has_a_summary(scene, tmp_path, monkeypatch):
    import monai_probreg.registration.batch as batch

    scans = tmp_path / "scans"
    scans.mkdir()
    for sid in ("a", "b", "c"):
        save_lps(scans / f"{sid}.nii.gz", scene.moved, scene.grid)
    real, calls = batch.register_scan, []

    def interrupt_second(*args, **kwargs):
        calls.append(args[2])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(batch, "register_scan", interrupt_second)
    out = tmp_path / "out"
    result = run_cli(
        "register-batch", "--moving", str(scans), "--out", str(out), "--no-affine", "--no-qc", *scene.common
    )
    assert result.rc == 130 and "interrupted" in result.err
    rows = list(csv.DictReader((out / "batch_summary.csv").open()))
    assert [(r["scan"], r["status"]) for r in rows] == [("a", "ok"), ("b", "not run"), ("c", "not run")]
