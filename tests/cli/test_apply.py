"""``monai-probreg apply``: a field or affine file applied to an image or label map, as antsApplyTransforms does.

Conventions pinned here with files written by nibabel, not by the package: a field pulls back, ``out(p) =
moving(p + D(p))``, D in LPS mm (so +2 mm along L moves content of a RAS-stored array to higher i, +2 mm along S to
lower k); NIfTI intent 1006 holds RAS components, which ITK (and so ANTs) turns into LPS. ITK's
``ResampleImageFilter`` with a ``DisplacementFieldTransform`` is the stand-in for antsApplyTransforms (ANTs
resamples with it). And ``register``'s own outputs come back byte for byte.
"""

from __future__ import annotations

import os
import struct
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
    OBLIQUE_DIRECTION,
    asymmetric_phantom,
    moved_phantom,
    rigid_matrix,
    run_cli,
    save_lps,
    tiny_bundle,
)

from monai_probreg.cli.main import main
from monai_probreg.registration.output_folder import write_transform
from monai_probreg.spatial.physical import (
    affine_from_itk,
    displacement_transform,
    grid_points,
    resample_with_itk,
)

SHAPE = (24, 26, 22)
RAS_STORED = np.diag([-1.0, -1.0, 1.0, 1.0])  # index -> LPS of an array stored RAS (nibabel affine = identity)


def _oblique_grid(shape, spacing, centre) -> np.ndarray:
    """An index -> LPS grid with permuted, flipped, anisotropic axes centred on ``centre`` (LPS mm)."""
    grid = np.eye(4)
    grid[:3, :3] = OBLIQUE_DIRECTION * np.asarray(spacing)
    grid[:3, 3] = np.asarray(centre) - grid[:3, :3] @ ((np.asarray(shape) - 1) / 2)
    return grid


def _save_field(path: Path, field: np.ndarray, index_to_lps: np.ndarray, intent: str | int = "vector") -> Path:
    """A displacement field file as ANTs writes it, by nibabel: (X, Y, Z, 1, 3) float32, intent ``intent``."""
    image = nib.Nifti1Image(np.asarray(field, np.float32)[:, :, :, None, :], RAS_STORED @ index_to_lps)
    image.header.set_intent(intent)
    nib.save(image, path)
    return path


