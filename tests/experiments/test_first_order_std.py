"""experiments/first_order_std.py: the variance of interpolated independent noise against the explicit interpolation
weights, the samples' variance converging to it for a small spread at the identity, the shipped map left alone, the
skip without a dataset."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import load_script

from monai_probreg.blocks.integration import resize_displacement

study = load_script("experiments", "first_order_std")


def test_independent_noise_variance_is_the_sum_of_squared_interpolation_weights():
    torch.manual_seed(0)
    grid, size = (2, 3, 2), (3, 5, 4)
    variance = torch.rand(1, 3, *grid) + 0.1
    ours = study.independent_noise_variance(variance, size)
    # brute force: each velocity voxel's unit impulse resized; its squared weights times that voxel's variance
    expected = torch.zeros(1, 3, *size, dtype=torch.float64)
    for index in range(math.prod(grid)):
        impulse = torch.zeros(1, 3, math.prod(grid), dtype=torch.float64)
        impulse[..., index] = 1.0
        weights = resize_displacement(impulse.view(1, 3, *grid), list(size))  # scaled per component, as a field is
        expected += weights.square() * variance.double().flatten(2)[..., index].view(1, 3, 1, 1, 1)
    torch.testing.assert_close(ours.double(), expected, rtol=1e-5, atol=0)


def test_a_small_spread_samples_to_the_independent_noise_variance():
    from monai_probreg import ProbRegNet

    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    grid, size = (5, 5, 5), (9, 9, 9)
    log_var = torch.full((1, 3, *grid), 2 * math.log(1e-3))
    with torch.inference_mode():
        sampled = study.sampled_variance(network, torch.zeros(1, 3, *grid), log_var, size, 400, 1.0, 0)
    expected = study.independent_noise_variance(log_var.exp(), size)
    assert float((sampled / expected).mean()) == pytest.approx(1.0, abs=0.03)


def test_the_first_order_variant_is_the_shipped_map(monkeypatch):
    calls = []
    monkeypatch.setattr(study.registration_network, "posterior_maps", lambda *a, **k: calls.append(a) or "shipped")
    assert study.variant_maps("first order", 1.0)(None, None, None, (2, 2, 2)) == "shipped" and calls


def test_the_study_skips_without_a_dataset(tmp_path, capsys):
    assert study.main(["--dataset-dir", str(tmp_path / "none"), "--out-dir", str(tmp_path)]) == 0
    assert "skipped" in capsys.readouterr().out
