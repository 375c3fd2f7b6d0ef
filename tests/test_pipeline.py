"""monai_probreg.pipeline internals: the streamed sample std equals the uncertainty module's, intensity scaling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monai_probreg import ProbRegNet, displacement_uncertainty, sample_velocity
from monai_probreg.io import InputError
from monai_probreg.pipeline import RegistrationOptions, _displacement_std_mm, normalise_intensity


def test_streamed_std_matches_displacement_uncertainty(single_thread):
    """sqrt(sum_k spacing_k^2 var_k) from chunked running sums == displacement_uncertainty on all samples at once
    (same draws); float64 sums of float32 samples: agreement to 1e-5 mm."""
    torch.manual_seed(0)
    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    mean, log_var = 0.5 * torch.randn(1, 3, 5, 6, 4), torch.full((1, 3, 5, 6, 4), -1.0)
    size, spacing, samples, chunk = (10, 12, 8), np.array([1.0, 1.5, 0.8]), 7, 3
    ours = _displacement_std_mm(network, mean, log_var, size, spacing, samples, seed=3, chunk=chunk)
    generator = torch.Generator().manual_seed(3)
    draws = torch.cat([sample_velocity(mean, log_var, min(chunk, samples - s), generator=generator)
                       for s in range(0, samples, chunk)])
    with torch.no_grad():
        displacements = network.velocity_to_displacement(draws.flatten(0, 1), size).unflatten(0, (samples, 1))
    variance = displacement_uncertainty(displacements).variance[0].double()
    expected = (variance * torch.as_tensor(spacing**2).view(3, 1, 1, 1)).sum(0).sqrt().numpy()
    assert ours.shape == size and ours.max() > 0.01
    np.testing.assert_allclose(ours, expected, atol=1e-5)


def test_intensity_scaling_ignores_scanner_scale_and_offset():
    raw = np.random.default_rng(0).gamma(2.0, 1.0, (12, 10, 8)).astype(np.float32)
    scaled = normalise_intensity(raw)
    assert scaled.min() == 0.0 and scaled.max() == 1.0
    np.testing.assert_allclose(normalise_intensity(raw * 3000.0 + 50.0), scaled, atol=1e-5)


@pytest.mark.parametrize("samples", [-1, 1])
def test_samples_must_allow_a_standard_deviation(samples):
    with pytest.raises(InputError, match="--samples"):
        RegistrationOptions(samples=samples)