def _smooth_field(shape, magnitude_mm: float, seed: int) -> np.ndarray:
    """A smooth random field (*shape, 3) of at most ``magnitude_mm``."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    coarse = rng.standard_normal((3, 3, 3, 3))
    field = np.stack([ndimage.zoom(coarse[..., c], np.asarray(shape) / 3, order=1) for c in range(3)], -1)
    return field * magnitude_mm / np.abs(field).max()


def _apply(*argv: str) -> SimpleNamespace:
    return run_cli("apply", *[str(a) for a in argv])


def _array(path: Path) -> np.ndarray:
    return np.asarray(nib.load(path).dataobj)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """The asymmetric phantom and its labels on an oblique anisotropic grid (the moving image), a reference grid
    of another orientation and spacing over the same region, and a smooth field on a third grid covering part of it."""
    root = tmp_path_factory.mktemp("apply")
    image, labels = asymmetric_phantom()
    moving_grid = _oblique_grid(image.shape, (1.1, 0.9, 1.2), (4.0, -6.0, 10.0))
    centre = grid_points(image.shape, moving_grid).reshape(-1, 3).mean(0)
    reference_grid = np.eye(4)
    reference_grid[:3, :3] = np.diag([-1.2, -1.0, 1.1])
    reference_grid[:3, 3] = centre - reference_grid[:3, :3] @ ((np.asarray(SHAPE) - 1) / 2)
    field_shape = (12, 14, 11)  # about 24 mm across: part of the reference grid lies outside it
    field_grid = _oblique_grid(field_shape, (2.0, 1.8, 2.1), centre + [1.0, -2.0, 0.5])
    files = {
        "moving": save_lps(root / "moving.nii.gz", image, moving_grid),
        "label": save_lps(root / "label.nii.gz", labels, moving_grid),
        "reference": save_lps(root / "reference.nii.gz", np.zeros(SHAPE, np.float32), reference_grid),
        "field": _save_field(root / "field.nii.gz", _smooth_field(field_shape, 4.0, 0), field_grid),
        "field_on_reference": _save_field(
            root / "field_on_reference.nii.gz", _smooth_field(SHAPE, 4.0, 1), reference_grid
        ),
    }
    return SimpleNamespace(image=image, labels=labels, moving_grid=moving_grid, **files)


def _itk_resampled(moving: Path, reference: Path, transform, nearest: bool = False) -> np.ndarray:
    """ITK's resampling (antsApplyTransforms' own), index order."""
    pixel = itk.SS if nearest else itk.F
    out = resample_with_itk(itk.imread(str(moving), pixel), itk.imread(str(reference), itk.F), transform, nearest)
    return itk.array_from_image(out).transpose(2, 1, 0)


# ------------------------------------------------------------------------------------------------ conventions
@pytest.mark.parametrize(
    "axis, lps_mm, intent, expected_shift",
    [
        (0, (2.0, 0.0, 0.0), "vector", (2, 0, 0)),  # +L: index i of a RAS-stored array counts towards R
        (1, (0.0, 2.0, 0.0), "vector", (0, 2, 0)),  # +P
        (2, (0.0, 0.0, 2.0), "vector", (0, 0, -2)),  # +S: index k counts towards S
        (0, (-2.0, 0.0, 0.0), 1006, (2, 0, 0)),  # intent 1006 stores RAS: -2 mm R is +2 mm L
    ],
)
def test_constant_field_pulls_back_in_lps(tmp_path, axis, lps_mm, intent, expected_shift):
    """out(p) = moving(p + D): with D = +2 mm along L, out[i] = moving[i - 2], so content moves 2 voxels to higher i.
    Exact (integer voxel shifts): linear interpolation at voxel centres returns the voxel."""
    image, _ = asymmetric_phantom(SHAPE)
    moving = save_lps(tmp_path / "moving.nii.gz", image, RAS_STORED)
    field = np.broadcast_to(np.asarray(lps_mm), (*SHAPE, 3))
    path = _save_field(tmp_path / "shift.nii.gz", field, RAS_STORED, intent)
    result = _apply("-t", path, "-i", moving, "-r", moving, "-o", tmp_path / "out.nii.gz")
    assert result.rc == 0, result.err
    out = _array(tmp_path / "out.nii.gz")
    expected = np.zeros_like(image)
    shift = expected_shift[axis]
    src = [slice(None)] * 3
    dst = [slice(None)] * 3
    src[axis] = slice(0, SHAPE[axis] - shift) if shift > 0 else slice(-shift, None)
    dst[axis] = slice(shift, None) if shift > 0 else slice(0, SHAPE[axis] + shift)
    expected[tuple(dst)] = image[tuple(src)]
    np.testing.assert_allclose(out, expected, atol=1e-6)
    assert out.dtype == np.float32
    np.testing.assert_allclose(nib.load(tmp_path / "out.nii.gz").affine, np.eye(4), atol=1e-6)


def test_identity_field_returns_the_image_and_the_labels(scene, tmp_path):
    """D = 0 on the moving grid, the moving image as the reference: the image itself (to float32 rounding of the
    index arithmetic: 1e-6 of its range) and the labels exactly, with the moving image's header."""
    zero = _save_field(tmp_path / "zero.nii.gz", np.zeros((*scene.image.shape, 3)), scene.moving_grid)
    assert _apply("-t", zero, "-i", scene.moving, "-r", scene.moving, "-o", tmp_path / "image.nii.gz").rc == 0
    np.testing.assert_allclose(_array(tmp_path / "image.nii.gz"), scene.image, atol=1e-6 * np.ptp(scene.image))
    argv = ("-t", zero, "-i", scene.label, "-r", scene.moving, "-o", tmp_path / "label.nii.gz", "-n", "nearest")
    assert _apply(*argv).rc == 0
    np.testing.assert_array_equal(_array(tmp_path / "label.nii.gz"), scene.labels)
    np.testing.assert_allclose(nib.load(tmp_path / "label.nii.gz").affine, nib.load(scene.moving).affine, atol=1e-5)


