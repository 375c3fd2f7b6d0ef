"""``monai-probreg`` end to end on synthetic scans, with a random-weights model (the network's deformation is ~0,
so what is tested is the geometry, the composition, the files and the errors, not registration quality).

The geometry round trip of the issue: an asymmetric phantom (the "atlas") is moved out of its space by a known
rigid transform (10-15 degrees, 5 mm) onto a permuted, flipped, anisotropic grid (1.4 x 0.9 x 1.1 mm, another
orientation code) with raw scanner intensities, registered back, and the recovered transform, the headers of every
output and ITK's (and ANTs') reproduction of our warped image are checked.
"""

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
import torch
from conftest import (
    BUNDLE_DIR,
    FAST_AFFINE,
    FIXED_LPS,
    PHANTOM_LABELS,
    moved_phantom,
    one_error_line,
    run_cli,
    save_lps,
    tiny_bundle,
)
from monai.bundle import ConfigParser

from monai_probreg.cli.main import main
from monai_probreg.spatial.physical import (
    affine_from_itk,
    apply_affine,
    displacement_transform,
    grid_points,
    resample_with_itk,
)
from monai_probreg.spatial.volume_io import geometry_of, read_image


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("cli")
    case = moved_phantom([10.0, -8.0, 12.0], [4.0, -3.0, 2.5])
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
        moving_grid=grid,
        bundle=tiny_bundle(root / "bundle", BUNDLE_DIR),
        fixed=save_lps(root / "fixed.nii.gz", image, FIXED_LPS),
        fixed_label=save_lps(root / "fixed_label.nii.gz", labels, FIXED_LPS),
        moving=save_lps(root / "moving.nii.gz", np.round(moved * 3000 + 200).astype(np.int16), grid),
        moving_label=save_lps(root / "moving_label.nii.gz", moved_labels.astype(np.uint8), grid),
    )
    s.common = ["--fixed", str(s.fixed), "--bundle-root", str(s.bundle)]
    return s


@pytest.fixture(scope="module")
def registered(scene) -> SimpleNamespace:
    out = scene.root / "out"
    result = run_cli(
        "register",
        "--moving",
        str(scene.moving),
        "--moving-label",
        str(scene.moving_label),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(out),
        "--samples",
        "2",
        *scene.common,
        *FAST_AFFINE,
    )
    result.dir = out
    return result


def test_register_succeeds_and_prints_one_summary_line(registered):
    assert registered.rc == 0, registered.err
    assert registered.out.count("\n") == 1 and "mean Dice" in registered.out and "affine" in registered.out


def test_geometry_round_trip_recovers_the_transform(scene, registered):
    brain = grid_points(scene.image.shape, FIXED_LPS)[scene.labels > 0]
    affine = affine_from_itk(itk.transformread(str(registered.dir / "affine.tfm"))[0])
    error = np.linalg.norm(apply_affine(affine, brain) - apply_affine(scene.truth, brain), axis=-1)
    assert error.mean() < 0.4 and error.max() < 0.8  # well under the 0.9-1.4 mm voxels (see test_affine)
    warp = itk.array_from_image(itk.imread(str(registered.dir / "warp.nii.gz"))).transpose(2, 1, 0, 3)
    composed = grid_points(scene.image.shape, FIXED_LPS) + warp  # p + D(p): the whole transform, fixed -> moving
    error = np.linalg.norm(composed[scene.labels > 0] - apply_affine(scene.truth, brain), axis=-1)
    assert error.mean() < 0.4 and error.max() < 0.8  # an untrained model adds ~0 deformation


def _geometry(path: Path) -> tuple:
    image = itk.imread(str(path))
    return tuple(image.GetLargestPossibleRegion().GetSize()), geometry_of(image)


def test_output_headers(scene, registered):
    fixed_size, fixed_geometry = _geometry(scene.fixed)
    moving_size, moving_geometry = _geometry(scene.moving)
    for name in ("warped", "warped_label", "jacobian", "entropy", "displacement_std", "warp"):
        size, geometry = _geometry(registered.dir / f"{name}.nii.gz")
        assert size == fixed_size, name
        np.testing.assert_allclose(geometry, fixed_geometry, atol=1e-5, err_msg=name)
    for name in ("inverse_warp", "fixed_label_in_moving"):
        size, geometry = _geometry(registered.dir / f"{name}.nii.gz")
        assert size == moving_size, name
        np.testing.assert_allclose(geometry, moving_geometry, atol=1e-5, err_msg=name)
    for name in ("warp", "inverse_warp"):
        stored = nib.load(registered.dir / f"{name}.nii.gz")
        assert stored.header.get_intent()[0] == "vector" and stored.shape[3:] == (1, 3)
    assert nib.load(registered.dir / "warped_label.nii.gz").get_data_dtype() == np.uint8
    assert set(np.unique(np.asarray(nib.load(registered.dir / "fixed_label_in_moving.nii.gz").dataobj))) <= {
        0,
        *PHANTOM_LABELS,
    }
    assert not [p for p in registered.dir.parent.iterdir() if ".partial-" in p.name]


