"""The MONAI transform chain of registration: load (checked), channel first, RAS, intensity, pad, resize.

Transforms load NIfTI with MONAI (nibabel), put channels first,
reorient to RAS, normalise intensities to [0, 1] by percentiles (robust to raw scanner values; the
bounds of :mod:`monai_probreg.spatial.intensity`), pad to a
multiple of ``divisor`` and, for a reduced-resolution model, resize to ``network_size`` with the same
align-corners linear resampling the model uses (``monai_probreg.blocks.integration.resize_displacement``).
Geometry (affine, original shape) stays in the MetaTensor metadata so outputs can be written back.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from monai.transforms import (
    Compose,
    DivisiblePadd,
    EnsureChannelFirstd,
    EnsureTyped,
    LoadImage,
    MapTransform,
    Orientationd,
    Resized,
    ScaleIntensityRangePercentilesd,
)

from monai_probreg.data.dataset import IMAGE_KEYS, LABEL_KEYS
from monai_probreg.spatial.checks import (
    check_image_values,
    check_label_values,
    check_nifti_header,
    check_size,
    corrupt_file_error,
    is_nifti,
)
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE
from monai_probreg.utils.errors import InputError

__all__ = ["LoadCheckedd", "NearestResizeAlignCornersd", "registration_transforms"]


class LoadCheckedd(MapTransform):
    """MONAI's ``LoadImage(image_only=True)`` per key, inside the package's input checks
    (:mod:`monai_probreg.spatial.checks`, the same as the command line's): header first (size, voxel limit, voxel type,
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
    image_keys: Sequence[str] = IMAGE_KEYS,
    label_keys: Sequence[str] = LABEL_KEYS,
) -> Compose:
    """Load -> channel first -> RAS -> percentile intensity scaling to [0, 1] -> pad to ``divisor``.

    Args:
        with_labels: also load ``moving_label``/``fixed_label`` (nearest-neighbour handling throughout).
        divisor: pad every spatial axis to a multiple of this (2**network depth).
        network_size: if given, images are resized (linear, align corners) to this size after padding.
        resize_labels: resize the label maps too (nearest); by default they stay on the full grid for evaluation.
        lower_percentile, upper_percentile: intensities at these percentiles map to 0 and 1 (clipped).
        axcodes: orientation every image is brought to.
        image_keys, label_keys: the keys of the images and label maps (default: a pair; ``("image",)`` and
            ``("label",)`` for one scan, as :mod:`monai_probreg.data.pairs` caches them).
    """
    images = list(image_keys)
    labels = list(label_keys) if with_labels else []
    keys = images + labels
    chain = [
        LoadCheckedd(keys=keys, label_keys=labels),
        EnsureChannelFirstd(keys=keys),
        Orientationd(keys=keys, axcodes=axcodes, labels=(("L", "R"), ("P", "A"), ("I", "S"))),
        ScaleIntensityRangePercentilesd(
            keys=images, lower=lower_percentile, upper=upper_percentile, b_min=0.0, b_max=1.0, clip=True
        ),
        DivisiblePadd(keys=keys, k=divisor),
    ]
    if network_size is not None:
        chain.append(
            Resized(
                keys=images, spatial_size=tuple(network_size), mode="trilinear", align_corners=True, anti_aliasing=False
            )
        )
        if resize_labels and labels:
            chain.append(NearestResizeAlignCornersd(keys=labels, spatial_size=network_size))
    chain.append(EnsureTyped(keys=images, dtype=torch.float32))
    if labels:
        chain.append(EnsureTyped(keys=labels, dtype=torch.int16))
    return Compose(chain)