def test_nearest_keeps_the_label_set_and_an_integer_type(scene, tmp_path):
    """Nearest neighbour invents no label; a map of labels < 256 is written as uint8, larger ones as int16 (as
    register writes labels); linear gives float32."""
    argv = ("-t", scene.field_on_reference, "-r", scene.reference, "-n", "nearest")
    assert _apply(*argv, "-i", scene.label, "-o", tmp_path / "small.nii.gz").rc == 0
    small = nib.load(tmp_path / "small.nii.gz")
    assert small.get_data_dtype() == np.uint8
    assert set(np.unique(small.dataobj)) == set(np.unique(scene.labels))  # a 4 mm field keeps every label
    big = save_lps(tmp_path / "big.nii.gz", (scene.labels * 1000).astype(np.int32), scene.moving_grid)
    assert _apply(*argv, "-i", big, "-o", tmp_path / "big_out.nii.gz").rc == 0
    out = nib.load(tmp_path / "big_out.nii.gz")
    assert out.get_data_dtype() == np.int16
    np.testing.assert_array_equal(np.asarray(out.dataobj), 1000 * np.asarray(small.dataobj, dtype=np.int32))
    linear = ("-t", scene.field_on_reference, "-r", scene.reference, "-i", scene.label, "-o", tmp_path / "l.nii.gz")
    assert _apply(*linear).rc == 0 and nib.load(tmp_path / "l.nii.gz").get_data_dtype() == np.float32


@pytest.mark.parametrize("which", ["field_on_reference", "field"])
def test_itk_resampling_reproduces_apply(scene, tmp_path, which):
    """ITK's ResampleImageFilter + DisplacementFieldTransform (what antsApplyTransforms runs), the field on the
    reference grid or on a third, coarser, oblique grid that covers part of it (interpolated, identity outside).
    Acceptance: labels identical in >= 99.9% of voxels, images within 1% of their range; what is asserted is much
    tighter: labels identical, images within 1e-5 of the range (float64 sampling here and in ITK, float32 files)."""
    field = getattr(scene, which)
    transform = displacement_transform(itk.imread(str(field)))
    result = _apply("-t", field, "-i", scene.moving, "-r", scene.reference, "-o", tmp_path / "image.nii.gz")
    assert result.rc == 0, result.err
    ours = _array(tmp_path / "image.nii.gz")
    theirs = _itk_resampled(scene.moving, scene.reference, transform)
    assert np.ptp(ours) > 0.5 * np.ptp(scene.image)  # the phantom is in view
    np.testing.assert_allclose(ours, theirs, atol=1e-5 * np.ptp(scene.image))
    argv = ("-t", field, "-i", scene.label, "-r", scene.reference, "-o", tmp_path / "label.nii.gz", "-n", "nearest")
    assert _apply(*argv).rc == 0
    labels = _array(tmp_path / "label.nii.gz")
    np.testing.assert_array_equal(labels, _itk_resampled(scene.label, scene.reference, transform, nearest=True))
    assert len(np.unique(labels)) == 5
    partly = which == "field"  # the coarse grid leaves some of the reference uncovered: a warning, exit status 0
    assert ("outside the field's grid" in result.err) == partly


def _matlab_file(path: Path, name: str, parameters, fixed, dtype: str = "<f8") -> Path:
    """ITK's MATLAB v4 transform file (ANTs' *GenericAffine.mat): the parameters matrix named after the type, then
    'fixed'; MOPT type code 0 = little-endian float64, 10 = float32."""
    code = {"<f8": 0, "<f4": 10}[dtype]
    blob = b""
    for label, values in ((name, parameters), ("fixed", fixed)):
        values = np.asarray(values, dtype=dtype)
        encoded = label.encode() + b"\0"
        blob += struct.pack("<5i", code, values.size, 1, 0, len(encoded)) + encoded + values.tobytes()
    path.write_bytes(blob)
    return path