def test_itk_reproduces_the_warped_image_and_labels(scene, registered):
    """ITK's ResampleImageFilter + DisplacementFieldTransform(warp.nii.gz) on the ORIGINAL moving scan gives our
    warped.nii.gz. Tolerance 1e-5 of the intensity range (~3000): the field is stored in float32 (~1e-6 mm at these
    coordinates) and the output in float32 (6e-8 relative); observed ~1e-7 of the range. Labels: identical."""
    transform = displacement_transform(itk.imread(str(registered.dir / "warp.nii.gz")))
    fixed = itk.imread(str(scene.fixed), itk.F)
    theirs = itk.array_from_image(resample_with_itk(itk.imread(str(scene.moving), itk.F), fixed, transform))
    ours = itk.array_from_image(itk.imread(str(registered.dir / "warped.nii.gz"), itk.F))
    assert ours.max() > 1000  # original intensities, not the network's [0, 1]
    np.testing.assert_allclose(theirs, ours, atol=1e-5 * ours.max())
    labels = resample_with_itk(itk.imread(str(scene.moving_label), itk.SS), fixed, transform, nearest=True)
    np.testing.assert_array_equal(
        itk.array_from_image(labels),
        itk.array_from_image(itk.imread(str(registered.dir / "warped_label.nii.gz"), itk.SS)),
    )


def test_ants_apply_transforms_reproduces_the_warped_image(scene, registered):
    ants = pytest.importorskip("ants")
    theirs = ants.apply_transforms(
        ants.image_read(str(scene.fixed)),
        ants.image_read(str(scene.moving)),
        [str(registered.dir / "warp.nii.gz")],
        interpolator="linear",
    ).numpy()
    ours = ants.image_read(str(registered.dir / "warped.nii.gz")).numpy()
    np.testing.assert_allclose(theirs, ours, atol=1e-5 * ours.max())


def test_inverse_warp_maps_back(scene, registered):
    """p -> q = p + D(p) (moving space) -> q + D_inv(q) = p, with ITK interpolating inverse_warp.nii.gz.
    Tolerance 0.05 mm: the model part is ~identity here, so only the field interpolation remains."""
    forward = displacement_transform(itk.imread(str(registered.dir / "warp.nii.gz")))
    inverse = displacement_transform(itk.imread(str(registered.dir / "inverse_warp.nii.gz")))
    for p in grid_points(scene.image.shape, FIXED_LPS)[scene.labels > 0][::97]:
        back = inverse.TransformPoint(forward.TransformPoint(p.tolist()))
        np.testing.assert_allclose(np.asarray(back), p, atol=0.05)


def test_summary_and_qc(scene, registered):
    summary = json.loads((registered.dir / "summary.json").read_text())
    assert list(summary["timings_s"]) == [
        "read",
        "affine",
        "resample",
        "model",
        "refine",
        "maps",
        "samples",
        "compose",
        "qc",
        "write",
        "total",
    ]
    assert summary["dice"]["mean"] > 0.85 and set(summary["dice"]["per_label"]) == {str(v) for v in PHANTOM_LABELS}
    assert summary["jacobian"]["num_nonpositive"] == 0
    assert summary["uncertainty"]["samples"] == 2 and summary["uncertainty"]["mean_displacement_std_mm"] >= 0
    assert summary["moving"]["orientation"] != summary["fixed"]["orientation"]
    assert summary["moving"]["spacing_mm"] == pytest.approx([1.4, 0.9, 1.1], abs=1e-4)
    assert sorted(summary["outputs"]) == sorted(p.name for p in registered.dir.iterdir())
    assert (registered.dir / "qc.png").read_bytes()[:4] == b"\x89PNG"
    warped = read_image(registered.dir / "warped.nii.gz").array
    assert np.corrcoef(warped[scene.labels > 0], scene.image[scene.labels > 0])[0, 1] > 0.95


