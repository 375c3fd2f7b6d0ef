"""Shared fixtures: tiny synthetic NIfTI datasets in the bundle's layout (never real data)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

TINY_LABELS = (21, 22, 181)  # non-contiguous ids, like LPBA40's


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


def make_tiny_dataset(root: Path, num_subjects: int = 3, shape: Sequence[int] = (32, 32, 32),
                      with_labels: bool = True, seed: int = 0) -> Path:
    """Write atlas/, images/ and labels/ like lpba40 (affine diag(-1, -1, 1), 1 mm) and return ``root``."""
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
def single_thread():
    """Run a test with one torch thread (the bundle tests share 2 cores with whatever else runs)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def bundle_with_random_model(root: Path, bundle_dir: Path, network_size: Sequence[int] | None = None) -> Path:
    """Copy ``bundle_dir/configs`` to ``root`` and save a seeded random ProbRegNet state_dict as models/model.pt."""
    import shutil

    import torch

    from monai_probreg import ProbRegNet

    shutil.copytree(bundle_dir / "configs", root / "configs")
    (root / "models").mkdir()
    torch.manual_seed(0)
    torch.save(ProbRegNet(network_size=network_size).state_dict(), root / "models" / "model.pt")
    return root


def numpy_mean_dice(dataset: Path, sid: str) -> float:
    """Mean Dice over the atlas' labels between subject ``sid``'s and the atlas' label files (same grid here)."""
    atlas = np.asarray(nib.load(dataset / "atlas" / "A01_label.nii.gz").dataobj)
    subject = np.asarray(nib.load(dataset / "labels" / f"{sid}.nii.gz").dataobj)
    labels = [v for v in np.unique(atlas) if v != 0]
    return float(np.mean([2 * np.sum((atlas == v) & (subject == v)) / (np.sum(atlas == v) + np.sum(subject == v))
                          for v in labels]))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the repository's bundle configs with random weights (network_size 16^3) in models/model.pt."""
    repo_bundle = Path(__file__).resolve().parents[1] / "bundle"
    return bundle_with_random_model(tmp_path_factory.mktemp("bundle"), repo_bundle, network_size=(16, 16, 16))