def test_affine_files_as_itk_reads_them(scene, tmp_path):
    """.tfm (ours and a hand-written MatrixOffsetTransformBase, which ITK's Python wrapping cannot create), .mat in
    float64 and float32 (ANTs' GenericAffine) and an Euler3DTransform (read through ITK): the same matrix ITK's
    reader gives where it reads the file, and the same resampling as ITK's with that transform."""
    centre = grid_points(scene.image.shape, scene.moving_grid).reshape(-1, 3).mean(0)
    matrix = rigid_matrix([6.0, -4.0, 9.0], [2.0, -1.5, 3.0], centre)
    matrix[:3, :3] = matrix[:3, :3] @ np.diag([1.04, 0.97, 1.01])
    pivot = centre + [3.0, 1.0, -2.0]
    params = [*matrix[:3, :3].ravel(), *(matrix[:3, 3] - pivot + matrix[:3, :3] @ pivot)]
    files = {
        "ours.tfm": write_transform(tmp_path / "ours.tfm", matrix, pivot),
        "double.mat": _matlab_file(tmp_path / "double.mat", "AffineTransform_double_3_3", params, pivot),
        "float.mat": _matlab_file(tmp_path / "float.mat", "AffineTransform_float_3_3", params, pivot, "<f4"),
    }
    for name, path in files.items():
        assert _apply("-t", path, "-i", scene.moving, "-r", scene.reference, "-o", tmp_path / f"{name}.nii.gz").rc == 0
        transform = itk.transformread(str(path))[0]
        tolerance = 1e-4 if name == "float.mat" else 1e-9  # float32 parameters: 1e-7 relative, ~1e-5 mm here
        np.testing.assert_allclose(affine_from_itk(transform), matrix, atol=tolerance * 100)
        theirs = _itk_resampled(scene.moving, scene.reference, transform)
        np.testing.assert_allclose(_array(tmp_path / f"{name}.nii.gz"), theirs, atol=1e-5 * np.ptp(scene.image))
    text = (
        (tmp_path / "ours.tfm")
        .read_text()
        .replace("AffineTransform_double_3_3", "MatrixOffsetTransformBase_double_3_3")
    )
    (tmp_path / "base.tfm").write_text(text)
    assert (
        _apply("-t", tmp_path / "base.tfm", "-i", scene.moving, "-r", scene.reference, "-o", tmp_path / "b.nii.gz").rc
        == 0
    )
    np.testing.assert_array_equal(_array(tmp_path / "b.nii.gz"), _array(tmp_path / "ours.tfm.nii.gz"))
    euler = itk.Euler3DTransform[itk.D].New()
    euler.SetCenter([float(c) for c in pivot])
    euler.SetRotation(0.1, -0.05, 0.2)
    euler.SetTranslation([1.0, -2.0, 0.5])
    (tmp_path / "euler.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: Euler3DTransform_double_3_3\n"
        f"Parameters: {' '.join(repr(float(p)) for p in euler.GetParameters())}\n"
        f"FixedParameters: {' '.join(repr(float(p)) for p in euler.GetFixedParameters())}\n"
    )
    assert (
        _apply("-t", tmp_path / "euler.tfm", "-i", scene.moving, "-r", scene.reference, "-o", tmp_path / "e.nii.gz").rc
        == 0
    )
    theirs = _itk_resampled(scene.moving, scene.reference, euler)
    np.testing.assert_allclose(_array(tmp_path / "e.nii.gz"), theirs, atol=1e-5 * np.ptp(scene.image))