def test_no_affine_for_an_aligned_scan(scene, tmp_path):
    """--no-affine: the identity pre-alignment (scans already in atlas space, as the paper assumes)."""
    aligned = save_lps(tmp_path / "aligned.nii.gz", (scene.image * 500).astype(np.float32), FIXED_LPS)
    result = run_cli(
        "register",
        "--moving",
        str(aligned),
        "--moving-label",
        str(scene.fixed_label),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(tmp_path / "out"),
        "--no-affine",
        "--no-qc",
        *scene.common,
    )
    assert result.rc == 0, result.err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["affine"]["stages"] == [] and summary["affine"]["matrix_fixed_to_moving_lps"] == np.eye(4).tolist()
    assert summary["dice"]["mean"] > 0.99 and not (tmp_path / "out" / "qc.png").exists()


def test_no_inverse_and_no_maps_leave_out_only_those_files(scene, tmp_path):
    """--no-inverse / --no-maps: the files asked for are byte-identical to a full run's; the others are absent."""
    args = [
        "register",
        "--moving",
        str(scene.moving),
        "--moving-label",
        str(scene.moving_label),
        "--fixed-label",
        str(scene.fixed_label),
        "--no-affine",
        "--no-qc",
        "--samples",
        "2",
        *scene.common,
    ]
    assert run_cli(*args, "--out", str(tmp_path / "full")).rc == 0
    result = run_cli(*args, "--out", str(tmp_path / "lean"), "--no-inverse", "--no-maps")
    assert result.rc == 0, result.err
    full, lean = ({p.name for p in (tmp_path / d).iterdir()} for d in ("full", "lean"))
    left_out = {
        "inverse_warp.nii.gz",
        "fixed_label_in_moving.nii.gz",
        "jacobian.nii.gz",
        "entropy.nii.gz",
        "displacement_std.nii.gz",
    }
    assert full - lean == left_out and lean <= full
    for name in lean - {"summary.json", "README.txt"}:
        assert (tmp_path / "lean" / name).read_bytes() == (tmp_path / "full" / name).read_bytes(), name
    summary = json.loads((tmp_path / "lean" / "summary.json").read_text())
    assert set(summary["outputs"]) == lean and summary["jacobian"]["num_nonpositive"] == 0
    assert summary["uncertainty"]["mean_displacement_std_mm"] > 0


def test_overwrite_replaces_an_earlier_run(scene, tmp_path):
    out = tmp_path / "out"
    args = ["register", "--moving", str(scene.fixed), "--out", str(out), "--no-affine", "--no-qc", *scene.common]
    assert run_cli(*args, "--samples", "2").rc == 0 and (out / "displacement_std.nii.gz").exists()
    assert run_cli(*args).rc == 1  # not empty
    assert run_cli(*args, "--overwrite").rc == 0
    assert not (out / "displacement_std.nii.gz").exists()  # no mix of two runs


def test_register_batch_folder_with_one_bad_scan(scene, tmp_path):
    scans, labels = tmp_path / "scans", tmp_path / "labels"
    scans.mkdir()
    labels.mkdir()
    for sid in ("A", "B"):
        shutil.copy(scene.moving, scans / f"{sid}.nii.gz")
    shutil.copy(scene.moving_label, labels / "A.nii.gz")
    bad = np.asarray(nib.load(scene.moving).dataobj).astype(np.float32)
    bad[0, 0, 0] = np.nan
    save_lps(scans / "C.nii.gz", bad, scene.moving_grid)
    out = tmp_path / "out"
    result = run_cli(
        "register-batch",
        "--moving",
        str(scans),
        "--moving-label-dir",
        str(labels),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(out),
        "--no-qc",
        *scene.common,
        *FAST_AFFINE,
    )
    assert result.rc == 1
    assert "1 of 3 scans failed" in result.err and "registering" in result.err  # the progress bar
    rows = {row["scan"]: row for row in csv.DictReader((out / "batch_summary.csv").open())}
    assert [rows[s]["status"] for s in "ABC"] == ["ok", "ok", "failed"]
    assert float(rows["A"]["mean_dice"]) > 0.85 and rows["B"]["mean_dice"] == ""  # B has no labels
    assert "NaN" in rows["C"]["error"] and "C.nii.gz" in rows["C"]["error"]
    assert sorted(p.name for p in out.iterdir()) == ["A", "B", "batch_summary.csv"]  # nothing for C
    assert "failed" in result.out and "A" in result.out


