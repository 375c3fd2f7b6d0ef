"""The inference uncertainty maps: calibration shifts/scales them as stated; the std map is the first-order one (no
sampling); the label entropy's sampling is seeded and widened by sample_gain; bad K refused."""

import math

import pytest
import torch

from monai_probreg import ProbRegNet
from monai_probreg.uncertainty.calibration import calibrate_log_var
from monai_probreg.uncertainty.entropy import velocity_entropy
from monai_probreg.uncertainty.partial_volume import PartialVolumeLabels
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.uncertainty.spread import displacement_variance

SIZE = (12, 10, 8)


@pytest.fixture
def setup():
    torch.manual_seed(0)
    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    mean = 0.3 * torch.randn(1, 3, 6, 5, 4)
    log_var = torch.full((1, 3, 6, 5, 4), -6.0) + 0.5 * torch.rand(1, 3, 6, 5, 4)
    labels = torch.zeros(1, 1, *SIZE, dtype=torch.int16)
    labels[..., :6, :, :] = 3
    labels[..., 6:, :5, :] = 5
    return network, mean, log_var, labels


def test_velocity_entropy_shifts_by_dims_log_scale(setup):
    network, mean, log_var, _ = setup
    raw = posterior_maps(network, mean, log_var, SIZE).velocity_entropy
    calibrated = posterior_maps(network, mean, log_var, SIZE, std_scale=3.0).velocity_entropy
    torch.testing.assert_close(calibrated - raw, torch.full_like(raw, 3 * math.log(3.0)), atol=1e-5, rtol=0)


def test_displacement_std_scales_with_std_scale(setup):
    network, mean, log_var, _ = setup
    raw = posterior_maps(network, mean, log_var, SIZE, num_samples=8).displacement_std
    doubled = posterior_maps(network, mean, log_var, SIZE, num_samples=8, std_scale=2.0).displacement_std
    assert raw.shape == SIZE and raw.min() > 0
    torch.testing.assert_close(doubled, 2.0 * raw, rtol=1e-5, atol=0)  # first order: linear in the scale


def test_bias_fraction_widens_the_velocity_posterior_where_the_mean_is_long(setup):
    network, mean, log_var, _ = setup
    raw = posterior_maps(network, mean, log_var, SIZE, num_samples=4)
    biased = posterior_maps(network, mean, log_var, SIZE, num_samples=4, bias_fraction=0.3)
    # sigma^2 -> sigma^2 + (0.3 |mu|)^2 per component: the entropy of that Gaussian, resized like the raw one
    widened = torch.log(log_var.exp() + 0.09 * mean.pow(2).sum(1, keepdim=True))
    torch.testing.assert_close(biased.velocity_entropy, velocity_entropy(widened, SIZE)[0, 0], atol=1e-5, rtol=0)
    # |mu| ~ 0.5 voxel against sigma ~ 0.05: the sampled spread grows several times
    assert (biased.displacement_std / raw.displacement_std).median() > 2.0


def test_the_residual_term_widens_the_posterior_where_the_pair_stays_unlike(setup):
    network, mean, log_var, _ = setup
    residual = torch.zeros(1, 1, *mean.shape[2:])
    residual[..., :3, :, :] = 0.05  # the first half of axis 0 unlike, the second alike
    raw = posterior_maps(network, mean, log_var, SIZE, num_samples=4)
    widened = posterior_maps(network, mean, log_var, SIZE, num_samples=4, residual=residual, residual_weight=0.5)
    expected = torch.log(log_var.exp() + 0.5 * residual)  # sigma^2 + w r, per component
    torch.testing.assert_close(widened.velocity_entropy, velocity_entropy(expected, SIZE)[0, 0], atol=1e-5, rtol=0)
    ratio = widened.displacement_std / raw.displacement_std
    # sqrt((0.0025 + 0.025) / 0.0025) ~ 3.3 where the residual is, 1 where not (velocity grid 6 -> 12 voxels)
    assert ratio[:4].median() > 2.5 and ratio[-3:].median() < 1.5


def test_label_entropy_of_a_certain_posterior_is_the_partial_volume_of_its_mean_positive_at_boundaries_when_not(
    setup,
):
    network, mean, _, labels = setup
    certain = posterior_maps(network, mean, torch.full_like(mean, -30.0), SIZE, 6, moving_label=labels)
    # every sample is the mean: what is left is the mean's own reading between voxels, 0 away from the boundaries
    reading = PartialVolumeLabels(labels)
    reading.add(network.velocity_to_displacement(mean, SIZE))
    assert certain.label_entropy is not None
    torch.testing.assert_close(certain.label_entropy, reading.entropy(), atol=1e-5, rtol=0)
    assert float((certain.label_entropy == 0).float().mean()) > 0.5
    vague = posterior_maps(network, mean, torch.full_like(mean, 0.0), SIZE, 6, moving_label=labels)
    assert vague.label_entropy.max() > 0.3
    assert vague.label_entropy.max() <= math.log(6) + 1e-6


def test_the_label_entropys_sampling_is_seeded_and_the_std_map_needs_none(setup):
    network, mean, log_var, labels = setup
    a = posterior_maps(network, mean, 0.0 * log_var - 2, SIZE, 4, moving_label=labels, seed=5)
    b = posterior_maps(network, mean, 0.0 * log_var - 2, SIZE, 4, moving_label=labels, seed=5)
    c = posterior_maps(network, mean, 0.0 * log_var - 2, SIZE, 8, moving_label=labels, seed=6)
    torch.testing.assert_close(a.label_entropy, b.label_entropy, rtol=0, atol=0)
    assert not torch.equal(a.label_entropy, c.label_entropy)
    torch.testing.assert_close(a.displacement_std, c.displacement_std, rtol=0, atol=0)  # whatever the seed and K