def test_output_in_a_new_folder_and_overwrite(scene, tmp_path):
    out = tmp_path / "new" / "deeper" / "out.nii"
    argv = ("-t", scene.field_on_reference, "-i", scene.moving, "-r", scene.reference, "-o", out)
    assert _apply(*argv).rc == 0 and out.is_file()
    out.write_bytes(b"old")
    assert _apply(*argv, "--overwrite").rc == 0 and nib.load(out).shape == SHAPE


def test_help_explains_the_command(capsys):
    with pytest.raises(SystemExit) as info:
        main(["apply", "--help"])
    text = capsys.readouterr().out
    assert info.value.code == 0
    assert "antsApplyTransforms" in text and "warped_label.nii.gz" in text and "--interpolation" in text


# ---------------------------------------------------------------------------------- bad input: one test each
def _argv(scene, tmp_path: Path, **files) -> list[str]:
    """apply's arguments: the scene's inputs, ``files`` (transform, moving, reference, out) replacing them."""
    argv = {"-t": scene.field_on_reference, "-i": scene.moving, "-r": scene.reference, "-o": tmp_path / "out.nii.gz"}
    names = {"transform": "-t", "moving": "-i", "reference": "-r", "out": "-o"}
    argv.update({names[k]: v for k, v in files.items()})
    return [str(x) for pair in argv.items() for x in pair]


def _fails(scene, tmp_path: Path, **files) -> str:
    """Run apply with ``files`` replacing the scene's inputs, expecting exit status 1: one error line, nothing
    written in ``tmp_path`` (where the bad inputs and the output live). Returns the line."""
    before = sorted(tmp_path.rglob("*"))
    result = _apply(*_argv(scene, tmp_path, **files))
    assert result.rc == 1, result.err
    lines = [line for line in result.err.splitlines() if line.startswith("monai-probreg: error:")]
    assert len(lines) == 1 and len(result.err.splitlines()) == 1, result.err
    assert sorted(tmp_path.rglob("*")) == before  # nothing written, no temporary left
    return lines[0]


def _vector_file(path: Path, data: np.ndarray, intent: str | int | None = "vector") -> Path:
    image = nib.Nifti1Image(data.astype(np.float32), RAS_STORED @ FIXED_LPS)
    if intent is not None:
        image.header.set_intent(intent)
    nib.save(image, path)
    return path


def test_bad_missing_transform(scene, tmp_path):
    line = _fails(scene, tmp_path, transform=tmp_path / "nowarp.nii.gz")
    assert "--transform" in line and "nowarp.nii.gz" in line and "no such file" in line


def test_bad_unreadable_transform(scene, tmp_path):
    (tmp_path / "garbage.nii.gz").write_bytes(b"\x00not an image" * 100)
    line = _fails(scene, tmp_path, transform=tmp_path / "garbage.nii.gz")
    assert "--transform" in line and "garbage.nii.gz" in line


def test_bad_scalar_image_as_field(scene, tmp_path):
    line = _fails(scene, tmp_path, transform=scene.moving)
    assert "--transform" in line and "moving.nii.gz" in line and "not a displacement field" in line
    assert "got 1 value per voxel" in line


def test_bad_vector_length(scene, tmp_path):
    path = _vector_file(tmp_path / "two.nii.gz", np.zeros((8, 9, 10, 1, 2)))
    line = _fails(scene, tmp_path, transform=path)
    assert "two.nii.gz" in line and "expected 3 values per voxel" in line and "got 2 values" in line


def test_bad_four_dimensional_scalar_field(scene, tmp_path):
    path = _vector_file(tmp_path / "fourd.nii.gz", np.zeros((8, 9, 10, 3)), intent=None)
    line = _fails(scene, tmp_path, transform=path)
    assert "fourd.nii.gz" in line and "not a displacement field" in line and "dimension 5" in line


def test_bad_vector_without_an_intent(scene, tmp_path):
    """(X, Y, Z, 1, 3) without the intent 'vector': ITK reads a 5-D scalar image, not a field."""
    path = _vector_file(tmp_path / "nointent.nii.gz", np.zeros((8, 9, 10, 1, 3)), intent=None)
    line = _fails(scene, tmp_path, transform=path)
    assert "nointent.nii.gz" in line and "5-D" in line and "intent" in line


