"""monai_probreg.fitting.population_probe: the random deformation has the asked RMS and its stated inverse, the
population model is the training velocities' mean and deviations, the posterior is the default path's; a case's
errors are its first-order std map and the answer's error, its samples spread less, as much more as the gain asks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_probreg.blocks.warp import compose_displacements, warp_image
from monai_probreg.fitting import population_probe as probe
from monai_probreg.utils.errors import InputError


def test_random_deformation_has_the_asked_rms_and_inverse(brain):
    forward, inverse = probe.random_deformation(brain, 1.5, torch.Generator().manual_seed(1))
    inside = brain[0, 0] > 0
    rms = forward[0][:, inside].pow(2).sum(0).mean().sqrt()
    assert rms.item() == pytest.approx(1.5, rel=0.05)
    # exp(v) o exp(-v) = id: the truth the benchmark scores against is the inverse of what deformed the image
    residual = compose_displacements(forward, inverse)[0][:, inside].abs().max()
    assert residual < 0.05
    # moving = fixed o exp(v); pulling moving back by exp(-v) restores fixed (up to interpolation blur)
    restored = warp_image(warp_image(brain, forward), inverse)
    assert (restored - brain)[0, 0][inside].abs().mean() < 0.1 * brain[0, 0][inside].mean()


class _ConstantPosterior(torch.nn.Module):
    """posterior(moving, fixed).mean = the moving image's mean intensity, constant on a (3, 4, 5, 3) velocity grid."""

    def posterior(self, moving, fixed):
        return type("Posterior", (), {"mean": moving.mean() * torch.ones((1, 3, 4, 5, 3))})()


def test_population_velocities_are_the_mean_and_the_deviations_from_it():
    items = [
        {"moving": torch.full((1, 8, 8, 8), value), "fixed": torch.zeros((1, 8, 8, 8)), "id": f"T{value}"}
        for value in (1.0, 2.0, 6.0)
    ]
    mean, deviations = probe.population_velocities(_ConstantPosterior(), items)
    assert mean.shape == (3, 4, 5, 3) and deviations.shape == (3, 3, 4, 5, 3)
    assert torch.allclose(mean, torch.full_like(mean, 3.0))
    assert torch.allclose(deviations[:, 0, 0, 0, 0], torch.tensor([-2.0, -1.0, 3.0]))


def test_population_velocities_need_two_subjects():
    with pytest.raises(InputError, match=">= 2 training subjects"):
        probe.population_velocities(
            _ConstantPosterior(), [{"moving": torch.ones((1, 8, 8, 8)), "fixed": torch.ones((1, 8, 8, 8))}]
        )


