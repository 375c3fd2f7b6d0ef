"""Damaged and odd input files through both loading paths: the command line's reader (monai_probreg.spatial.volume_io) and the
bundle's (monai_probreg.data.transforms.LoadCheckedd, used by inference.yaml, evaluate.yaml and training).

Each case is one file and what must happen: either a one-line InputError that names the file and contains the
expected words, or a correct load (voxels equal to what was written, geometry equal to the header's). A raw
traceback, a hang or a silently different array fails the test. ``CASES`` is the catalogue docs/design.md counts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from rel_helpers import affine_of, flip_byte, rotation, save, set_header_dim, smooth, truncate

from monai_probreg.data.transforms import LoadCheckedd
from monai_probreg.spatial.checks import MAX_VOXELS_ENV
from monai_probreg.spatial.volume_io import LPS_TO_RAS, read_image, read_label
from monai_probreg.utils.errors import InputError

SHAPE = (9, 10, 11)
DATA = smooth(SHAPE)  # float64 in ~[0.2, 0.9]


@dataclass(frozen=True)
class Case:
    """``make(folder)`` writes the file and returns (path, voxels it must load as or None, RAS affine or None).
    ``io`` / ``bundle``: words the error must contain on that path, or None when it must load correctly."""

    name: str
    make: Callable[[Path], tuple[Path, np.ndarray | None, np.ndarray | None]]
    io: str | None
    bundle: str | None = "same"  # "same": as io
    label: bool = False
    env: dict | None = None


def _ok(name: str, data: np.ndarray, affine: np.ndarray | None = None, dtype=None, **kw) -> Callable:
    affine = np.eye(4) if affine is None else affine

    def make(folder: Path):
        path = save(folder / f"{name}.nii.gz", data, affine, dtype=dtype, **kw)
        expected = data * kw["slope"] + kw.get("inter", 0.0) if "slope" in kw else data
        return path, expected, affine

    return make


def _file(
    name: str, data: np.ndarray, affine: np.ndarray | None = None, edit: Callable | None = None, suffix: str = ".nii.gz"
) -> Callable:
    def make(folder: Path):
        path = save(folder / f"{name}{suffix}", data, np.eye(4) if affine is None else affine)
        return (edit(path) if edit else path), None, None

    return make


def _raw(name: str, content: bytes | None) -> Callable:
    def make(folder: Path):
        path = folder / name
        if content is None:
            path.mkdir()
        else:
            path.write_bytes(content)
        return path, None, None

    return make


def _with(value: float, where=(1, 2, 3), base: np.ndarray = DATA) -> np.ndarray:
    data = base.astype(np.float32).copy()
    data[where] = value
    return data


_LABELS = np.where(DATA > 0.5, 3, 0) + np.where(DATA > 0.7, 14, 0)
_NAN_AFFINE = np.eye(4)
_NAN_AFFINE[0, 3] = np.nan
_SHEAR = np.eye(4)
_SHEAR[0, 1] = 0.3

CASES = [
    # --- odd but valid: must load exactly ----------------------------------------------------------------------
    Case("float32", _ok("float32", DATA.astype(np.float32)), None),
    Case("float64", _ok("float64", DATA), None),
    Case("int8", _ok("int8", np.round(DATA * 200 - 100).astype(np.int8)), None),
    Case("uint8", _ok("uint8", np.round(DATA * 255).astype(np.uint8)), None),
    Case("int16", _ok("int16", np.round(DATA * 3000).astype(np.int16)), None),
    Case("uint16", _ok("uint16", np.round(DATA * 65000).astype(np.uint16)), None),
    Case("int32", _ok("int32", np.round(DATA * 1e9).astype(np.int32)), None),
    Case("int64", _ok("int64", np.round(DATA * 1e6).astype(np.int64), dtype=np.int64), None),
    Case(
        "scaled int16 (scl_slope)", _ok("scaled", np.round(DATA * 3000).astype(np.int16), slope=0.01, inter=-7.0), None
    ),
    Case("intensities 1e-6", _ok("tiny", (DATA * 1e-6).astype(np.float32)), None),
    Case("intensities 1e9", _ok("huge", (DATA * 1e9).astype(np.float32)), None),
    Case("intensities 1e30 (float64)", _ok("f64huge", DATA * 1e30), None),
    Case("negative intensities", _ok("negative", (DATA * 4000 - 5000).astype(np.float32)), None),
    Case("4-D with one volume", _ok("trailing1", DATA.astype(np.float32)[..., None]), None),
    Case(
        "anisotropic 0.05 x 1 x 20 mm", _ok("aniso", DATA.astype(np.float32), affine_of(np.eye(3), (0.05, 1, 20))), None
    ),
    Case(
        "oblique",
        _ok("oblique", DATA.astype(np.float32), affine_of(rotation((25, -40, 70)), (0.8, 1.3, 2.5), (-40, 12, 7))),
        None,
    ),
    Case(
        "permuted and flipped axes",
        _ok("permuted", DATA.astype(np.float32), affine_of(np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]]), (1, 1.5, 2))),
        None,
    ),
    Case("2 voxels thin", _ok("thin", smooth((2, 12, 12)).astype(np.float32)), None),
    Case("labels uint8", _ok("labels_u8", _LABELS.astype(np.uint8)), None, label=True),
    Case("labels float32, integer values", _ok("labels_f32", _LABELS.astype(np.float32)), None, label=True),
    Case("labels int16, ids > 255", _ok("labels_i16", (_LABELS * 150).astype(np.int16)), None, label=True),
    Case("labels all zero", _ok("labels_zero", np.zeros(SHAPE, np.uint8)), None, label=True),
    Case("sheared axes", _ok("shear", DATA.astype(np.float32), _SHEAR), "sheared", None),
    # --- damaged or unusable: one clear line -------------------------------------------------------------------
    Case("truncated .nii.gz", _file("cut", DATA, edit=lambda p: truncate(p, 0.5)), "truncated"),
    Case("truncated .nii", _file("cut_raw", DATA, edit=lambda p: truncate(p, 0.7), suffix=".nii"), "truncated"),
    Case("corrupt gzip (one byte flipped)", _file("flipped", DATA, edit=lambda p: flip_byte(p, 0.6)), "corrupt"),
    Case("not an image (garbage bytes)", _raw("garbage.nii.gz", b"\x1f\x8b\x08garbage" * 40), "corrupt"),
    Case("empty file", _raw("empty.nii.gz", b""), "empty file"),
    Case(
        "header size larger than data",
        _file("dims_up", DATA, edit=lambda p: set_header_dim(p, 1, 18), suffix=".nii"),
        "truncated",
    ),
    Case(
        "header size smaller than data (.nii)",
        _file("dims_down", DATA, edit=lambda p: set_header_dim(p, 1, 4), suffix=".nii"),
        "dimensions",
    ),
    Case(
        "header size smaller than data (.nii.gz)",
        _file("dims_down_gz", DATA, edit=lambda p: set_header_dim(p, 3, 5)),
        "dimensions",
    ),
    Case("zero-sized axis", _file("empty_axis", np.zeros((0, 4, 4), np.float32)), "at least 2 voxels"),
    Case("one voxel", _file("one_voxel", np.ones((1, 1, 1), np.float32)), "at least 2 voxels"),
    Case("2-D image", _file("slice", DATA[:, :, 0]), "2-D"),
    Case("4-D series", _file("series", np.stack([DATA] * 3, axis=-1)), "4-D"),
    Case("NaN voxel", _file("nan", _with(np.nan)), "1 NaN"),
    Case("+Inf voxel", _file("inf", _with(np.inf)), "1 Inf"),
    Case("-Inf voxel", _file("neg_inf", _with(-np.inf)), "1 Inf"),
    Case("float64 beyond float32", _file("overflow", DATA * 1e300), "float32"),
    Case("complex voxels", _file("complex", DATA.astype(np.complex64)), "complex"),
    Case("NaN in the affine", _file("nan_affine", DATA, _NAN_AFFINE), "affine"),
    Case("all-zero image", _file("zeros", np.zeros(SHAPE, np.float32)), "constant"),
    Case("constant image", _file("constant", np.full(SHAPE, 7.0, np.float32)), "constant"),
    Case("labels with fractions", _file("fractional", _LABELS + 0.5 * (DATA > 0.8)), "non-integer", label=True),
    Case("negative labels", _file("negative_labels", _LABELS.astype(np.int16) - 1), "[0, 2^31)", label=True),
    Case("labels beyond int32", _file("big_labels", _LABELS * 1e10), "[0, 2^31)", label=True),
    Case("labels with NaN", _file("nan_labels", _with(np.nan, base=_LABELS)), "NaN", label=True),
    Case("more voxels than the limit", _file("over_limit", DATA), "at most 980 voxels", env={MAX_VOXELS_ENV: "980"}),
    Case(
        "header claims 4096^3 voxels",
        _file("huge_header", DATA, edit=lambda p: [set_header_dim(p, k, 4096) for k in (1, 2, 3)][-1], suffix=".nii"),
        "at most 134,217,728 voxels",
    ),
    Case("missing file", lambda folder: (folder / "absent.nii.gz", None, None), "no such file"),
    Case("a folder", _raw("folder.nii.gz", None), "folder"),
]

FAULTS = [c for c in CASES if c.io is not None or c.bundle not in (None, "same")]


def _load(path: Path, label: bool, loader: str) -> tuple[np.ndarray, np.ndarray]:
    """(voxels in file order, RAS affine) through one loading path."""
    if loader == "io":
        volume = (read_label if label else read_image)(path, "--moving")
        return volume.array, LPS_TO_RAS @ volume.index_to_lps
    key = "moving_label" if label else "moving"
    image = LoadCheckedd([key], label_keys=[key] if label else [])({key: str(path)})[key]
    array = np.asarray(image)
    return (array[..., 0] if array.ndim == 4 and array.shape[3] == 1 else array), np.asarray(image.affine)


@pytest.mark.parametrize("loader", ["io", "bundle"])
@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_input(case: Case, loader: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    for key, value in (case.env or {}).items():
        monkeypatch.setenv(key, value)
    path, expected, affine = case.make(tmp_path)
    words = case.io if loader == "io" or case.bundle == "same" else case.bundle
    if words is not None:
        with pytest.raises(InputError) as info:
            _load(path, case.label, loader)
        message = str(info.value)
        assert "\n" not in message and path.name in message and words in message, message
        return
    array, loaded_affine = _load(path, case.label, loader)
    want = np.squeeze(expected, axis=3) if expected.ndim == 4 else expected
    if loader == "io" and not case.label:
        want = want.astype(np.float32)  # the command line reads images as float32, labels as int32
    assert array.shape == want.shape
    # float32 storage, and for scl_slope float32 arithmetic (raw * slope + inter): a few float32 epsilons (1.2e-7)
    # of the largest magnitude; integers come back exactly
    np.testing.assert_allclose(array, want, rtol=2e-7, atol=4e-7 * float(np.abs(want).max()))
    if loader == "io" and case.label:
        assert array.dtype == np.int32
    # NIfTI stores the affine in float32 (sform): 1e-6 relative of its largest entry
    np.testing.assert_allclose(loaded_affine, affine, atol=1e-6 * np.abs(affine).max())


def test_the_catalogue_is_what_the_readme_reports():
    """docs/design.md "Reliability" quotes these numbers; update both together."""
    assert (len(CASES), len(FAULTS)) == (51, 29)


def test_a_huge_header_is_refused_before_reading(tmp_path):
    """4096^3 float64 voxels would be 512 GiB; the refusal comes from the header, so it is immediate."""
    import time

    path = set_header_dim(save(tmp_path / "lie.nii", DATA), 1, 4096)
    for k in (2, 3):
        set_header_dim(path, k, 4096)
    start = time.perf_counter()
    with pytest.raises(InputError, match="68,719,476,736"):
        read_image(path)
    assert time.perf_counter() - start < 5.0  # reading (or allocating) 512 GiB would take far longer or be killed


def test_voxel_limit_from_the_environment_must_be_a_number(monkeypatch, tmp_path):
    monkeypatch.setenv(MAX_VOXELS_ENV, "lots")
    with pytest.raises(InputError, match=f"{MAX_VOXELS_ENV}.*positive integer.*'lots'"):
        read_image(save(tmp_path / "a.nii.gz", DATA))


def test_nibabel_and_itk_agree_on_an_oblique_file(tmp_path):
    """Both paths read the same geometry: the command line (ITK, LPS) and the bundle (nibabel, RAS)."""
    affine = affine_of(rotation((10, 20, 30)), (0.7, 1.1, 3.0), (5, -6, 7))
    path = save(tmp_path / "o.nii.gz", DATA.astype(np.float32), affine)
    np.testing.assert_allclose(LPS_TO_RAS @ read_image(path).index_to_lps, nib.load(path).affine, atol=1e-5)
