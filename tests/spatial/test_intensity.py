"""monai_probreg.spatial.intensity: one intensity scale for the bundle's transforms and the command line."""

from __future__ import annotations

import inspect

import numpy as np

from monai_probreg.data.transforms import registration_transforms
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE, normalise_intensity


def test_intensity_scaling_ignores_scanner_scale_and_offset():
    raw = np.random.default_rng(0).gamma(2.0, 1.0, (12, 10, 8)).astype(np.float32)
    scaled = normalise_intensity(raw)
    assert scaled.min() == 0.0 and scaled.max() == 1.0
    np.testing.assert_allclose(normalise_intensity(raw * 3000.0 + 50.0), scaled, atol=1e-5)


def test_percentiles_are_the_training_ones():
    # the command line normalises with the very constants the training transforms default to; check the behaviour:
    # those percentiles of a ramp land on 0 and 1, clipped outside
    defaults = inspect.signature(registration_transforms).parameters
    assert (defaults["lower_percentile"].default, defaults["upper_percentile"].default) == (
        LOWER_PERCENTILE,
        UPPER_PERCENTILE,
    )
    ramp = np.arange(1000, dtype=np.float32).reshape(10, 10, 10)
    lo, hi = np.percentile(ramp, [LOWER_PERCENTILE, UPPER_PERCENTILE])
    out = normalise_intensity(ramp)
    np.testing.assert_allclose(out, np.clip((ramp - lo) / (hi - lo), 0, 1), atol=1e-6)  # float32 arithmetic