def test_help_explains_the_fixed_image(capsys):
    with pytest.raises(SystemExit) as info:
        main(["register", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    assert "--fixed" in text and "MNI ICBM152 2009a" in text and "warp.nii.gz" in text and "--samples" in text


def test_console_script_is_declared():
    import tomllib

    project = tomllib.loads((BUNDLE_DIR.parent / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["monai-probreg"] == "monai_probreg.cli.main:run"


@pytest.mark.parametrize(
    "argv, status",
    [
        (["--help"], 0),
        (["register", "--moving", "m.nii.gz"], 2),
        (["register", "--moving", "missing.nii.gz", "--out", "o"], 1),
    ],
)
def test_console_entry_point_keeps_the_exit_status_and_the_output(tmp_path, argv, status):
    """``run`` leaves with os._exit (no interpreter teardown): the status is main's and nothing printed is lost."""
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "monai_probreg.cli", *argv],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
        timeout=300,
    )
    assert result.returncode == status
    if status == 0:
        assert "register-batch" in result.stdout and result.stdout.rstrip().endswith("show this help message and exit")
    elif status == 1:
        assert result.stderr.startswith("monai-probreg: error: --moving 'missing.nii.gz': no such file")


def test_the_torch_path_loads_no_itk_module(scene, tmp_path):
    """NIfTI in, NIfTI out, the torch affine: ITK's modules (about 1.7 s to load) are never needed, so never loaded
    (a fresh process: this one has ITK loaded by other tests)."""
    import subprocess
    import sys

    argv = [
        "register",
        "--moving",
        str(scene.moving),
        "--moving-label",
        str(scene.moving_label),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(tmp_path / "out"),
        "--threads",
        "1",
        *scene.common,
        *FAST_AFFINE,
    ]
    code = (
        "import json, sys\nfrom monai_probreg.cli.main import main\n"
        f"status = main({argv!r})\n"
        "print(json.dumps([status, sorted(m for m in sys.modules if m.startswith('itk.') and m.endswith('Python'))]))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=600)
    status, loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert status == 0, done.stderr[-2000:]
    assert loaded == [] and (tmp_path / "out" / "warp.nii.gz").is_file()


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as info:
        main(["register", "--moving", "m.nii.gz"])
    assert info.value.code == 2 and "--fixed" in capsys.readouterr().err


# ---------------------------------------------------------------------------------- bad input: one test each
def _fails(scene, tmp_path, *argv: str, moving: Path | None = None, label: Path | None = None) -> str:
    """Run register expecting failure; return the one-line error. Nothing may be left in or next to DIR."""
    out = tmp_path / "out"
    args = ["register", "--moving", str(moving or scene.moving), "--out", str(out), *scene.common, *argv]
    if label is not None:
        args += ["--moving-label", str(label)]
    return one_error_line(run_cli(*args), out)


def test_bad_refine_steps(scene, tmp_path):
    line = _fails(scene, tmp_path, "--refine", "-2")
    assert "--refine" in line and "got -2" in line


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (("--smoothness", "0"), "got 0.0"),
        (("--smoothness", "-1"), "got -1.0"),
        (("--smoothness", "nan"), "got nan"),
        (("--smoothness", "2", "--refine", "0"), "got --refine 0"),
    ],
)
def test_bad_smoothness(scene, tmp_path, extra, expected):
    line = _fails(scene, tmp_path, *extra)
    assert "--smoothness" in line and expected in line


def test_smoothness_scales_the_refinements_prior(scene, tmp_path):
    """--smoothness S: the refinement's prior_lambda is the config's times S (recorded in summary.json), its other
    settings as shipped (what a larger prior does to the warp: tests/engines/test_refinement.py)."""
    out = tmp_path / "smooth"
    result = _register(scene, out, "--smoothness", "2.5", "--refine", "3", "--no-qc", *FAST_AFFINE)
    assert result.rc == 0, result.err
    refinement = json.loads((out / "summary.json").read_text())["model"]["refinement"]
    config = ConfigParser.load_config_file(str(Path(scene.bundle) / "configs" / "inference.yaml"))
    assert refinement["prior_lambda"] == pytest.approx(config["refine_prior_lambda"] * 2.5)
    assert refinement["num_iterations"] == 3


def test_contrast_other_needs_the_refinement(scene, tmp_path):
    line = _fails(scene, tmp_path, "--contrast", "other", "--refine", "0")
    assert "--contrast other" in line and "got --refine 0" in line


def test_contrast_other_refines_with_the_configs_other_contrast_settings(scene, tmp_path):
    """--contrast other: the refinement's fields of the config's ``other_contrast`` (no pull towards the network's
    mean, recorded in summary.json), its other settings as shipped; --smoothness still scales the prior."""
    out = tmp_path / "other"
    result = _register(scene, out, "--contrast", "other", "--smoothness", "2", "--refine", "3", "--no-qc", *FAST_AFFINE)
    assert result.rc == 0, result.err
    model = json.loads((out / "summary.json").read_text())["model"]
    refinement = model["refinement"]
    config = ConfigParser.load_config_file(str(Path(scene.bundle) / "configs" / "inference.yaml"))
    assert model["contrast_match_bins"] == 0  # the moving scan as it is, without --match-contrast
    assert refinement["posterior_weight"] == config["contrast_posterior_weight"] == 0.0
    assert config["refine_posterior_weight"] > 0  # what --contrast same keeps
    assert refinement["image_loss"] == config["refine_image_loss"]
    assert refinement["prior_lambda"] == pytest.approx(config["refine_prior_lambda"] * 2)
    assert refinement["num_iterations"] == 3


def test_match_contrast_maps_the_moving_scan_over_the_configs_bins(scene, tmp_path):
    """--contrast other --match-contrast: summary.json records the config's contrast_match_bins (what register_scan
    then maps the moving scan with: tests/registration/test_scan.py), the refinement as --contrast other's."""
    out = tmp_path / "matched"
    result = _register(scene, out, "--contrast", "other", "--match-contrast", "--refine", "2", "--no-qc", *FAST_AFFINE)
    assert result.rc == 0, result.err
    model = json.loads((out / "summary.json").read_text())["model"]
    config = ConfigParser.load_config_file(str(Path(scene.bundle) / "configs" / "inference.yaml"))
    assert model["contrast_match_bins"] == config["contrast_match_bins"] >= 2
    assert model["refinement"]["posterior_weight"] == config["contrast_posterior_weight"]


def test_match_contrast_needs_contrast_other(scene, tmp_path):
    line = _fails(scene, tmp_path, "--match-contrast")
    assert line.endswith("--match-contrast maps a second contrast onto the first: expected --contrast other too")


def test_match_contrast_without_the_configs_bins_says_so(tmp_path):
    from monai_probreg.cli.main import _with_refinement
    from monai_probreg.engines.refinement import RefinementSettings
    from monai_probreg.registration.options import RegistrationOptions
    from monai_probreg.utils.errors import InputError

    model = SimpleNamespace(
        refinement=RefinementSettings(num_iterations=3),
        other_contrast={"posterior_weight": 0.0},
        contrast_match_bins=0,
        config_file=tmp_path / "mine.yaml",
    )
    with pytest.raises(InputError, match=r"--match-contrast: expected the config's 'contrast_match_bins'.*mine.yaml"):
        _with_refinement(RegistrationOptions(), model, None, None, "other", True)
    model.contrast_match_bins = 32
    assert _with_refinement(RegistrationOptions(), model, None, None, "other", True).contrast_match_bins == 32
    assert _with_refinement(RegistrationOptions(), model, None, None, "other").contrast_match_bins == 0


def test_contrast_other_is_handed_to_the_registration(tmp_path):
    """--contrast other reaches RegistrationOptions.contrast (no quality estimate there), besides the refinement's
    other_contrast fields; --contrast same leaves the default."""
    from monai_probreg.cli.main import _with_refinement
    from monai_probreg.engines.refinement import RefinementSettings
    from monai_probreg.registration.options import RegistrationOptions

    model = SimpleNamespace(
        refinement=RefinementSettings(num_iterations=3),
        other_contrast={"posterior_weight": 0.0},
        contrast_match_bins=0,
        config_file=tmp_path / "mine.yaml",
    )
    from monai_probreg.cli.main import build_parser
    from monai_probreg.registration.options import CONTRASTS

    choices = next(
        a.choices
        for g in build_parser()._subparsers._group_actions
        for a in g.choices["register"]._actions
        if a.dest == "contrast"
    )
    assert tuple(choices) == CONTRASTS  # the command's choices are the options' (one list, written twice)
    other = _with_refinement(RegistrationOptions(), model, None, None, "other")
    assert other.contrast == "other" and other.refinement.posterior_weight == 0.0
    assert _with_refinement(RegistrationOptions(), model, 3, None, "same").contrast == "same"


def test_contrast_other_without_the_configs_settings_says_so(tmp_path):
    from monai_probreg.cli.main import _with_refinement
    from monai_probreg.engines.refinement import RefinementSettings
    from monai_probreg.registration.options import RegistrationOptions
    from monai_probreg.utils.errors import InputError

    model = SimpleNamespace(
        refinement=RefinementSettings(num_iterations=3), other_contrast={}, config_file=tmp_path / "mine.yaml"
    )
    with pytest.raises(
        InputError, match=r"--contrast other: expected the config's 'other_contrast' settings, got none"
    ):
        _with_refinement(RegistrationOptions(), model, None, None, "other")
    assert _with_refinement(RegistrationOptions(), model, None, None, "same").refinement is None  # the config's


def test_a_bad_other_contrast_setting_names_the_config(tmp_path):
    from monai_probreg.engines.refinement import RefinementSettings
    from monai_probreg.registration.model import _other_contrast
    from monai_probreg.utils.errors import InputError

    parser = ConfigParser({"other_contrast": {"image_loss": "mind", "mind_dilation": 0}})
    with pytest.raises(InputError, match=r"mine.yaml.*bad 'other_contrast' settings.*mind_dilation"):
        _other_contrast(parser, RefinementSettings(num_iterations=3), tmp_path / "mine.yaml")
    assert _other_contrast(ConfigParser({}), RefinementSettings(), tmp_path / "mine.yaml") == {}


def _register(scene, out: Path, *extra: str):
    """``register`` of the scene's moving scan into ``out`` with the scene's fixed image and bundle, plus ``extra``."""
    return run_cli("register", "--moving", str(scene.moving), "--out", str(out), *extra, *scene.common)


def test_refine_adds_its_stage_and_records_its_settings(scene, tmp_path):
    """--refine N: a ``refine`` stage between ``model`` and ``maps``, its settings in summary.json (the rest from the
    bundle's inference.yaml), no folding."""
    out = tmp_path / "refined"
    result = _register(scene, out, "--refine", "3", "--no-qc", *FAST_AFFINE)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["timings_s"])[3:6] == ["model", "refine", "maps"]
    assert summary["model"]["refinement"]["num_iterations"] == 3
    assert summary["model"]["refinement"]["prior_lambda"] > 0 and summary["jacobian"]["num_nonpositive"] == 0
    assert "refine" in result.err