def test_the_std_map_is_the_first_order_spread_of_the_calibrated_posterior(setup):
    network, mean, log_var, _ = setup
    residual = torch.rand(1, 1, *mean.shape[2:]) * 1e-3
    spacing = (1.0, 1.5, 0.8)
    maps = posterior_maps(
        network, mean, log_var, SIZE, 4, 2.0, bias_fraction=0.1, spacing=spacing, residual=residual, residual_weight=3.0
    )
    calibrated = calibrate_log_var(log_var, 2.0, mean, 0.1, residual, 3.0)
    expected = displacement_variance(calibrated, SIZE, spacing)[0]
    torch.testing.assert_close(maps.displacement_variance, expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(maps.displacement_std, expected.sum(0).sqrt(), rtol=1e-6, atol=0)


def test_sample_gain_widens_the_label_entropys_samples_and_nothing_else(setup):
    network, mean, log_var, labels = setup
    log_var = torch.full_like(log_var, -3.0)
    gained = posterior_maps(network, mean, log_var, SIZE, 4, 1.5, labels, seed=2, sample_gain=2.0)
    plain = posterior_maps(network, mean, log_var, SIZE, 4, 1.5, labels, seed=2)
    wider = posterior_maps(network, mean, log_var, SIZE, 4, 3.0, labels, seed=2)
    # the same draws at a velocity std 1.5 * 2: the scale's entropy; the maps of the posterior itself stay at 1.5
    torch.testing.assert_close(gained.label_entropy, wider.label_entropy, rtol=0, atol=1e-5)
    assert float(gained.label_entropy.sum()) > float(plain.label_entropy.sum())
    torch.testing.assert_close(gained.displacement_std, plain.displacement_std, rtol=0, atol=0)
    torch.testing.assert_close(gained.velocity_entropy, plain.velocity_entropy, rtol=0, atol=0)


@pytest.mark.parametrize("gain", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_sample_gain_is_refused(setup, gain):
    network, mean, log_var, labels = setup
    with pytest.raises(ValueError, match="sample_gain"):
        posterior_maps(network, mean, log_var, SIZE, 2, moving_label=labels, sample_gain=gain)
    with pytest.raises(ValueError, match="sample_gain"):  # refused with no label to sample for too
        posterior_maps(network, mean, log_var, SIZE, 0, sample_gain=gain)


def test_no_samples_gives_entropy_only(setup):
    network, mean, log_var, labels = setup
    maps = posterior_maps(network, mean, log_var, SIZE, 0, moving_label=labels)
    assert maps.displacement_std is None and maps.label_entropy is None and maps.displacement_variance is None


@pytest.mark.parametrize("num_samples", [1, -2])
def test_bad_num_samples_is_refused(setup, num_samples):
    network, mean, log_var, _ = setup
    with pytest.raises(ValueError, match="num_samples"):
        posterior_maps(network, mean, log_var, SIZE, num_samples)


def test_batch_of_two_is_refused(setup):
    network, mean, log_var, _ = setup
    with pytest.raises(ValueError, match="one pair"):
        posterior_maps(network, mean.repeat(2, 1, 1, 1, 1), log_var.repeat(2, 1, 1, 1, 1), SIZE)


def test_spacing_of_the_wrong_length_is_refused(setup):
    network, mean, log_var, _ = setup
    with pytest.raises(ValueError, match="one spacing per axis"):
        posterior_maps(network, mean, log_var, SIZE, num_samples=2, spacing=(1.0, 1.0))


def test_interval_dof_draws_the_label_entropys_samples_student_t_and_nothing_else(setup):
    from monai_probreg.uncertainty.samples import sample_scales

    network, mean, log_var, labels = setup
    log_var = torch.full_like(log_var, -3.0)
    student = posterior_maps(network, mean, log_var, SIZE, 4, 1.5, labels, seed=2, interval_dof=3.0)
    gaussian = posterior_maps(network, mean, log_var, SIZE, 4, 1.5, labels, seed=2)
    assert not torch.equal(student.label_entropy, gaussian.label_entropy)
    torch.testing.assert_close(student.displacement_std, gaussian.displacement_std, rtol=0, atol=0)
    torch.testing.assert_close(student.velocity_entropy, gaussian.velocity_entropy, rtol=0, atol=0)
    # the same Gaussian draws, each sample's deviation times its scale: the labels read by hand
    calibrated = calibrate_log_var(log_var, 1.5, mean)
    generator = torch.Generator().manual_seed(2)
    eps = torch.randn((4, *mean.shape), generator=generator)
    z = mean + sample_scales(4, 3.0).view(4, 1, 1, 1, 1, 1) * calibrated.mul(0.5).exp() * eps
    reader = PartialVolumeLabels(labels)
    for velocity in z:
        reader.add(network.velocity_to_displacement(velocity, SIZE))
    torch.testing.assert_close(student.label_entropy, reader.entropy(), rtol=0, atol=1e-4)


@pytest.mark.parametrize("dof", [0.0, -3.0, float("nan")])
def test_a_bad_interval_dof_is_refused(setup, dof):
    network, mean, log_var, labels = setup
    with pytest.raises(ValueError, match="interval_dof"):
        posterior_maps(network, mean, log_var, SIZE, 2, moving_label=labels, interval_dof=dof)
