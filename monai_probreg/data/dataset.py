"""Dataset discovery: a dataset folder becomes a list of pair dicts.

A dataset folder is laid out like ``lpba40``::

    DIR/atlas/<name>_image.nii.gz   the fixed image (exactly one)
    DIR/atlas/<name>_label.nii.gz   its label map (optional)
    DIR/images/<id>.nii.gz          moving images
    DIR/labels/<id>.nii.gz          their label maps (optional, same <id>)

Every pair is a dict with keys ``moving``, ``fixed`` and, where labels exist, ``moving_label``,
``fixed_label`` (paths), plus ``id``.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monai_probreg.utils.files import file_stem

__all__ = [
    "labelled_pairs",
    "IMAGE_KEYS",
    "LABEL_KEYS",
    "DatasetIndex",
    "index_dataset",
    "split_ids",
    "pair_dicts",
    "atlas_label_values",
]


IMAGE_KEYS = ("moving", "fixed")


LABEL_KEYS = ("moving_label", "fixed_label")


_NII = (".nii.gz", ".nii")


def _niftis(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.name.endswith(_NII)) if folder.is_dir() else []


@dataclass
class DatasetIndex:
    """What a dataset folder holds: the atlas (and its labels) and the subjects with their optional labels."""

    atlas_image: Path
    atlas_label: Path | None
    images: dict[str, Path] = field(default_factory=dict)
    labels: dict[str, Path] = field(default_factory=dict)

    @property
    def ids(self) -> list[str]:
        return sorted(self.images)


def index_dataset(dataset_dir: str | Path, default_atlas: Callable[[], Path] | None = None) -> DatasetIndex:
    """Read the atlas and subject lists from ``dataset_dir`` (nothing hard-coded); clear errors if malformed.

    ``default_atlas``: called for the atlas image when ``dataset_dir`` has no ``atlas/`` folder (e.g.
    :func:`monai_probreg.data.template.mni152_template_path`; no atlas labels then); None: ``atlas/`` is required.
    """
    root = Path(dataset_dir)
    if not root.is_dir():
        raise FileNotFoundError(
            f"dataset_dir {str(root)!r} does not exist or is not a folder "
            "(expected atlas/, images/ and optionally labels/ inside)"
        )
    images = {file_stem(p): p for p in _niftis(root / "images")}
    if not images:
        raise ValueError(f"no NIfTI images found in {root / 'images'}")
    labels = {file_stem(p): p for p in _niftis(root / "labels") if file_stem(p) in images}
    if default_atlas is not None and not (root / "atlas").exists():
        return DatasetIndex(Path(default_atlas()), None, images, labels)
    atlas = [p for p in _niftis(root / "atlas") if file_stem(p).endswith("_image")]
    if len(atlas) != 1:
        raise ValueError(
            f"expected exactly one atlas image {root / 'atlas'}/*_image.nii.gz; found {len(atlas)}: "
            f"{[p.name for p in atlas]}"
        )
    stem = file_stem(atlas[0])
    atlas_label = atlas[0].parent / (stem[: -len("_image")] + "_label" + atlas[0].name[len(stem) :])
    return DatasetIndex(atlas[0], atlas_label if atlas_label.is_file() else None, images, labels)


def split_ids(ids: Sequence[str], num_val: int, seed: int = 0) -> tuple[list[str], list[str]]:
    """Deterministic random split of subject ids into (train, validation)."""
    if not 0 <= num_val < len(ids):
        raise ValueError(f"num_val must be in [0, {len(ids) - 1}] for {len(ids)} subjects; got {num_val}")
    shuffled = sorted(ids)
    random.Random(seed).shuffle(shuffled)
    return sorted(shuffled[num_val:]), sorted(shuffled[:num_val])


def pair_dicts(index: DatasetIndex, ids: Sequence[str] | None = None, require_labels: bool = False) -> list[dict]:
    """One dict per subject registered to the atlas (moving = subject, fixed = atlas)."""
    chosen = index.ids if ids is None else list(ids)
    missing = [i for i in chosen if i not in index.images]
    if missing:
        raise ValueError(f"subjects {missing} are not in the dataset (have {index.ids})")
    pairs = []
    for sid in chosen:
        item: dict = {"id": sid, "moving": str(index.images[sid]), "fixed": str(index.atlas_image)}
        has_labels = sid in index.labels and index.atlas_label is not None
        if require_labels and not has_labels:
            continue
        if has_labels:
            item["moving_label"] = str(index.labels[sid])
            item["fixed_label"] = str(index.atlas_label)
        pairs.append(item)
    return pairs


def atlas_label_values(index: DatasetIndex) -> list[int]:
    """Sorted non-zero label ids of the atlas label map (the structures Dice is computed over)."""
    if index.atlas_label is None:
        raise ValueError(f"the dataset has no atlas label map next to {index.atlas_image}")
    import nibabel as nib

    data = np.asanyarray(nib.load(str(index.atlas_label)).dataobj)
    if not np.array_equal(data, np.round(data)):
        raise ValueError(f"{index.atlas_label} must hold integer labels; got non-integer values")
    return [int(v) for v in np.unique(data) if v != 0]


def labelled_pairs(index: DatasetIndex, ids: Sequence[str] | None = None) -> list[dict]:
    """:func:`~monai_probreg.data.dataset.pair_dicts` of the subjects (``ids``, default all) with labels; a clear error
    when there are none."""
    pairs = pair_dicts(index, ids, require_labels=True)
    if not pairs:
        where = (
            "the atlas has no *_label file" if index.atlas_label is None else "no labels/<id>.nii.gz matches an image"
        )
        raise ValueError(
            f"nothing to evaluate in {str(index.atlas_image.parent.parent)!r}: {where}; "
            "evaluation needs labels (use inference.yaml to register unlabelled images)"
        )
    return pairs