def test_dice_counts_only_the_labels_both_maps_have(scene, tmp_path):
    """A moving label map without one of the fixed labels (another protocol) is scored on the labels both have; the
    summary says so and counts the fixed-only labels."""
    dropped = PHANTOM_LABELS[-1]
    labels = np.asarray(nib.load(scene.moving_label).dataobj).copy()
    labels[labels == dropped] = 0
    partial = save_lps(tmp_path / "partial_label.nii.gz", labels.astype(np.uint8), scene.moving_grid)
    out = tmp_path / "partial"
    result = run_cli(
        "register",
        "--moving",
        str(scene.moving),
        "--moving-label",
        str(partial),
        "--fixed-label",
        str(scene.fixed_label),
        "--out",
        str(out),
        "--no-qc",
        *scene.common,
        *FAST_AFFINE,
    )
    assert result.rc == 0, result.err
    dice = json.loads((out / "summary.json").read_text())["dice"]
    assert set(dice["per_label"]) == set(dice["per_label_affine_only"]) == {str(v) for v in PHANTOM_LABELS[:-1]}
    assert dice["num_fixed_only_labels"] == 1 and dice["mean"] > 0.85  # not dragged down by a 0 for the dropped one


def test_bad_brain_mask_margin(scene, tmp_path):
    line = _fails(scene, tmp_path, "--brain-mask-margin", "-1")
    assert "--brain-mask-margin" in line and "got -1" in line


