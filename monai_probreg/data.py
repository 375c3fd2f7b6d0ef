"""Dataset discovery and MONAI transform chains for scan-to-atlas registration.

A dataset folder is laid out like ``lpba40``::

    DIR/atlas/<name>_image.nii.gz   the fixed image (exactly one)
    DIR/atlas/<name>_label.nii.gz   its label map (optional)
    DIR/images/<id>.nii.gz          moving images
    DIR/labels/<id>.nii.gz          their label maps (optional, same <id>)

Every pair is a dict with keys ``moving``, ``fixed`` and, where labels exist, ``moving_label``,
``fixed_label`` (paths), plus ``id``. Transforms load NIfTI with MONAI (nibabel), put channels first,
reorient to RAS, normalise intensities to [0, 1] by percentiles (robust to raw scanner values), pad to a
multiple of ``divisor`` and, for a reduced-resolution model, resize to ``network_size`` with the same
align-corners linear resampling the model uses (``monai_probreg.blocks.integration.resize_displacement``).
Geometry (affine, original shape) stays in the MetaTensor metadata so outputs can be written back.
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from monai.transforms import (
    Compose,
    MapTransform,
    DivisiblePadd,
    EnsureChannelFirstd,
    EnsureTyped,
    LoadImage,
    Orientationd,
    Resized,
    ScaleIntensityRangePercentilesd,
)

from monai_probreg.validation import (InputError, check_image_values, check_label_values, check_nifti_header,
                                      check_size, corrupt_file_error, is_nifti)

__all__ = ["DatasetIndex", "LoadCheckedd", "NearestResizeAlignCornersd", "index_dataset", "pair_dicts", "split_ids",
           "registration_transforms", "atlas_label_values", "IMAGE_KEYS", "LABEL_KEYS", "LOWER_PERCENTILE", "UPPER_PERCENTILE"]

IMAGE_KEYS = ("moving", "fixed")
LOWER_PERCENTILE, UPPER_PERCENTILE = 0.5, 99.5  # intensities here map to 0 and 1 (training, bundle and command line)
LABEL_KEYS = ("moving_label", "fixed_label")
_NII = (".nii.gz", ".nii")


def _stem(path: Path) -> str:
    for ext in _NII:
        if path.name.endswith(ext):
            return path.name[: -len(ext)]
    return path.stem


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


def index_dataset(dataset_dir: str | Path) -> DatasetIndex:
    """Read the atlas and subject lists from ``dataset_dir`` (nothing hard-coded); clear errors if malformed."""
    root = Path(dataset_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset_dir {str(root)!r} does not exist or is not a folder "
                                "(expected atlas/, images/ and optionally labels/ inside)")
    atlas = [p for p in _niftis(root / "atlas") if _stem(p).endswith("_image")]
    if len(atlas) != 1:
        raise ValueError(f"expected exactly one atlas image {root / 'atlas'}/*_image.nii.gz; found {len(atlas)}: "
                         f"{[p.name for p in atlas]}")
    atlas_label = atlas[0].parent / (_stem(atlas[0])[: -len("_image")] + "_label" + atlas[0].name[len(_stem(atlas[0])):])
    images = {_stem(p): p for p in _niftis(root / "images")}
    if not images:
        raise ValueError(f"no NIfTI images found in {root / 'images'}")
    labels = {_stem(p): p for p in _niftis(root / "labels") if _stem(p) in images}
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


class LoadCheckedd(MapTransform):
    """MONAI's ``LoadImage(image_only=True)`` per key, inside the package's input checks
    (:mod:`monai_probreg.validation`, the same as the command line's): header first (size, voxel limit, voxel type,
    affine, byte count; nothing read yet), then the load (a truncated or corrupt file becomes one line), then the
    values (finite; images not constant; ``label_keys`` integer labels). Any problem is an :class:`InputError`
    naming the key and the file, so one damaged scan in a dataset is reported as such, not as a traceback."""

    def __init__(self, keys: Sequence[str], label_keys: Sequence[str] = (), allow_missing_keys: bool = False) -> None:
        super().__init__(keys, allow_missing_keys)
        self.label_keys = set(label_keys)
        self.loader = LoadImage(image_only=True)

    def __call__(self, data: dict) -> dict:
        d = dict(data)
        for key in self.key_iterator(d):
            path = str(d[key])
            role = key.replace("_", " ") + ("" if key in self.label_keys else " image")
            if not Path(path).is_file():
                what = "a folder" if Path(path).is_dir() else "no such file"
                raise InputError(f"{role} {path!r}: expected an image file, got {what}")
            if is_nifti(path):
                check_nifti_header(path, role)
            try:
                image = self.loader(path)
            except Exception as err:  # noqa: BLE001 - whatever the reader raises, the file is unusable
                raise corrupt_file_error(path, role, err) from None
            check_size(image.shape, path, role)
            values = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
            (check_label_values if key in self.label_keys else check_image_values)(values, path, role)
            d[key] = image
        return d


class NearestResizeAlignCornersd(MapTransform):
    """Nearest-neighbour resize of label maps with align-corners geometry, matching the images' linear resize.

    MONAI's ``Resized(mode="nearest")`` maps output voxel i to input floor(i * n / m) (half-open geometry), up to
    one input voxel away from where the align-corners image resize samples; the label term of semi-supervised
    training would then compare slightly shifted maps. We sample at exactly the align-corners positions.
    """

    def __init__(self, keys: Sequence[str], spatial_size: Sequence[int]) -> None:
        super().__init__(keys)
        self.spatial_size = tuple(int(n) for n in spatial_size)

    def __call__(self, data: dict) -> dict:
        d = dict(data)
        for key in self.key_iterator(d):
            labels = d[key]
            ndims = labels.ndim - 1
            theta = torch.eye(ndims, ndims + 1, dtype=torch.float32).unsqueeze(0)
            grid = F.affine_grid(theta, [1, 1, *self.spatial_size], align_corners=True)
            src = torch.as_tensor(labels, dtype=torch.float32).unsqueeze(0)
            resized = F.grid_sample(src, grid, mode="nearest", align_corners=True)[0]
            d[key] = resized.to(torch.as_tensor(labels).dtype)
        return d


def registration_transforms(
    with_labels: bool = True,
    divisor: int = 16,
    network_size: Sequence[int] | None = None,
    resize_labels: bool = False,
    lower_percentile: float = LOWER_PERCENTILE,
    upper_percentile: float = UPPER_PERCENTILE,
    axcodes: str = "RAS",
) -> Compose:
    """Load -> channel first -> RAS -> percentile intensity scaling to [0, 1] -> pad to ``divisor``.

    Args:
        with_labels: also load ``moving_label``/``fixed_label`` (nearest-neighbour handling throughout).
        divisor: pad every spatial axis to a multiple of this (2**network depth).
        network_size: if given, images are resized (linear, align corners) to this size after padding.
        resize_labels: resize the label maps too (nearest); by default they stay on the full grid for evaluation.
        lower_percentile, upper_percentile: intensities at these percentiles map to 0 and 1 (clipped).
        axcodes: orientation every image is brought to.
    """
    keys = list(IMAGE_KEYS) + (list(LABEL_KEYS) if with_labels else [])
    labels = list(LABEL_KEYS) if with_labels else []
    chain = [
        LoadCheckedd(keys=keys, label_keys=labels),
        EnsureChannelFirstd(keys=keys),
        Orientationd(keys=keys, axcodes=axcodes, labels=(("L", "R"), ("P", "A"), ("I", "S"))),
        ScaleIntensityRangePercentilesd(keys=list(IMAGE_KEYS), lower=lower_percentile, upper=upper_percentile,
                                        b_min=0.0, b_max=1.0, clip=True),
        DivisiblePadd(keys=keys, k=divisor),
    ]
    if network_size is not None:
        chain.append(Resized(keys=list(IMAGE_KEYS), spatial_size=tuple(network_size), mode="trilinear",
                             align_corners=True, anti_aliasing=False))
        if resize_labels and labels:
            chain.append(NearestResizeAlignCornersd(keys=labels, spatial_size=network_size))
    chain.append(EnsureTyped(keys=list(IMAGE_KEYS), dtype=torch.float32))
    if labels:
        chain.append(EnsureTyped(keys=labels, dtype=torch.int16))
    return Compose(chain)


def atlas_label_values(index: DatasetIndex) -> list[int]:
    """Sorted non-zero label ids of the atlas label map (the structures Dice is computed over)."""
    if index.atlas_label is None:
        raise ValueError(f"the dataset has no atlas label map next to {index.atlas_image}")
    import nibabel as nib
    import numpy as np

    data = np.asanyarray(nib.load(str(index.atlas_label)).dataobj)
    if not np.array_equal(data, np.round(data)):
        raise ValueError(f"{index.atlas_label} must hold integer labels; got non-integer values")
    return [int(v) for v in np.unique(data) if v != 0]
