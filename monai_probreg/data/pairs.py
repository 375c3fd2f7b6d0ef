"""Any-pair registration: pairs between subjects, pair lists from a file, and training on random pairs.

VoxelMorph's scan-to-scan mode: the model is trained on ordered (moving, fixed) pairs drawn from the training subjects
*and* the atlas as the fixed image, so one network registers any pair; scan-to-atlas is a case of it.

- :func:`subject_pairs`: every ordered pair among subjects (and, optionally, every subject to the atlas), as the pair
  dicts of :mod:`monai_probreg.data.dataset` (``id`` = ``<moving>_to_<fixed>``).
- :func:`read_pairs_file`: a pair list given by the user, as Learn2Reg's pair lists: a CSV with columns ``moving``,
  ``fixed`` and optional ``moving_label``, ``fixed_label``, ``id``; or JSON, a list of such objects (or Learn2Reg's
  ``{"registration_val": [...]}``). Relative paths are taken from the file's folder.
- :func:`scan_dicts` and :class:`PairDataset`: training caches each scan once (``image``/``label`` keys, preprocessed
  by :func:`~monai_probreg.data.transforms.registration_transforms` with ``image_keys=("image",)``) and
  :class:`PairDataset` makes pair ``k`` from two cached scans on the fly, then applies the random transforms: all
  ordered pairs of 24 subjects would otherwise cache 552 pairs (2 volumes each) instead of 25 scans.
- :func:`mixed_sampler`: draws pairs from several such datasets concatenated (e.g. LPBA40's grid and the template's,
  ``train_template.yaml``) at fixed fractions, whatever their sizes.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset, WeightedRandomSampler

from monai_probreg.data.dataset import IMAGE_KEYS, LABEL_KEYS, DatasetIndex
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import file_stem

__all__ = [
    "ATLAS_ID",
    "SCAN_IMAGE",
    "SCAN_LABEL",
    "PairDataset",
    "mixed_sampler",
    "ordered_pairs",
    "read_pairs_file",
    "scan_dicts",
    "subject_pairs",
]

ATLAS_ID = "atlas"  # the id of the atlas among the scans of scan_dicts
SCAN_IMAGE, SCAN_LABEL = "image", "label"  # keys of one preprocessed scan
_PAIR_COLUMNS = (*IMAGE_KEYS, *LABEL_KEYS)


def _pair(
    moving_id: str,
    moving: Path,
    fixed_id: str,
    fixed: Path,
    moving_label: Path | None,
    fixed_label: Path | None,
    require_labels: bool,
) -> dict | None:
    if require_labels and (moving_label is None or fixed_label is None):
        return None
    item: dict = {"id": f"{moving_id}_to_{fixed_id}", "moving": str(moving), "fixed": str(fixed)}
    if moving_label is not None and fixed_label is not None:
        item["moving_label"], item["fixed_label"] = str(moving_label), str(fixed_label)
    return item


def subject_pairs(
    index: DatasetIndex, ids: Sequence[str] | None = None, include_atlas: bool = True, require_labels: bool = False
) -> list[dict]:
    """Every ordered pair (moving, fixed) of distinct subjects in ``ids`` (default all), then, with
    ``include_atlas``, every subject to the atlas; labels where both sides have them (``require_labels``: only
    those pairs)."""
    chosen = index.ids if ids is None else list(ids)
    missing = [i for i in chosen if i not in index.images]
    if missing:
        raise ValueError(f"subjects {missing} are not in the dataset (have {index.ids})")
    pairs = [
        _pair(m, index.images[m], f, index.images[f], index.labels.get(m), index.labels.get(f), require_labels)
        for m in chosen
        for f in chosen
        if m != f
    ]
    if include_atlas:
        pairs += [
            _pair(
                m, index.images[m], ATLAS_ID, index.atlas_image, index.labels.get(m), index.atlas_label, require_labels
            )
            for m in chosen
        ]
    return [p for p in pairs if p is not None]


def _resolve(value: str, root: Path, source: Path, row: int, column: str) -> str:
    path = Path(value)
    path = path if path.is_absolute() else root / path
    if not path.is_file():
        raise InputError(f"pairs file {str(source)!r}, pair {row}: {column} {str(path)!r} does not exist")
    return str(path)


def read_pairs_file(path: str | os.PathLike, require_labels: bool = False) -> list[dict]:
    """Pair dicts from a CSV or JSON pair list (module docstring); every file must exist. ``id`` defaults to
    ``<moving stem>_to_<fixed stem>``. ``InputError`` naming the file and the pair for anything unusable."""
    source = Path(path)
    if not source.is_file():
        raise InputError(f"pairs file {str(source)!r} does not exist")
    try:
        if source.suffix.lower() == ".json":
            records = json.loads(source.read_text())
            if isinstance(records, Mapping):
                lists = [v for v in records.values() if isinstance(v, list)]
                records = [r for lst in lists for r in lst]
        else:
            with source.open(newline="") as f:
                records = list(csv.DictReader(f))
    except (OSError, ValueError) as err:
        raise InputError(f"pairs file {str(source)!r}: expected CSV or JSON, could not parse it ({err})") from None
    if not isinstance(records, list) or not records:
        raise InputError(f"pairs file {str(source)!r}: expected a non-empty list of pairs, got none")
    pairs, seen = [], set()
    for row, record in enumerate(records, start=1):
        if not isinstance(record, Mapping) or not record.get("moving") or not record.get("fixed"):
            raise InputError(
                f"pairs file {str(source)!r}, pair {row}: expected 'moving' and 'fixed', got "
                f"{dict(record) if isinstance(record, Mapping) else record!r}"
            )
        item = {k: _resolve(str(record[k]), source.parent, source, row, k) for k in _PAIR_COLUMNS if record.get(k)}
        if ("moving_label" in item) != ("fixed_label" in item):
            raise InputError(f"pairs file {str(source)!r}, pair {row}: expected both label maps or neither")
        if require_labels and "moving_label" not in item:
            raise InputError(f"pairs file {str(source)!r}, pair {row}: evaluation needs moving_label and fixed_label")
        item["id"] = str(record.get("id") or f"{file_stem(item['moving'])}_to_{file_stem(item['fixed'])}")
        if item["id"] in seen:
            raise InputError(f"pairs file {str(source)!r}, pair {row}: id {item['id']!r} is used twice")
        seen.add(item["id"])
        pairs.append(item)
    return pairs


def scan_dicts(
    index: DatasetIndex, ids: Sequence[str], include_atlas: bool = True, require_labels: bool = False
) -> list[dict]:
    """One dict per scan (``id``, ``image``, ``label`` where present): the subjects ``ids``, then the atlas."""
    scans = []
    for sid in ids:
        if sid not in index.images:
            raise ValueError(f"subject {sid!r} is not in the dataset (have {index.ids})")
        scans.append((sid, index.images[sid], index.labels.get(sid)))
    if include_atlas:
        scans.append((ATLAS_ID, index.atlas_image, index.atlas_label))
    out = []
    for sid, image, label in scans:
        if require_labels and label is None:
            raise ValueError(f"scan {sid!r} has no label map; label-supervised training needs one for every scan")
        item = {"id": sid, SCAN_IMAGE: str(image)}
        if label is not None:
            item[SCAN_LABEL] = str(label)
        out.append(item)
    return out


def ordered_pairs(
    scan_ids: Sequence[str], atlas_repeats: int = 1, atlas_as_moving: bool = False, self_repeats: int = 0
) -> list[tuple[int, int]]:
    """Index pairs (moving, fixed) into ``scan_ids``: every ordered pair of distinct subjects, and every subject to
    the atlas (id :data:`ATLAS_ID`) ``atlas_repeats`` times (its weight among the pairs; 0 = none); the atlas is
    never moving unless ``atlas_as_moving``.

    ``self_repeats``: every scan (the atlas too) also paired with itself this many times (0 = none). A self pair has
    one anatomy on both sides, so its answer is known: the identity, or the inverse of the random deformation the
    moving augmentation draws for it (:func:`~monai_probreg.data.augmentation.moving_augmentation`). Between two
    subjects no warp matches the images exactly; these pairs teach the network to return nothing where there is
    nothing to register and to recover a deformation in full where there is one (``monai-probreg demo`` measures
    both)."""
    if atlas_repeats < 0 or self_repeats < 0:
        raise ValueError(f"atlas_repeats and self_repeats must be >= 0; got {atlas_repeats} and {self_repeats}")
    ids = list(scan_ids)
    atlas = ids.index(ATLAS_ID) if ATLAS_ID in ids else None
    subjects = [i for i in range(len(ids)) if i != atlas]
    pairs = [(m, f) for m in subjects for f in subjects if m != f]
    if atlas is not None:
        pairs += [(m, atlas) for m in subjects] * atlas_repeats
        if atlas_as_moving:
            pairs += [(atlas, f) for f in subjects]
    pairs += [(i, i) for i in range(len(ids))] * self_repeats
    if not pairs:
        raise ValueError(f"no pair can be made of the scans {ids}")
    return pairs


class PairDataset(Dataset):
    """Pair ``k`` = ``scans[pairs[k][0]]`` as moving and ``scans[pairs[k][1]]`` as fixed (keys ``image``/``label``
    renamed to ``moving``/``fixed``/``moving_label``/``fixed_label``), then ``transform`` (the random augmentation).

    Args:
        scans: indexable preprocessed scans (e.g. a ``CacheDataset`` over :func:`scan_dicts`).
        pairs: (moving, fixed) indices into ``scans`` (:func:`ordered_pairs`).
        transform: applied to each pair dict (None: none).
        space: a name for the scans' space, prefixed to the pair ids (``<space>:<moving>_to_<fixed>``) when several
            spaces are trained together (``train_template.yaml``); "" = none.
    """

    def __init__(
        self,
        scans: Sequence[Mapping[str, Any]],
        pairs: Sequence[tuple[int, int]],
        transform: Callable[[dict], dict] | None = None,
        space: str = "",
    ) -> None:
        bad = [p for p in pairs if not (0 <= p[0] < len(scans) and 0 <= p[1] < len(scans))]
        if bad:
            raise ValueError(f"pairs must index scans 0..{len(scans) - 1}; got {bad[:3]}")
        self.scans, self.pairs, self.transform = scans, list(pairs), transform
        self.prefix = f"{space}:" if space else ""

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, k: int) -> dict:
        moving, fixed = (self.scans[i] for i in self.pairs[k])
        item = {
            "id": f"{self.prefix}{moving['id']}_to_{fixed['id']}",
            IMAGE_KEYS[0]: moving[SCAN_IMAGE],
            IMAGE_KEYS[1]: fixed[SCAN_IMAGE],
        }
        if SCAN_LABEL in moving and SCAN_LABEL in fixed:
            item[LABEL_KEYS[0]], item[LABEL_KEYS[1]] = moving[SCAN_LABEL], fixed[SCAN_LABEL]
        return self.transform(item) if self.transform is not None else item


def mixed_sampler(
    sizes: Sequence[int], fractions: Sequence[float], num_samples: int, generator: torch.Generator | None = None
) -> WeightedRandomSampler:
    """Sampler over datasets concatenated in this order (``torch.utils.data.ConcatDataset`` of datasets of ``sizes``
    items) that draws each one's items with probability proportional to its ``fractions`` entry, uniformly inside
    it (with replacement): e.g. half the pairs in LPBA40's space and half in a template's, whatever their sizes."""
    if len(sizes) != len(fractions) or not sizes:
        raise ValueError(f"expected one fraction per dataset; got {len(sizes)} sizes and {len(fractions)} fractions")
    if any(n < 1 for n in sizes) or any(f < 0 for f in fractions) or sum(fractions) <= 0:
        raise ValueError(
            f"expected sizes >= 1 and fractions >= 0 with a positive sum; got {list(sizes)} and {list(fractions)}"
        )
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1; got {num_samples}")
    weights = torch.cat(
        [torch.full((int(n),), float(f) / int(n), dtype=torch.float64) for n, f in zip(sizes, fractions)]
    )
    return WeightedRandomSampler(weights, num_samples, replacement=True, generator=generator)
