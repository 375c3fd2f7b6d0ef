"""monai_probreg.cli.pipeline internals: the streamed sample std equals the uncertainty module's, intensity scaling."""

from __future__ import annotations

import numpy as np
import pytest

from monai_probreg.cli.pipeline import RegistrationOptions, normalise_intensity
from monai_probreg.utils.errors import InputError


def test_intensity_scaling_ignores_scanner_scale_and_offset():
    raw = np.random.default_rng(0).gamma(2.0, 1.0, (12, 10, 8)).astype(np.float32)
    scaled = normalise_intensity(raw)
    assert scaled.min() == 0.0 and scaled.max() == 1.0
    np.testing.assert_allclose(normalise_intensity(raw * 3000.0 + 50.0), scaled, atol=1e-5)


@pytest.mark.parametrize("samples", [-1, 1])
def test_samples_must_allow_a_standard_deviation(samples):
    with pytest.raises(InputError, match="--samples"):
        RegistrationOptions(samples=samples)