def test_population_deformation_is_the_drawn_subject_to_atlas_field_and_its_inverse(brain):
    """Deviations (d, -d): the draw is -v = (w0 - w1) d with w = randn(2) of the same generator; the truth is
    exp(-v) integrated at full resolution, the forward field its inverse."""
    velocity_grid = tuple(n // 2 for n in brain.shape[2:])
    d = torch.zeros((3, *velocity_grid))
    x = torch.linspace(0, math.pi, velocity_grid[0])[:, None, None]
    d[0] = 0.8 * torch.sin(x).expand(velocity_grid)  # a smooth bump along axis 0, velocity-grid voxels
    draw = probe.population_velocity((torch.zeros_like(d), torch.stack([d, -d])), torch.Generator().manual_seed(3))
    forward, truth = probe.population_deformation(brain, draw)
    w = torch.randn(2, generator=torch.Generator().manual_seed(3))
    expected = probe.ScalingAndSquaring(num_steps=probe.TRUTH_STEPS)(
        probe.resize_displacement(((w[0] - w[1]) * d)[None], brain.shape[2:])
    )
    assert torch.allclose(truth, expected, atol=1e-5)
    inside = brain[0, 0] > 0
    assert compose_displacements(forward, truth)[0][:, inside].abs().max() < 0.05


def test_the_posterior_of_the_default_path_has_the_refined_mean_and_the_networks_variance(brain):
    from monai_probreg import ProbRegNet
    from monai_probreg.engines.refinement import RefinementSettings

    torch.manual_seed(0)
    network = ProbRegNet(network_size=(16, 16, 16)).eval()
    moving = warp_image(brain, torch.full((1, 3, *brain.shape[2:]), 1.5))  # the brain shifted: something to refine
    with torch.inference_mode():
        plain = network.posterior(moving, brain)
    same = probe.posterior_for(network, moving, brain, RefinementSettings(num_iterations=0))
    assert torch.equal(same.mean, plain.mean) and torch.equal(same.log_var, plain.log_var)
    refined = probe.posterior_for(network, moving, brain, RefinementSettings(num_iterations=3))
    assert torch.equal(refined.log_var, plain.log_var)  # the refinement moves the mean only
    assert (refined.mean - plain.mean).abs().max() > 1e-4


def _case(mean_shift: float = 0.0, sigma: float = 0.05) -> dict:
    """A population-probe case made by hand: the posterior N(mean, sigma^2) on an 8^3 velocity grid for a 15^3 image,
    a truth 0.25 voxel off the answer along axis 0, every image voxel scored."""
    from monai_probreg import ProbRegNet

    torch.manual_seed(0)
    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    size, grid = (15, 15, 15), (8, 8, 8)
    mean = torch.zeros(1, 3, *grid)
    mean[:, 0] = mean_shift
    with torch.inference_mode():
        answer = network.velocity_to_displacement(mean, size)[0].flatten(1)
    voxels = torch.arange(answer.shape[1])
    truth = answer.clone()
    truth[0] += 0.25
    case = {
        "mean": mean,
        "log_var": torch.full((1, 3, *grid), 2 * math.log(sigma)),
        "residual": torch.zeros(1, 1, *grid),
        "truth": truth,
        "answer": answer,
        "voxels": voxels,
        "size": size,
        "seed": 3,
        "displacement_norm": answer.norm(dim=0),
    }
    return network, case


def test_case_errors_are_the_calibrated_map_and_the_answers_error():
    from monai_probreg.uncertainty.calibration import Calibration

    _, case = _case(mean_shift=0.5)
    std, error, norm = probe.case_errors(case, Calibration(2.0, 0.0))
    # the std map: 2 * 0.05 velocity-grid voxels, times (15 - 1) / (8 - 1) = 2 image voxels, every component
    assert std.shape == error.shape == norm.shape == (3, 15**3)
    assert std == pytest.approx(0.2, rel=1e-5)
    assert error[0] == pytest.approx(-0.25) and error[1:] == pytest.approx(0.0)  # answer - truth, the sign kept
    assert norm == pytest.approx(case["displacement_norm"].numpy()[None].repeat(3, 0))


def test_sampled_variance_is_damped_and_widened_by_the_gain():
    from monai_probreg.uncertainty.calibration import Calibration

    network, case = _case()
    mapped = probe.case_errors(case, Calibration(1.0, 0.0))[0] ** 2
    sampled = probe.sampled_case_variance(network, case, Calibration(1.0, 0.0), 64)
    assert sampled.shape == (3, 15**3)
    kappa = sampled.mean() / mapped.mean()
    assert 0.2 < kappa < 0.7  # independent noise between the velocity grid's voxels: weights squared
    gained = probe.sampled_case_variance(network, case, Calibration(1.0, 0.0, sample_gain=2.0), 64)
    # the same draws, twice as wide: four times the variance were the integration linear; its damping grows with the
    # spread, so a little less
    assert 3.3 < gained.mean() / sampled.mean() < 4.0


def test_sampled_case_errors_take_the_samples_std_and_the_answers_error():
    from monai_probreg.uncertainty.calibration import Calibration

    network, case = _case()
    std, error, _ = probe.sampled_case_errors(network, case, Calibration(1.0, 0.0), 8)
    np.testing.assert_allclose(std**2, probe.sampled_case_variance(network, case, Calibration(1.0, 0.0), 8), rtol=1e-6)
    np.testing.assert_allclose(error, probe.case_errors(case, Calibration(1.0, 0.0))[1])
