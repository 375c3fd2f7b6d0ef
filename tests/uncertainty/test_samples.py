"""How the label entropy's samples are drawn: the std widened by the gain, the Student-t scale mixture's stratified
scales (their t marginal against scipy's quantiles), one test per bad argument."""

from __future__ import annotations

import pytest
import torch
from scipy import stats

from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.uncertainty.samples import sample_log_var, sample_scales


def test_the_samples_log_var_widens_the_std_by_the_gain():
    log_var = torch.tensor([[-2.0, 0.5]])
    torch.testing.assert_close(sample_log_var(log_var, 3.0).mul(0.5).exp(), 3.0 * log_var.mul(0.5).exp())
    torch.testing.assert_close(sample_log_var(log_var, 1.0), log_var)
    with pytest.raises(ValueError, match="sample_gain"):
        sample_log_var(log_var, 0.0)


def test_gaussian_intervals_give_unit_scales():
    assert torch.equal(sample_scales(5, None), torch.ones(5))


def test_the_scales_are_the_strata_middles_of_the_chi2_largest_first():
    scales = sample_scales(4, 3.0).double()
    levels = stats.chi2.cdf(3.0 / scales.square().numpy(), 3.0)  # each scale's chi^2 quantile level
    assert levels == pytest.approx([0.125, 0.375, 0.625, 0.875], abs=1e-6)
    assert bool((scales[:-1] > scales[1:]).all())


@pytest.mark.parametrize("dof", [2.5, 3.0, 8.0])
def test_the_scale_mixture_has_the_student_t_marginal(dof):
    # one Gaussian draw per sample and voxel, one scale per sample: the pooled draws follow t_dof (scale 1)
    num = 2000
    z = sample_velocity(
        torch.zeros(1, 1, 400), torch.zeros(1, 1, 400), num, torch.Generator().manual_seed(0), sample_scales(num, dof)
    ).flatten()
    for level in (0.5, 0.8, 0.95, 0.99):
        observed = float(torch.quantile(z.abs(), level))
        assert observed == pytest.approx(stats.t.ppf(0.5 + level / 2, dof), rel=0.03), level
    gaussian = float(torch.quantile(torch.randn(num * 400, generator=torch.Generator().manual_seed(1)).abs(), 0.99))
    assert float(torch.quantile(z.abs(), 0.99)) > 1.1 * gaussian  # heavier tails than the Gaussian's


@pytest.mark.parametrize("num", [0, -2, 1.5, True])
def test_a_bad_sample_count_is_refused(num):
    with pytest.raises(ValueError, match="num_samples must be an integer >= 1"):
        sample_scales(num, 3.0)


@pytest.mark.parametrize("dof", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_dof_is_refused(dof):
    with pytest.raises(ValueError, match="interval_dof"):
        sample_scales(4, dof)