def test_bad_nan_in_the_field(scene, tmp_path):
    data = np.zeros((8, 9, 10, 1, 3))
    data[2, 3, 4, 0, 1] = np.nan
    line = _fails(scene, tmp_path, transform=_vector_file(tmp_path / "nan.nii.gz", data))
    assert "nan.nii.gz" in line and "NaN" in line


def test_bad_truncated_field(scene, tmp_path):
    whole = scene.field_on_reference.read_bytes()
    path = tmp_path / "cut.nii.gz"
    path.write_bytes(whole[: len(whole) // 2])
    line = _fails(scene, tmp_path, transform=path)
    assert "cut.nii.gz" in line and ("truncated" in line or "corrupt" in line)


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("empty.tfm", "#Insight Transform File V1.0\n", "one 'Transform:' line"),
        ("fsl.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "one 'Transform:' line"),
        ("two.tfm", "Transform: A\nParameters: 1\nTransform: B\nParameters: 1\n", "got 2"),
        (
            "short.tfm",
            "Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1\nFixedParameters: 0 0 0\n",
            "12 parameters",
        ),
        ("words.tfm", "Transform: AffineTransform_double_3_3\nParameters: a b c\n", "not numbers"),
        ("bspline.tfm", "Transform: BSplineTransform_double_3_3\nParameters: 0\nFixedParameters: 0\n", "BSpline"),
        ("cut.mat", b"\x00\x00\x00\x00\x0c\x00\x00\x00\x01\x00\x00\x00", "MATLAB"),
        ("binary.tfm", b"\xff\xfe\x00garbage", "binary"),
    ],
)
def test_bad_affine_file(scene, tmp_path, name, content, problem):
    path = tmp_path / name
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    line = _fails(scene, tmp_path, transform=path)
    assert "--transform" in line and name in line and problem in line, line


def test_bad_missing_moving(scene, tmp_path):
    line = _fails(scene, tmp_path, moving=tmp_path / "nothing.nii.gz")
    assert "--moving" in line and "nothing.nii.gz" in line and "no such file" in line


def test_bad_nan_in_the_moving_image(scene, tmp_path):
    data = scene.image.copy()
    data[3, 3, 3] = np.nan
    line = _fails(scene, tmp_path, moving=save_lps(tmp_path / "nanimg.nii.gz", data, scene.moving_grid))
    assert "--moving" in line and "nanimg.nii.gz" in line and "NaN" in line


def test_bad_reference(scene, tmp_path):
    (tmp_path / "ref.nrrd").write_text("NRRD0004\ntype: nonsense\n")
    line = _fails(scene, tmp_path, reference=tmp_path / "ref.nrrd")
    assert "--reference" in line and "ref.nrrd" in line


def test_a_field_as_the_reference_gives_its_own_grid(scene, tmp_path):
    """``-r warp.nii.gz``: the field's grid, as ANTs takes any image as the reference."""
    out = tmp_path / "out.nii.gz"
    assert _apply(*_argv(scene, tmp_path, reference=scene.field_on_reference)).rc == 0
    np.testing.assert_allclose(nib.load(out).affine, nib.load(scene.reference).affine, atol=1e-5)
    assert nib.load(out).shape == SHAPE


def test_bad_interpolation_is_a_usage_error(scene, tmp_path, capsys):
    """A value outside the choices is a malformed command line: exit status 2 as every choice option of the
    command (argparse names the option and the choices), nothing written."""
    with pytest.raises(SystemExit) as info:
        main(["apply", *_argv(scene, tmp_path), "-n", "cubic"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "--interpolation" in err and "cubic" in err and "'nearest'" in err
    assert list(tmp_path.iterdir()) == []


def test_ants_interpolation_names_are_accepted(scene, tmp_path):
    argv = ("-t", scene.field_on_reference, "-i", scene.label, "-r", scene.reference, "-o", tmp_path / "o.nii.gz")
    assert _apply(*argv, "-n", "NearestNeighbor").rc == 0
    assert nib.load(tmp_path / "o.nii.gz").get_data_dtype() == np.uint8


def test_bad_output_is_a_folder(scene, tmp_path):
    (tmp_path / "dir.nii.gz").mkdir()
    line = _fails(scene, tmp_path, out=tmp_path / "dir.nii.gz")
    assert "--out" in line and "dir.nii.gz" in line and "is a folder" in line


def test_bad_output_exists(scene, tmp_path):
    (tmp_path / "out.nii.gz").write_bytes(b"mine")
    line = _fails(scene, tmp_path)
    assert "--out" in line and "out.nii.gz" in line and "--overwrite" in line
    assert (tmp_path / "out.nii.gz").read_bytes() == b"mine"


def test_bad_output_suffix(scene, tmp_path):
    line = _fails(scene, tmp_path, out=tmp_path / "out.png")
    assert "--out" in line and "out.png" in line and ".nii.gz" in line


def test_bad_output_folder_is_a_file(scene, tmp_path):
    (tmp_path / "afile").write_text("x")
    line = _fails(scene, tmp_path, out=tmp_path / "afile" / "out.nii.gz")
    assert "--out" in line and "afile" in line and "not a folder" in line


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_bad_output_folder_not_writable(scene, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        line = _fails(scene, tmp_path, out=locked / "out.nii.gz")
    finally:
        locked.chmod(0o700)
    assert "--out" in line and "locked" in line and "permission" in line


# --------------------------------------------------------------------------- register's outputs, byte for byte
@pytest.fixture(scope="module")
def registered(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """``register`` on the moved phantom (random-weights tiny bundle, fast affine, no maps or figure)."""
    root = tmp_path_factory.mktemp("registered")
    case = moved_phantom([8.0, -6.0, 10.0], [3.0, -2.0, 2.0])
    s = SimpleNamespace(
        root=root,
        fixed=save_lps(root / "fixed.nii.gz", case.image, FIXED_LPS),
        fixed_label=save_lps(root / "fixed_label.nii.gz", case.labels, FIXED_LPS),
        moving=save_lps(root / "moving.nii.gz", np.round(case.moved * 3000 + 200).astype(np.int16), case.grid),
        moving_label=save_lps(root / "moving_label.nii.gz", case.moved_labels.astype(np.uint8), case.grid),
        out=root / "out",
    )
    bundle = tiny_bundle(root / "bundle", BUNDLE_DIR)
    result = run_cli(
        "register",
        *("--moving", str(s.moving), "--moving-label", str(s.moving_label)),
        *("--fixed", str(s.fixed), "--fixed-label", str(s.fixed_label)),
        *("--out", str(s.out), "--bundle-root", str(bundle), "--no-qc", "--no-maps", *FAST_AFFINE),
    )
    assert result.rc == 0, result.err
    return s


@pytest.mark.parametrize(
    "name, field, moving, reference, interpolation",
    [
        ("warped_label.nii.gz", "warp.nii.gz", "moving_label", "fixed", "nearest"),
        ("warped.nii.gz", "warp.nii.gz", "moving", "fixed", "linear"),
        ("fixed_label_in_moving.nii.gz", "inverse_warp.nii.gz", "fixed_label", "moving", "nearest"),
    ],
)
def test_apply_reproduces_registers_outputs_byte_for_byte(
    registered, tmp_path, name, field, moving, reference, interpolation
):
    """The same sampling code at the same points (the float32 field of the file, the inputs read by the same
    readers), written by the same writer: the same bytes, header included."""
    out = tmp_path / name
    result = _apply(
        *("-t", registered.out / field, "-i", getattr(registered, moving), "-r", getattr(registered, reference)),
        *("-o", out, "-n", interpolation),
    )
    assert result.rc == 0 and result.err == "", result.err
    assert len(np.unique(_array(out))) > 3  # the phantom's labels (or intensities) are in view
    assert out.read_bytes() == (registered.out / name).read_bytes()
