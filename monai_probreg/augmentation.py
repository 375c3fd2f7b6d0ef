"""Training-time spatial augmentation of the moving scan (MONAI ``RandAffined``), scan-to-atlas.

Only the moving side is augmented: the fixed image is the atlas, the one space every output lives in, so moving it
would change the task. The moving image and its label map get the *same* random affine (MONAI draws it once per
call for all keys): the image resampled linearly, the labels by nearest neighbour, so no label value is invented.
The transform runs after the cached deterministic chain (``CacheDataset`` caches up to the first random
transform), on the network grid, so an epoch pays only for one small resampling per subject.

Why: the shipped models are trained on 24 subjects; the semi-supervised Dice term fits them noticeably better than
unseen subjects. Small random poses (a few degrees, a few per cent of scale, a few voxels of shift) give the network
more moving anatomy to match without changing what it has to learn. The ranges are the bundle's
``augment_*`` settings; ``augment_prob`` 0 (the default) turns augmentation off.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from monai.transforms import Compose, EnsureTyped, RandAffined

from monai_probreg.data import IMAGE_KEYS, LABEL_KEYS

__all__ = ["moving_augmentation"]

_MOVING_IMAGE = IMAGE_KEYS[0]
_MOVING_LABEL = LABEL_KEYS[0]


_MAX_AXES = 3  # rotation and shift parameters MONAI reads per axis; a 2-d grid uses the first one (rotation) or two


def _non_negative(name: str, values: float | Sequence[float]) -> tuple[float, ...]:
    # one number applies to every axis: MONAI would otherwise randomise only the first one
    seq = (values,) * _MAX_AXES if isinstance(values, (int, float)) else tuple(values)
    out = tuple(float(v) for v in seq)
    if not out or any(v < 0 for v in out):
        raise ValueError(f"{name} must be one or more non-negative numbers, got {values!r}")
    return out


def moving_augmentation(
    prob: float = 0.0,
    rotate_range: float | Sequence[float] = 0.0,
    scale_range: float | Sequence[float] = 0.0,
    translate_range: float | Sequence[float] = 0.0,
    with_labels: bool = False,
    seed: int | None = None,
) -> Compose:
    """Random affine of the moving image (and its label map) about the grid centre.

    Args:
        prob: probability that a pair is augmented (0 = identity, 1 = always).
        rotate_range: maximum rotation in radians, per axis (one value for all, or one per rotation axis);
            each angle is drawn uniformly in ``[-r, r]``.
        scale_range: maximum relative scaling per axis; the factor is ``1 + U(-s, s)``.
        translate_range: maximum shift in voxels of the grid the transform sees (the network grid in training).
        with_labels: also transform ``moving_label`` (nearest neighbour; its integer dtype is restored).
        seed: seed of the transform's own random state (``None``: set by MONAI's ``set_determinism``).

    Shapes: ``moving`` (C, *S) and ``moving_label`` (1, *S) keep their shape; out-of-field voxels become 0.

    Raises:
        ValueError: ``prob`` outside [0, 1], or a negative range.
    """
    if not 0.0 <= float(prob) <= 1.0:
        raise ValueError(f"prob must be in [0, 1], got {prob!r}")
    rotate = _non_negative("rotate_range", rotate_range)
    scale = _non_negative("scale_range", scale_range)
    translate = _non_negative("translate_range", translate_range)
    keys = [_MOVING_IMAGE] + ([_MOVING_LABEL] if with_labels else [])
    modes = ["bilinear"] + (["nearest"] if with_labels else [])
    affine = RandAffined(keys=keys, prob=float(prob), rotate_range=rotate, scale_range=scale,
                         translate_range=translate, mode=modes, padding_mode="zeros", cache_grid=False)
    chain: list = [affine, EnsureTyped(keys=[_MOVING_IMAGE], dtype=torch.float32, track_meta=True)]
    if with_labels:
        chain.append(EnsureTyped(keys=[_MOVING_LABEL], dtype=torch.int16, track_meta=True))
    augmentation = Compose(chain)
    if seed is not None:  # after Compose: its constructor re-seeds the transforms it holds
        augmentation.set_random_state(seed=seed)
    return augmentation