def test_brain_mask_of_a_skull_stripped_fixed_image_is_recorded_and_can_be_switched_off(scene, registered, tmp_path):
    """A fixed image with a background at its minimum (skull-stripped: the phantom outside its labels set to 0) gets a
    brain mask (its support + 3 mm) and the summary says so; --no-brain-mask records none; the noisy phantom itself has
    no background, so nothing is hidden."""
    assert json.loads((registered.dir / "summary.json").read_text())["model"]["brain_mask"] is None
    stripped = save_lps(
        tmp_path / "stripped.nii.gz", np.where(scene.labels > 0, scene.image, 0.0).astype(np.float32), FIXED_LPS
    )
    fraction = {}
    for name, extra in (("masked", []), ("unmasked", ["--no-brain-mask"])):
        out = tmp_path / name
        result = run_cli(
            "register",
            "--moving",
            str(scene.moving),
            "--out",
            str(out),
            "--fixed",
            str(stripped),
            "--bundle-root",
            str(scene.bundle),
            "--no-qc",
            *extra,
            *FAST_AFFINE,
        )
        assert result.rc == 0, result.err
        fraction[name] = json.loads((out / "summary.json").read_text())["model"]["brain_mask"]
    assert fraction["unmasked"] is None and fraction["masked"]["margin_mm"] == 3.0
    support = float((scene.labels > 0).mean())
    assert support < fraction["masked"]["fraction_of_fixed_grid"] < 1.0  # the support, dilated


