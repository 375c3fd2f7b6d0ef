"""Shared fixtures: tiny synthetic NIfTI datasets in the bundle's layout (never real data)."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType, SimpleNamespace

import nibabel as nib
import numpy as np
import pytest

from monai_probreg.spatial.affine_settings import AffineSettings

REPO = Path(__file__).resolve().parents[1]
DEFAULT_WEIGHTS = "model.pt"  # the configs' model_file: the shipped default (the model zoo's name)
TINY_LABELS = (21, 22, 181)  # non-contiguous ids, like LPBA40's


def load_script(folder: str, name: str) -> ModuleType:
    """``<folder>/<name>.py`` of the repository (``benchmarks`` or ``experiments``: folders of scripts, not packages)
    imported as a module. The scripts' own plain imports (``from common import ...``, one script from another) resolve
    through pytest's ``pythonpath`` (pyproject.toml), as ``python benchmarks/<name>.py`` resolves them through the
    script's folder and ``PYTHONPATH=benchmarks python experiments/<name>.py`` through the variable."""
    spec = importlib.util.spec_from_file_location(f"{name}_{folder}", REPO / folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _phantom(shape: Sequence[int], shift: Sequence[float], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth 'brain': an ellipsoid split into two halves plus an inner blob, shifted by ``shift`` voxels."""
    grid = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    centre = [n / 2 - 0.5 + s for n, s in zip(shape, shift)]
    radii = [n * 0.32 for n in shape]
    r2 = sum(((g - c) / r) ** 2 for g, c, r in zip(grid, centre, radii))
    labels = np.zeros(shape, dtype=np.uint8)
    inside = r2 < 1.0
    labels[inside & (grid[0] < centre[0])] = TINY_LABELS[0]
    labels[inside & (grid[0] >= centre[0])] = TINY_LABELS[1]
    inner = sum(((g - c) / (0.4 * r)) ** 2 for g, c, r in zip(grid, centre, radii)) < 1.0
    labels[inner] = TINY_LABELS[2]
    image = np.where(inside, 0.5, 0.0) + np.where(inner, 0.4, 0.0) + 0.03 * rng.standard_normal(shape)
    return np.clip(image, 0, None).astype(np.float32), labels


def make_tiny_dataset(
    root: Path, num_subjects: int = 3, shape: Sequence[int] = (32, 32, 32), with_labels: bool = True, seed: int = 0
) -> Path:
    """Write atlas/, images/ and labels/ in the lpba40 layout (affine diag(-1, -1, 1): arrays stored LPS, which
    the RAS reorientation turns; 1 mm) and return ``root``."""
    rng = np.random.default_rng(seed)
    affine = np.diag([-1.0, -1.0, 1.0, 1.0])
    for sub in ("atlas", "images", "labels"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    image, labels = _phantom(shape, (0, 0, 0), rng)
    nib.save(nib.Nifti1Image(image, affine), root / "atlas" / "A01_image.nii.gz")
    nib.save(nib.Nifti1Image(labels, affine), root / "atlas" / "A01_label.nii.gz")
    for i in range(num_subjects):
        shift = rng.uniform(-2.0, 2.0, size=len(shape))
        image, labels = _phantom(shape, shift, rng)
        sid = f"T{i + 1:02d}"
        nib.save(nib.Nifti1Image(image * rng.uniform(50, 500), affine), root / "images" / f"{sid}.nii.gz")
        if with_labels:
            nib.save(nib.Nifti1Image(labels, affine), root / "labels" / f"{sid}.nii.gz")
    return root


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Read-only tiny dataset: 3 labelled subjects of 32^3 (copy it before writing into it)."""
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny_dataset"))


@pytest.fixture
def brain():
    """A smooth positive 'brain' (1, 1, 32, 36, 28) inside a zero background (linear interpolation barely blurs it)."""
    import torch

    x, y, z = torch.meshgrid(*(torch.arange(n, dtype=torch.float32) for n in (32, 36, 28)), indexing="ij")
    image = torch.zeros(1, 1, 32, 36, 28)
    inside = (slice(6, 26), slice(6, 30), slice(5, 23))
    image[0, 0][inside] = (1.5 + torch.sin(x / 3) * torch.cos(y / 4) + 0.5 * torch.sin(z / 5))[inside]
    return image


@pytest.fixture
def single_thread():
    """Run a test with one torch thread (the bundle tests share 2 cores with whatever else runs)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def bundle_with_random_model(root: Path, bundle_dir: Path, network_size: Sequence[int] | None = None) -> Path:
    """Copy ``bundle_dir/configs`` to ``root`` and save a seeded random ProbRegNet state_dict as the one shipped weights
    file, models/model.pt (the configs' default)."""
    import shutil

    import torch

    from monai_probreg import ProbRegNet

    shutil.copytree(bundle_dir / "configs", root / "configs")
    (root / "models").mkdir()
    torch.manual_seed(0)
    torch.save(ProbRegNet(network_size=network_size).state_dict(), root / "models" / DEFAULT_WEIGHTS)
    return root


def run_validation_study(script: ModuleType, tmp_path: Path, dataset: Path, name: str, *args: str) -> dict:
    """Run a validation-subject study (``main`` of a script built on ``uncertainty_calibration.validation_run``) on
    ``dataset`` with a bundle of random weights, which has no calibration sidecar (the warning is expected), and
    return its record ``name.json``."""
    import json

    bundle = bundle_with_random_model(tmp_path / "bundle", REPO / "bundle")
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="no calibration"):
        code = script.main(["--dataset-dir", str(dataset), "--bundle-root", str(bundle), "--out-dir", str(out), *args])
    assert code == 0
    return json.loads((out / f"{name}.json").read_text())


def numpy_mean_dice(dataset: Path, sid: str) -> float:
    """Mean Dice over the atlas' labels between subject ``sid``'s and the atlas' label files (same grid here)."""
    atlas = np.asarray(nib.load(dataset / "atlas" / "A01_label.nii.gz").dataobj)
    subject = np.asarray(nib.load(dataset / "labels" / f"{sid}.nii.gz").dataobj)
    labels = [v for v in np.unique(atlas) if v != 0]
    return float(
        np.mean(
            [2 * np.sum((atlas == v) & (subject == v)) / (np.sum(atlas == v) + np.sum(subject == v)) for v in labels]
        )
    )


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the repository's bundle configs with random weights (network_size 16^3) in models/model.pt."""
    repo_bundle = Path(__file__).resolve().parents[1] / "bundle"
    return bundle_with_random_model(tmp_path_factory.mktemp("bundle"), repo_bundle, network_size=(16, 16, 16))


# ----------------------------------------------------------------------------- physical-space phantoms (CLI tests)
FIXED_LPS = np.diag(
    [-1.0, -1.0, 1.0, 1.0]
)  # index -> LPS of the synthetic atlases: a RAS array (as LPBA40, identity RAS affine), origin 0
PHANTOM_LABELS = (1, 2, 3, 4)


def asymmetric_phantom(shape: Sequence[int] = (40, 44, 36), seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth 'head' with no symmetry (so a rotation is identifiable): an ellipsoid with three distinct radii,
    split in two halves, a bright and a dark off-centre blob. Returns (image float32 in ~[0, 1], labels int16)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    grid = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    centre = [n / 2 - 0.5 for n in shape]

    def ellipsoid(c: Sequence[float], radii: Sequence[float]) -> np.ndarray:
        return sum(((g - m) / r) ** 2 for g, m, r in zip(grid, c, radii)) < 1

    brain = ellipsoid(centre, [0.36 * shape[0], 0.30 * shape[1], 0.26 * shape[2]])
    bright = ellipsoid([centre[0] + 5, centre[1] - 4, centre[2] + 3], [5, 3.5, 4]) & brain
    dark = ellipsoid([centre[0] - 6, centre[1] + 5, centre[2] - 2], [3, 5, 3]) & brain
    labels = np.zeros(shape, np.int16)
    labels[brain] = PHANTOM_LABELS[0]
    labels[brain & (grid[0] > centre[0])] = PHANTOM_LABELS[1]
    labels[bright] = PHANTOM_LABELS[2]
    labels[dark] = PHANTOM_LABELS[3]
    image = ndimage.gaussian_filter(0.5 * brain + 0.4 * bright - 0.3 * dark, 1.0) + 0.01 * rng.standard_normal(shape)
    return image.astype(np.float32), labels


def save_lps(path: Path, array: np.ndarray, index_to_lps: np.ndarray) -> Path:
    """Save ``array`` (index order) as NIfTI with the grid ``index_to_lps`` (ITK's LPS; nibabel wants RAS)."""
    nib.save(nib.Nifti1Image(array, np.diag([-1.0, -1.0, 1.0, 1.0]) @ index_to_lps), path)
    return path


def rigid_matrix(angles_deg: Sequence[float], translation_mm: Sequence[float], centre: Sequence[float]) -> np.ndarray:
    """(4, 4) rotation by ``angles_deg`` (x, y, z Euler, degrees) about ``centre`` then translation, in LPS mm."""
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()
    matrix[:3, 3] = np.asarray(centre) - matrix[:3, :3] @ np.asarray(centre) + np.asarray(translation_mm)
    return matrix


def moved_scan(
    image: np.ndarray,
    labels: np.ndarray,
    fixed_to_moving: np.ndarray,
    spacing: Sequence[float],
    direction: np.ndarray,
    shape: Sequence[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The phantom as another scanner would see it: a grid of ``shape``/``spacing``/``direction`` centred on the
    moved object, with ``moving(q) = image(fixed_to_moving^-1 q)`` (linear; labels nearest).
    Returns (image, labels, index_to_lps of the new grid)."""
    from monai_probreg.spatial.physical import apply_affine, grid_points
    from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
    from monai_probreg.spatial.volume_io import Volume

    fixed = Volume(image, FIXED_LPS)
    centre = grid_points(image.shape, FIXED_LPS).reshape(-1, 3).mean(0)
    index_to_lps = np.eye(4)
    index_to_lps[:3, :3] = np.asarray(direction, dtype=np.float64) * np.asarray(spacing, dtype=np.float64)
    index_to_lps[:3, 3] = apply_affine(fixed_to_moving, centre) - index_to_lps[:3, :3] @ ((np.asarray(shape) - 1) / 2)
    back = apply_affine(np.linalg.inv(fixed_to_moving), grid_points(tuple(shape), index_to_lps))
    moved = sample_linear(fixed, back).astype(np.float32)
    moved_labels = sample_nearest(Volume(labels, FIXED_LPS), back)
    return moved, moved_labels, index_to_lps


SHIPPED_NETWORK_SIZE = (80, 96, 80)  # inference.yaml's network_size (the grid the shipped weights run on)


def tiny_bundle(root: Path, bundle_dir: Path, network_size: Sequence[int] = (16, 16, 16)) -> Path:
    """:func:`bundle_with_random_model` whose inference.yaml runs the UNet at ``network_size`` (fast tests)."""
    bundle_with_random_model(root, bundle_dir)
    config = root / "configs" / "inference.yaml"
    text = config.read_text()
    shipped = f"network_size: {list(SHIPPED_NETWORK_SIZE)}"
    assert shipped in text
    text = text.replace(shipped, f"network_size: {list(network_size)}")
    # the refinement's step is in velocity-grid voxels: on a grid min(network_size) / min(SHIPPED_NETWORK_SIZE) as fine
    # as the shipped one, the shipped step would be that much larger in mm, so it is scaled to stay the shipped step
    step = re.search(r"^refine_learning_rate: ([0-9.]+)", text, re.MULTILINE)
    scaled = float(step.group(1)) * min(network_size) / min(SHIPPED_NETWORK_SIZE)
    config.write_text(text.replace(step.group(0), f"refine_learning_rate: {scaled:.6g}"))
    return root


# ---------------------------------------------------------------------------------------------- the command line
BUNDLE_DIR = Path(__file__).resolve().parents[1] / "bundle"
OBLIQUE_DIRECTION = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # a moved scan's axes (AIL-like)
FAST_AFFINE = ["--affine-levels", "2", "1", "--affine-iterations", "100", "50", "--affine-sampling", "0.25"]
# the same fast affine stage as settings, for tests that call the library (torch backend, the command's default)
FAST_AFFINE_SETTINGS = AffineSettings(
    shrink_factors=(2, 1),
    smoothing_sigmas_mm=(1.0, 0.0),
    rigid_iterations=(100, 50),
    affine_iterations=(100, 50),
    sampling_percentage=0.25,
)


def run_cli(*argv: str, threads: int = 1) -> SimpleNamespace:
    """``monai-probreg`` in-process with ``threads`` threads; returns rc, stdout, stderr (torch's thread count
    restored)."""
    import torch

    from monai_probreg.cli.main import main

    previous = torch.get_num_threads()
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main([*argv, "--threads", str(threads)])
    finally:
        torch.set_num_threads(previous)
    return SimpleNamespace(rc=rc, out=out.getvalue(), err=err.getvalue())


def one_error_line(result: SimpleNamespace, out: Path) -> str:
    """The one ``monai-probreg: error:`` line of a command that had to fail (``run_cli``'s ``result``), checked: exit
    status 1, exactly one such line, and neither the output folder ``out`` nor a staging folder next to it left."""
    assert result.rc == 1, result.err
    lines = [line for line in result.err.splitlines() if line.startswith("monai-probreg: error:")]
    assert len(lines) == 1, result.err
    assert not out.exists() and not [p for p in out.parent.iterdir() if ".partial-" in p.name]
    return lines[0]


def moved_phantom(angles_deg: Sequence[float], translation_mm: Sequence[float]) -> SimpleNamespace:
    """The asymmetric phantom (fixed, on FIXED_LPS) and a scan of it moved by a known rigid transform and resampled
    onto an oblique anisotropic grid: image, labels, truth (fixed -> moving, LPS mm), moved, moved_labels, grid."""
    from monai_probreg.spatial.physical import grid_points

    image, labels = asymmetric_phantom()
    centre = grid_points(image.shape, FIXED_LPS).reshape(-1, 3).mean(0)
    truth = rigid_matrix(angles_deg, translation_mm, centre)
    moved, moved_labels, grid = moved_scan(image, labels, truth, (1.4, 0.9, 1.1), OBLIQUE_DIRECTION, (34, 52, 40))
    return SimpleNamespace(image=image, labels=labels, truth=truth, moved=moved, moved_labels=moved_labels, grid=grid)
