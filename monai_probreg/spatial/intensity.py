"""The intensity scale every network input is brought to: the ``LOWER_PERCENTILE`` and ``UPPER_PERCENTILE``
percentiles of an image map to 0 and 1, clipped outside (MONAI's ``ScaleIntensityRangePercentiles``), so raw
scanner values of any scale and offset become the same [0, 1] image.

One definition for every path that feeds or imitates the network: the bundle's transform chain
(:func:`monai_probreg.data.transforms.registration_transforms`), training augmentation and label rendering
(:mod:`monai_probreg.data.augmentation`, :mod:`monai_probreg.data.label_synthesis`), the torch affine's metric
(:mod:`monai_probreg.spatial.affine_torch`) and the command line (:func:`normalise_intensity`, used by
:mod:`monai_probreg.registration.affine_stage` on the moving scan resampled onto the fixed grid).
"""

from __future__ import annotations

import numpy as np
import torch
from monai.transforms import ScaleIntensityRangePercentiles

__all__ = ["LOWER_PERCENTILE", "UPPER_PERCENTILE", "normalise_intensity"]

LOWER_PERCENTILE, UPPER_PERCENTILE = 0.5, 99.5  # intensities here map to 0 and 1 (training, bundle and command line)


def normalise_intensity(array: np.ndarray) -> np.ndarray:
    """Percentiles LOWER/UPPER_PERCENTILE -> 0 / 1, clipped (MONAI's ScaleIntensityRangePercentiles, as in training).
    Any array shape; float32 out."""
    scale = ScaleIntensityRangePercentiles(
        lower=LOWER_PERCENTILE, upper=UPPER_PERCENTILE, b_min=0.0, b_max=1.0, clip=True
    )
    return np.asarray(torch.as_tensor(scale(torch.from_numpy(np.asarray(array, np.float32))[None]))[0])