def test_refinement_is_on_by_default(registered):
    """The default path refines the network's mean (inference.yaml's refine_iterations: the network alone does not
    generalise beyond its training data); the stage is timed and its settings recorded."""
    summary = json.loads((registered.dir / "summary.json").read_text())
    steps = ConfigParser.load_config_file(str(BUNDLE_DIR / "configs" / "inference.yaml"))["refine_iterations"]
    assert steps > 0 and summary["model"]["refinement"]["num_iterations"] == steps and "refine" in summary["timings_s"]


def test_refine_0_gives_the_network_alone(scene, tmp_path):
    out = tmp_path / "network"
    result = _register(scene, out, "--refine", "0", "--no-qc", *FAST_AFFINE)
    assert result.rc == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["model"]["refinement"]["num_iterations"] == 0 and "refine" not in summary["timings_s"]


def _bad_image(tmp_path: Path, name: str, data: np.ndarray) -> Path:
    return save_lps(tmp_path / name, data, FIXED_LPS)


def test_bad_missing_file(scene, tmp_path):
    line = _fails(scene, tmp_path, moving=tmp_path / "missing.nii.gz")
    assert "--moving" in line and "missing.nii.gz" in line and "no such file" in line


def test_bad_unreadable_file(scene, tmp_path):
    (tmp_path / "garbage.nii.gz").write_bytes(b"\x00not an image" * 100)
    assert "garbage.nii.gz" in _fails(scene, tmp_path, moving=tmp_path / "garbage.nii.gz")


def test_bad_two_dimensional_image(scene, tmp_path):
    path = tmp_path / "slice.nii.gz"
    nib.save(nib.Nifti1Image(np.random.default_rng(0).random((30, 30)).astype(np.float32), np.eye(4)), path)
    line = _fails(scene, tmp_path, moving=path)
    assert "slice.nii.gz" in line and "2-D" in line


def test_bad_four_dimensional_image(scene, tmp_path):
    path = tmp_path / "fmri.nii.gz"
    nib.save(nib.Nifti1Image(np.random.default_rng(0).random((20, 20, 20, 4)).astype(np.float32), np.eye(4)), path)
    line = _fails(scene, tmp_path, moving=path)
    assert "fmri.nii.gz" in line and "4-D" in line


def test_bad_nan_voxels(scene, tmp_path):
    data = scene.image.copy()
    data[5, 5, 5] = np.nan
    line = _fails(scene, tmp_path, moving=_bad_image(tmp_path, "nan.nii.gz", data))
    assert "nan.nii.gz" in line and "NaN" in line


def test_bad_inf_voxels_in_the_fixed_image(scene, tmp_path):
    data = scene.image.copy()
    data[5, 5, 5] = -np.inf
    fixed = _bad_image(tmp_path, "inf_atlas.nii.gz", data)
    line = _fails(scene, tmp_path, "--fixed", str(fixed))  # the later --fixed wins
    assert "--fixed" in line and "inf_atlas.nii.gz" in line and "Inf" in line


def test_bad_constant_image(scene, tmp_path):
    line = _fails(scene, tmp_path, moving=_bad_image(tmp_path, "blank.nii.gz", np.zeros((20, 20, 20), np.float32)))
    assert "blank.nii.gz" in line and "constant" in line


def test_bad_non_integer_labels(scene, tmp_path):
    fuzzy = np.asarray(nib.load(scene.moving_label).dataobj).astype(np.float32) * 0.5
    label = save_lps(tmp_path / "fuzzy.nii.gz", fuzzy, scene.moving_grid)
    line = _fails(scene, tmp_path, label=label)
    assert "--moving-label" in line and "fuzzy.nii.gz" in line and "non-integer" in line


def test_bad_labels_on_another_grid(scene, tmp_path):
    label = save_lps(tmp_path / "atlas_grid.nii.gz", scene.labels, FIXED_LPS)  # the atlas grid, not the scan's
    line = _fails(scene, tmp_path, label=label)
    assert "atlas_grid.nii.gz" in line and "moving.nii.gz" in line and "not on the grid" in line


def test_bad_output_folder_not_empty(scene, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    result = _register(scene, out)
    assert result.rc == 1 and "not empty" in result.err and "--overwrite" in result.err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_bad_nondeterministic_affine_without_the_itk_backend(scene, tmp_path):
    line = _fails(scene, tmp_path, "--nondeterministic-affine")
    assert "--nondeterministic-affine" in line and "--affine-backend itk" in line


def test_bad_affine_max_samples_with_the_itk_backend(scene, tmp_path):
    line = _fails(scene, tmp_path, "--affine-backend", "itk", "--affine-max-samples", "1000")
    assert "--affine-max-samples" in line and "torch only" in line


def test_bad_negative_affine_max_samples(scene, tmp_path):
    line = _fails(scene, tmp_path, "--affine-max-samples", "-5")
    assert "--affine-max-samples" in line and "got -5" in line


def test_bad_affine_iterations_per_level(scene, tmp_path):
    line = _fails(scene, tmp_path, "--affine-levels", "4", "2", "--affine-iterations", "10")
    assert "--affine-iterations" in line and "got 1" in line


def test_bad_negative_affine_iterations(scene, tmp_path):
    line = _fails(scene, tmp_path, "--affine-levels", "2", "1", "--affine-iterations", "10", "-1")
    assert "iterations must be >= 0" in line


def test_affine_backend_and_levels_are_recorded(scene, tmp_path):
    """--affine-levels without --affine-iterations: the backend's defaults for the first levels (torch: rigid 30, 15;
    affine 30, 15); the backend is in summary.json."""
    out = tmp_path / "levels"
    result = _register(scene, out, "--no-qc", "--affine-levels", "2", "1")
    assert result.rc == 0, result.err
    settings = json.loads((out / "summary.json").read_text())["affine"]["settings"]
    assert settings["backend"] == "torch" and settings["shrink_factors"] == [2, 1]
    assert settings["rigid_iterations"] == [30, 15] and settings["affine_iterations"] == [30, 15]


def test_bad_samples(scene, tmp_path):
    assert "--samples" in _fails(scene, tmp_path, "--samples", "1")


def test_bad_model_file(scene, tmp_path):
    line = _fails(scene, tmp_path, "--model-file", str(tmp_path / "nope.pt"))
    assert "--model-file" in line and "nope.pt" in line


def test_bad_model_file_for_the_config(scene, tmp_path):
    torch.save({"network": {}, "optimizer": {}}, tmp_path / "checkpoint.pt")  # a training checkpoint, not weights
    line = _fails(scene, tmp_path, "--model-file", str(tmp_path / "checkpoint.pt"))
    assert "checkpoint.pt" in line and "does not fit" in line


@pytest.mark.parametrize("value", [1, -2, 2.5, "64", True])
def test_a_bad_contrast_match_bins_names_the_config(tmp_path, value):
    from monai_probreg.registration.model import _contrast_match_bins
    from monai_probreg.utils.errors import InputError

    with pytest.raises(InputError, match=r"mine.yaml.*bad 'contrast_match_bins': expected 0 \(none\) or an integer"):
        _contrast_match_bins(ConfigParser({"contrast_match_bins": value}), tmp_path / "mine.yaml")
    assert _contrast_match_bins(ConfigParser({}), tmp_path / "mine.yaml") == 0  # no such key: not mapped
    assert _contrast_match_bins(ConfigParser({"contrast_match_bins": 0}), tmp_path / "mine.yaml") == 0


@pytest.mark.parametrize("given", [[], ["--affine-local", "never"], ["--affine-local", "always"]])
def test_affine_local_reaches_the_affine_settings(given):
    """--affine-local's choices and default are AffineSettings' (one list, written twice: --help stays light), and
    the choice reaches the affine stage's settings (the default: for --contrast other)."""
    from monai_probreg.cli.main import _options, build_parser
    from monai_probreg.spatial.affine_settings import LOCAL_STAGE, AffineSettings

    parser = build_parser()
    action = next(
        a for g in parser._subparsers._group_actions for a in g.choices["register"]._actions if a.dest == "affine_local"
    )
    assert tuple(action.choices) == LOCAL_STAGE and action.default == AffineSettings().local_stage
    args = parser.parse_args(["register", "--moving", "m.nii.gz", "--out", "out", *given])
    expected = given[1] if given else "other-contrast"
    assert _options(args).affine.local_stage == expected
