"""monai_probreg.engines.refinement: test-time refinement of the posterior mean (settings, recovery of a known shift,
consistency of the returned fields, the network left as it was, the engine and bundle hooks)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from monai_probreg.blocks.integration import resize_displacement
from monai_probreg.blocks.warp import warp_image
from monai_probreg.engines.handlers import RegistrationInferer
from monai_probreg.engines.refinement import (
    LATER_SETTINGS,
    RefinementSettings,
    local_blend,
    refine_registration,
    resize_log_var,
)
from monai_probreg.engines.registration import register_pair, timed_register_pair
from monai_probreg.losses.mind import MINDLoss
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.networks.probreg_net import ProbRegNet

pytestmark = pytest.mark.usefixtures("single_thread")

SHIFT = 1.5  # image-grid voxels: the known displacement the refinement must find
SMALL = {"enc_channels": (4, 8, 8, 8), "dec_channels": (8, 8, 8, 8, 4)}


def _identity_net(spatial_dims: int, **kwargs) -> ProbRegNet:
    """A small ProbRegNet whose posterior mean is exactly 0 (zeroed mean head): refinement starts at the identity."""
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=spatial_dims, **SMALL, **kwargs)
    with torch.no_grad():
        net.unet.mean_head.weight.zero_()
        net.unet.mean_head.bias.zero_()
    return net.eval()


def _blobs(shape: tuple[int, ...], offset: tuple[float, ...]) -> torch.Tensor:
    """(1, 1, *shape): a wide Gaussian off the centre plus a smaller one (no symmetry), moved by ``offset`` voxels."""
    axes = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")
    big = [0.45 * n + o for n, o in zip(shape, offset)]
    small = [0.7 * n + o for n, o in zip(shape, offset)]
    image = torch.exp(-sum((x - c) ** 2 for x, c in zip(axes, big)) / (2 * 5.0**2))
    image = image + 0.6 * torch.exp(-sum((x - c) ** 2 for x, c in zip(axes, small)) / (2 * 2.5**2))
    return image[None, None]


def _pair(shape: tuple[int, ...], axis: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(moving, fixed) with moving[y] = fixed[y - SHIFT e_axis]: the registration is u = +SHIFT e_axis (pull-back)."""
    offset = tuple(SHIFT if a == axis else 0.0 for a in range(len(shape)))
    return _blobs(shape, offset), _blobs(shape, (0.0,) * len(shape))


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("num_iterations", -1),
        ("num_iterations", 2.0),
        ("num_iterations", True),
        ("learning_rate", 0.0),
        ("learning_rate", -0.1),
        ("learning_rate", "0.1"),
        ("image_sigma", 0.0),
        ("image_sigma", math.nan),
        ("prior_lambda", -1.0),
        ("prior_lambda", None),
        ("posterior_weight", -0.5),
        ("posterior_weight", math.nan),
        ("posterior_weight", True),
        ("image_loss", "ncc"),
        ("image_loss", None),
        ("image_weight", -1.0),
        ("image_weight", math.nan),
        ("image_weight", "20"),
        ("fold_backtracks", -1),
        ("fold_backtracks", 1.0),
        ("fold_backtracks", True),
        ("lncc_kernel_size", 4),
        ("lncc_kernel_size", 1),
        ("lncc_kernel_size", 9.0),
        ("velocity_grid_factor", 0),
        ("velocity_grid_factor", 2.0),
        ("velocity_grid_factor", True),
        ("fold_local_steps", -1),
        ("fold_local_steps", 2.0),
        ("fold_local_steps", True),
        ("image_grid_factor", 0),
        ("image_grid_factor", 2.0),
        ("image_grid_factor", True),
        ("coarse_iterations", -1),
        ("coarse_iterations", 2.0),
        ("coarse_iterations", True),
        ("coarse_iterations", 1),  # more than num_iterations (0)
        ("symmetric_start", 1),
        ("symmetric_start", "yes"),
        ("similarity_guard", 1),
        ("similarity_guard", "true"),
        ("adam_eps", 0.0),
        ("adam_eps", -1e-8),
        ("adam_eps", "1e-8"),
        ("coarse_lncc_kernel_size", 4),
        ("coarse_lncc_kernel_size", 1),
        ("coarse_lncc_kernel_size", 5.0),
        ("image_loss", "mi"),
        ("mind_radius", -1),
        ("mind_radius", 1.0),
        ("mind_dilation", 0),
        ("mind_dilation", True),
    ],
)
def test_bad_setting_names_itself(name, value):
    with pytest.raises(ValueError, match=name):
        RefinementSettings(**{name: value})


def test_default_is_off_and_returns_the_output_itself():
    settings = RefinementSettings()
    assert not settings.enabled
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    output = register_pair(net, moving, fixed)
    assert refine_registration(net, moving, fixed, output, settings) is output


@pytest.mark.parametrize(("shape", "axis"), [((32, 48), 0), ((32, 48), 1), ((32, 32, 48), 2), ((32, 32, 48), 0)])
def test_refinement_finds_a_known_shift(shape, axis):
    """From the identity, the refined displacement inside the structure is +SHIFT along ``axis`` (pull-back: the
    moving structure sits SHIFT voxels higher) and ~0 along the other axes; the image error drops. The prior is
    strong enough (lambda 10) that the translation, which it does not penalise, wins over the non-rigid fields that
    match smooth blobs about as well (with lambda 0.1 the mean displacement stops near 1.0)."""
    net = _identity_net(len(shape))
    moving, fixed = _pair(shape, axis)
    settings = RefinementSettings(
        num_iterations=60,
        learning_rate=0.1,
        image_loss="gaussian",
        image_weight=1.0,
        image_sigma=0.05,
        prior_lambda=10.0,
        posterior_weight=0.0,
    )  # the untrained posterior (log_var -10) would pin it
    start = register_pair(net, moving, fixed)
    refined = refine_registration(net, moving, fixed, start, settings)
    inside = fixed[0, 0] > 0.3
    for k in range(len(shape)):
        mean_k = refined.displacement[0, k][inside].mean().item()
        expected = SHIFT if k == axis else 0.0
        # tolerance 0.25 voxel: the smoothness prior and the finite steps leave a small bias, a wrong sign or axis is
        # off by >= 1.5
        assert mean_k == pytest.approx(expected, abs=0.25), (k, mean_k)
    before = (start.warped - fixed).square().mean()
    after = (refined.warped - fixed).square().mean()
    assert after < 0.1 * before, (before.item(), after.item())


def test_refinement_with_local_ncc_finds_a_known_shift():
    """The LNCC image term (the default) aligns the same pair; the direction is the Gaussian term's (pull-back)."""
    assert RefinementSettings().image_loss == "lncc"
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=1)
    settings = RefinementSettings(num_iterations=60, learning_rate=0.1, prior_lambda=10.0, posterior_weight=0.0)
    refined = refine_registration(net, moving, fixed, register_pair(net, moving, fixed), settings)
    inside = fixed[0, 0] > 0.3
    assert refined.displacement[0, 1][inside].mean().item() == pytest.approx(SHIFT, abs=0.35)
    assert refined.displacement[0, 0][inside].abs().mean().item() < 0.35


def _folding_case() -> tuple:
    """A pair of noise images refined with a huge step and almost no prior: the optimiser folds the field."""
    net = _identity_net(2)
    generator = torch.Generator().manual_seed(3)
    moving, fixed = (torch.rand((1, 1, 32, 48), generator=generator) for _ in range(2))
    return net, moving, fixed, register_pair(net, moving, fixed)


def _folds(displacement: torch.Tensor) -> int:
    return int((jacobian_determinant(displacement) <= 0).sum())


# a huge step, almost no prior, no local step: the folding case's refinement, guarded by halving alone
LOOSE_HALVING = {
    "num_iterations": 30,
    "learning_rate": 2.0,
    "prior_lambda": 1e-6,
    "posterior_weight": 0.0,
    "fold_local_steps": 0,
}


def test_the_fold_guard_backs_off_towards_the_network_mean_until_nothing_folds():
    net, moving, fixed, start = _folding_case()
    loose = LOOSE_HALVING
    unguarded = refine_registration(net, moving, fixed, start, RefinementSettings(**loose, fold_backtracks=0))
    assert _folds(unguarded.displacement) > 0  # the case folds without the guard, so the guard has work to do
    halving = RefinementSettings(**loose, fold_backtracks=4)  # the halving alone
    guarded = refine_registration(net, moving, fixed, start, halving)
    assert _folds(guarded.displacement) == 0
    change, full = guarded.velocity_mean - start.velocity_mean, unguarded.velocity_mean - start.velocity_mean
    with torch.no_grad():  # brute force: the largest fold-free fraction of the change, 1/2 ... 1/16, else none
        fractions = [0.5**k for k in range(1, 5)] + [0.0]
        size = moving.shape[2:]
        expected = next(
            f
            for f in fractions
            if f == 0.0 or _folds(net.velocity_to_displacement(start.velocity_mean + f * full, size)) == 0
        )
    torch.testing.assert_close(change, expected * full, rtol=0, atol=1e-6)
    with torch.no_grad():  # and the returned fields are those of the kept mean
        torch.testing.assert_close(
            guarded.displacement, net.velocity_to_displacement(guarded.velocity_mean, moving.shape[2:])
        )


def test_without_a_fold_free_fraction_the_networks_registration_is_returned_as_it_was():
    net, moving, fixed, start = _folding_case()
    loose = LOOSE_HALVING
    unguarded = refine_registration(net, moving, fixed, start, RefinementSettings(**loose, fold_backtracks=0))
    with torch.no_grad():  # the premise: half of the change still folds, so one backtrack cannot save it
        half = start.velocity_mean + 0.5 * (unguarded.velocity_mean - start.velocity_mean)
        assert _folds(net.velocity_to_displacement(half, moving.shape[2:])) > 0
    settings = RefinementSettings(**loose, fold_backtracks=1)
    assert refine_registration(net, moving, fixed, start, settings) is start


def test_the_fold_guard_leaves_a_fold_free_refinement_alone():
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    start = register_pair(net, moving, fixed)
    settings = {"num_iterations": 20, "posterior_weight": 0.0}
    guarded = refine_registration(net, moving, fixed, start, RefinementSettings(**settings))
    unguarded = refine_registration(net, moving, fixed, start, RefinementSettings(**settings, fold_backtracks=0))
    assert _folds(unguarded.displacement) == 0
    torch.testing.assert_close(guarded.velocity_mean, unguarded.velocity_mean, rtol=0, atol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_the_local_blend_is_one_around_the_folds_and_zero_far_from_them(spatial_dims):
    """One folded voxel of a fine grid (4x the velocity grid): weight 1 on its cell and within ``radius`` cells,
    between 0 and 1 up to ``3 radius`` cells, 0 beyond; the cell is found with an anisotropic ratio too."""
    grid = (12, 16, 10)[:spatial_dims]
    fine = [4 * n for n in grid]
    fine[0] += 3  # not an integer multiple: the adaptive pooling still maps the voxel to its cell
    folds = torch.zeros((1, 1, *fine), dtype=torch.bool)
    cell = (5, 7, 4)[:spatial_dims]
    voxel = tuple(int((c + 0.5) * f / g) for c, f, g in zip(cell, fine, grid))
    folds[(0, 0, *voxel)] = True
    weight = local_blend(folds, grid, radius=1)[0, 0]
    assert tuple(weight.shape) == grid
    index = torch.stack(torch.meshgrid(*[torch.arange(n) for n in grid], indexing="ij"))
    distance = (index - torch.tensor(cell).view(-1, *[1] * spatial_dims)).abs().amax(0)  # chessboard, in cells
    assert torch.all(weight[distance <= 1] == 1.0)
    assert torch.all(weight[distance >= 4] == 0.0)
    ramp = weight[(distance == 2) | (distance == 3)]
    assert torch.all((ramp > 0) & (ramp < 1))


def test_the_local_fold_guard_keeps_the_change_away_from_the_folds():
    """A shifted pair with unrelated noise in one corner: refined with a large step and a weak prior, the field folds
    in that corner only. The local guard returns a fold-free field that keeps the whole change in the opposite corner, and
    more of the change overall than halving it."""
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    generator = torch.Generator().manual_seed(3)
    for image in (moving, fixed):
        image[..., 2:12, 34:46] = torch.rand((10, 12), generator=generator)
    start = register_pair(net, moving, fixed)
    loose = {"num_iterations": 30, "learning_rate": 0.5, "prior_lambda": 0.01, "posterior_weight": 0.0}
    unguarded = RefinementSettings(**loose, fold_backtracks=0, fold_local_steps=0)
    free = refine_registration(net, moving, fixed, start, unguarded)
    assert _folds(free.displacement) > 0
    local = refine_registration(
        net, moving, fixed, start, RefinementSettings(**loose, fold_backtracks=0, fold_local_steps=4)
    )
    assert _folds(local.displacement) == 0
    change = local.velocity_mean - start.velocity_mean
    full = free.velocity_mean - start.velocity_mean
    far = (..., slice(10, None), slice(0, 8))  # velocity cells (16 x 24 grid) of the corner opposite the noise
    torch.testing.assert_close(change[far], full[far], rtol=0, atol=1e-6)
    assert float(full[far].abs().max()) > 0.1  # the premise: there is a change to keep there
    halving = RefinementSettings(**loose, fold_backtracks=4, fold_local_steps=0)
    halved = refine_registration(net, moving, fixed, start, halving)
    assert _folds(halved.displacement) == 0
    assert float((change - full).abs().mean()) < float((halved.velocity_mean - start.velocity_mean - full).abs().mean())


def test_refined_fields_are_consistent_and_the_network_is_untouched():
    net = _identity_net(3, bidirectional=True)
    params = {k: v.clone() for k, v in net.state_dict().items()}
    moving, fixed = _pair((32, 32, 48), axis=1)
    start = register_pair(net, moving, fixed)
    refined = refine_registration(net, moving, fixed, start, RefinementSettings(num_iterations=5))
    assert torch.equal(refined.velocity, refined.velocity_mean)
    assert not torch.equal(refined.velocity_mean, start.velocity_mean)
    assert torch.equal(refined.velocity_log_var, start.velocity_log_var)  # the uncertainty stays the network's
    with torch.no_grad():
        displacement = net.velocity_to_displacement(refined.velocity_mean, moving.shape[2:])
        inverse = net.velocity_to_displacement(-refined.velocity_mean, moving.shape[2:])
        torch.testing.assert_close(refined.displacement, displacement)
        torch.testing.assert_close(refined.warped, warp_image(moving, displacement))
        torch.testing.assert_close(refined.inverse_displacement, inverse)
        torch.testing.assert_close(refined.warped_fixed, warp_image(fixed, inverse))
    assert all(torch.equal(params[k], v) for k, v in net.state_dict().items())
    assert all(p.grad is None for p in net.parameters())


def test_a_strong_posterior_weight_keeps_the_network_mean():
    """The pull is in units of the network's posterior std: the untrained head's log_var of -10 (std 0.007 voxel) pins
    the mean to the network's at the default weight, and weight 0 lets it go."""
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    start = register_pair(net, moving, fixed)
    free = refine_registration(net, moving, fixed, start, RefinementSettings(num_iterations=20, posterior_weight=0.0))
    pinned = refine_registration(net, moving, fixed, start, RefinementSettings(num_iterations=20))
    assert free.velocity_mean.abs().max() > 0.2
    assert pinned.velocity_mean.abs().max() < 0.2 * free.velocity_mean.abs().max()


def test_refinement_refuses_inference_mode():
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    output = register_pair(net, moving, fixed)
    with torch.inference_mode(), pytest.raises(RuntimeError, match="inference_mode"):
        refine_registration(net, moving, fixed, output, RefinementSettings(num_iterations=1))


def test_refinement_checks_the_pair():
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    output = register_pair(net, moving, fixed)
    with pytest.raises(ValueError, match="same shape"):
        refine_registration(net, moving, fixed[..., :32], output, RefinementSettings(num_iterations=1))
    with pytest.raises(ValueError, match="batch"):
        refine_registration(
            net, moving.repeat(2, 1, 1, 1), fixed.repeat(2, 1, 1, 1), output, RefinementSettings(num_iterations=1)
        )


def test_register_pair_and_the_engine_inferer_refine_the_same_way():
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    settings = RefinementSettings(num_iterations=8)
    by_hand = refine_registration(net, moving, fixed, register_pair(net, moving, fixed), settings)
    through_register, runtime = timed_register_pair(net, moving, fixed, settings)
    inferer = RegistrationInferer(refinement=settings)
    with torch.no_grad():  # as MONAI's evaluator calls its inferer
        through_inferer = inferer(moving, net, fixed)
    torch.testing.assert_close(through_register.displacement, by_hand.displacement)
    torch.testing.assert_close(through_inferer.displacement, by_hand.displacement)
    assert runtime > 0 and inferer.last_runtime_s > 0
    assert not torch.equal(RegistrationInferer()(moving, net, fixed).displacement, by_hand.displacement)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_a_resized_log_variance_is_in_the_new_grids_units(spatial_dims):
    """Variance of a velocity component scales with the square of resize_displacement's factor on its axis."""
    source = (5, 6, 7)[:spatial_dims]
    target = [2 * n for n in source]
    log_var = torch.full((1, spatial_dims, *source), -3.0)
    resized = resize_log_var(log_var, target)
    assert tuple(resized.shape) == (1, spatial_dims, *target)
    for k, (n, m) in enumerate(zip(source, target)):
        assert torch.allclose(resized[0, k], torch.tensor(-3.0 + 2.0 * math.log((m - 1) / (n - 1))), atol=1e-6)
    # the same factor as the mean's: a sample's std and the resized mean scale alike
    std = resize_displacement(torch.ones(1, spatial_dims, *source), target)
    assert torch.allclose((0.5 * (resized + 3.0)).exp(), std, atol=1e-5)


def test_a_finer_refinement_grid_starts_from_the_networks_field_and_finds_the_shift():
    """velocity_grid_factor 2: the mean and log-variance live on a grid twice finer than the network's velocity
    grid; a step so small that nothing moves keeps the network's displacement (the start, a smooth field of about two
    voxels, resized in the finer grid's units, integrates to the same field: a wrong unit would scale it), and a real
    refinement finds the known shift as the default grid does."""
    net = _identity_net(2, int_downsize=2)
    moving, fixed = _pair((32, 48), axis=1)
    start = register_pair(net, moving, fixed)
    coarse = tuple(start.velocity_mean.shape[2:])
    axes = torch.meshgrid(*[torch.linspace(0, math.pi, n) for n in coarse], indexing="ij")
    smooth = torch.stack([1.5 * torch.sin(axes[0]) * torch.cos(axes[1]), torch.sin(axes[1])])[None]
    start = start._replace(
        velocity_mean=smooth, displacement=net.velocity_to_displacement(smooth, list(moving.shape[2:]))
    )
    still = RefinementSettings(num_iterations=1, learning_rate=1e-9, velocity_grid_factor=2)
    kept = refine_registration(net, moving, fixed, start, still)
    assert tuple(kept.velocity_mean.shape[2:]) == tuple(2 * n for n in coarse)
    assert kept.velocity_log_var.shape == kept.velocity_mean.shape
    assert start.displacement.abs().max() > 1.0
    # linear interpolation of the velocity before or after integrating differs by a few hundredths of a voxel here;
    # a velocity left in the coarse grid's units would be off by half a voxel and more
    assert (kept.displacement - start.displacement).abs().max() < 0.05
    settings = RefinementSettings(
        num_iterations=60, learning_rate=0.1, prior_lambda=10.0, posterior_weight=0.0, velocity_grid_factor=2
    )
    refined = refine_registration(net, moving, fixed, register_pair(net, moving, fixed), settings)
    inside = fixed[0, 0] > 0.3
    assert refined.displacement[0, 1][inside].mean().item() == pytest.approx(SHIFT, abs=0.35)
    assert refined.displacement[0, 0][inside].abs().mean().item() < 0.35


@pytest.mark.parametrize(
    "shape, size", [((1, 2, 5, 6), [10, 12, 14]), ((1, 3, 5, 6), [10, 12]), ((1, 2, 1, 6), [2, 12])]
)
def test_a_log_variance_resize_names_a_bad_shape(shape, size):
    with pytest.raises(ValueError, match="expected|at least 2"):
        resize_log_var(torch.zeros(shape), size)


def test_a_finer_image_grid_is_capped_at_the_images_and_finds_the_shift():
    """image_grid_factor: the loss's images on a grid finer than the network's (network_size 16 x 32 here), at most
    the images' own (32 x 64): a factor of 4 is capped there and gives exactly the factor 2's answer, which differs
    from the network grid's and finds the known shift (pull-back, +SHIFT along the axis)."""
    net = _identity_net(2, network_size=(16, 32))
    moving, fixed = _pair((32, 64), axis=1)
    start = register_pair(net, moving, fixed)
    base = {"num_iterations": 60, "learning_rate": 0.1, "prior_lambda": 10.0, "posterior_weight": 0.0}
    answers = {
        f: refine_registration(net, moving, fixed, start, RefinementSettings(**base, image_grid_factor=f))
        for f in (1, 2, 4)
    }
    assert torch.equal(answers[2].velocity_mean, answers[4].velocity_mean)
    assert not torch.allclose(answers[1].velocity_mean, answers[2].velocity_mean)
    inside = fixed[0, 0] > 0.3
    assert answers[2].displacement[0, 1][inside].mean().item() == pytest.approx(SHIFT, abs=0.35)
    assert answers[2].displacement[0, 0][inside].abs().mean().item() < 0.35


def test_differences_name_each_setting_that_differs_from_a_record():
    """RefinementSettings.differences: what summary.json reports against the quality model's fit."""
    fitted = RefinementSettings(num_iterations=10).as_dict()
    assert RefinementSettings(num_iterations=10).differences(fitted) == {}
    changed = RefinementSettings(num_iterations=0, prior_lambda=3.0)
    assert changed.differences(fitted) == {"num_iterations": [10, 0], "prior_lambda": [1.5, 3.0]}
    assert RefinementSettings().differences({}) == {}  # an empty record: no refinement
    assert RefinementSettings(num_iterations=3).differences({}) == {"num_iterations": [0, 3]}
    # neither refines: the other settings are unused, so nothing differs
    assert RefinementSettings(image_grid_factor=2).differences({}) == {}
    assert RefinementSettings(num_iterations=3, image_grid_factor=2).differences({}) == {
        "num_iterations": [0, 3],
        "image_grid_factor": [1, 2],
    }
    older = {k: v for k, v in fitted.items() if k != "image_grid_factor"}  # a record made before a setting existed
    assert RefinementSettings(num_iterations=10).differences(older) == {"image_grid_factor": [None, 1]}
    # a record made before the later settings ran their defaults: nothing differs there unless this run changes them
    before = {k: v for k, v in fitted.items() if k not in LATER_SETTINGS}
    assert RefinementSettings(num_iterations=10).differences(before) == {}
    assert RefinementSettings(num_iterations=10, adam_eps=1e-5).differences(before) == {"adam_eps": [1e-8, 1e-5]}
    assert set(LATER_SETTINGS) <= set(fitted)
    assert all(RefinementSettings().as_dict()[k] == v for k, v in LATER_SETTINGS.items())


def test_a_coarse_to_fine_schedule_runs_its_first_steps_on_the_networks_grid():
    """coarse_iterations: every step coarse is image_grid_factor 1's answer, none is the finer grid's, and a
    schedule of both finds the known shift (network_size 16 x 32, images 32 x 64)."""
    net = _identity_net(2, network_size=(16, 32))
    moving, fixed = _pair((32, 64), axis=1)
    start = register_pair(net, moving, fixed)
    base = {"num_iterations": 60, "learning_rate": 0.1, "prior_lambda": 10.0, "posterior_weight": 0.0}

    def refined(**kwargs):
        return refine_registration(net, moving, fixed, start, RefinementSettings(**base, **kwargs)).velocity_mean

    coarse_only, fine_only = refined(image_grid_factor=2, coarse_iterations=60), refined(image_grid_factor=2)
    torch.testing.assert_close(coarse_only, refined(image_grid_factor=1), rtol=1e-5, atol=1e-6)
    narrow = refined(image_grid_factor=2, coarse_iterations=60, coarse_lncc_kernel_size=5)  # the coarse window
    torch.testing.assert_close(narrow, refined(image_grid_factor=1, lncc_kernel_size=5), rtol=1e-5, atol=1e-6)
    assert not torch.allclose(narrow, coarse_only)
    torch.testing.assert_close(fine_only, refined(image_grid_factor=2, coarse_iterations=0), rtol=0, atol=0)
    both = refine_registration(
        net, moving, fixed, start, RefinementSettings(**base, image_grid_factor=2, coarse_iterations=50)
    )
    assert not torch.allclose(both.velocity_mean, coarse_only) and not torch.allclose(both.velocity_mean, fine_only)
    inside = fixed[0, 0] > 0.3
    assert both.displacement[0, 1][inside].mean().item() == pytest.approx(SHIFT, abs=0.35)


def _trained_like_net(spatial_dims: int) -> ProbRegNet:
    """A small ProbRegNet with a nonzero mean head: it invents a displacement even for a pair of copies."""
    torch.manual_seed(1)
    net = ProbRegNet(spatial_dims=spatial_dims, **SMALL)
    with torch.no_grad():
        net.unet.mean_head.weight.normal_(0.0, 0.5)
        net.unet.mean_head.bias.normal_(0.0, 0.5)
    return net.eval()


def test_the_symmetric_start_is_the_antisymmetric_part_of_the_two_directions():
    """symmetric_start: the refinement starts from (mu(m, f) - mu(f, m)) / 2 (one step of a vanishing size keeps it
    there), where the plain start is mu(m, f)."""
    net = _trained_like_net(2)
    moving, fixed = _pair((32, 48), axis=0)
    forward, backward = register_pair(net, moving, fixed), register_pair(net, fixed, moving)
    tiny = {"num_iterations": 1, "learning_rate": 1e-9}
    symmetric = refine_registration(net, moving, fixed, forward, RefinementSettings(**tiny, symmetric_start=True))
    expected = 0.5 * (forward.velocity_mean - backward.velocity_mean)
    torch.testing.assert_close(symmetric.velocity_mean, expected, rtol=0, atol=1e-7)
    plain = refine_registration(net, moving, fixed, forward, RefinementSettings(**tiny))
    torch.testing.assert_close(plain.velocity_mean, forward.velocity_mean, rtol=0, atol=1e-7)


def test_a_scan_onto_a_copy_of_itself_starts_at_the_identity_and_a_gradient_floor_keeps_it_there():
    """The network invents a displacement for a pair of copies; the symmetric start removes it exactly. There the
    image term's gradient is float rounding, which Adam scales into a step of about its learning rate (0.3 voxel);
    adam_eps well above that rounding turns it into a step of its size instead."""
    net = _trained_like_net(2)
    image, _ = _pair((32, 48), axis=0)
    # a zero background, as a skull-stripped scan's: the blobs' faint tails would leave windows whose variance is
    # below LNCC's floor, where the loss is not stationary at the identity (a real gradient, not rounding)
    image = torch.where(image > 0.02, image, torch.zeros_like(image))
    output = register_pair(net, image, image)
    assert output.displacement.abs().max() > 0.05
    one_step = {"num_iterations": 1, "learning_rate": 0.3, "posterior_weight": 0.0, "symmetric_start": True}
    floored = refine_registration(net, image, image, output, RefinementSettings(**one_step, adam_eps=1e-4))
    assert floored.velocity_mean.abs().max() < 1e-3
    unfloored = refine_registration(net, image, image, output, RefinementSettings(**one_step, adam_eps=1e-8))
    assert unfloored.velocity_mean.abs().max() > 0.1


def test_the_cropped_hand_written_lncc_refines_as_monais_lncc_does():
    """The refinement's LNCC (the fixed image's sums once, a hand-written gradient, the moving image warped only in
    the box around the fixed image's nonzero voxels) gives the answer of MONAI's warp and LNCC over the whole grid
    (``fast_sampling=False`` takes that path), on a fixed image with a zero background."""
    moving, fixed = _pair((48, 48), axis=1)
    fixed = torch.where(fixed > 0.05, fixed, torch.zeros_like(fixed))
    settings = RefinementSettings(num_iterations=10, learning_rate=0.1, posterior_weight=0.0)
    answers = []
    for fast in (True, False):
        net = _identity_net(2, fast_sampling=fast)
        answers.append(refine_registration(net, moving, fixed, register_pair(net, moving, fixed), settings))
    torch.testing.assert_close(answers[0].velocity_mean, answers[1].velocity_mean, rtol=1e-4, atol=1e-5)
    assert answers[0].velocity_mean.abs().max() > 0.1  # it moved


def test_a_number_of_steps_keeps_the_schedules_finer_steps_last():
    """with_iterations (the command's --refine N): N steps in all, as many finer steps as the schedule has (at most
    N), the rest coarse; the other settings as they were."""
    schedule = RefinementSettings(num_iterations=10, coarse_iterations=8, learning_rate=0.2)
    assert schedule.with_iterations(20) == RefinementSettings(
        num_iterations=20, coarse_iterations=18, learning_rate=0.2
    )
    assert schedule.with_iterations(1) == RefinementSettings(num_iterations=1, coarse_iterations=0, learning_rate=0.2)
    assert not schedule.with_iterations(0).enabled
    assert RefinementSettings(num_iterations=10).with_iterations(4) == RefinementSettings(num_iterations=4)
    with pytest.raises(ValueError, match="num_iterations"):
        schedule.with_iterations(-1)


def test_fields_replaced_with_a_number_of_steps_keep_the_finer_steps_last():
    schedule = RefinementSettings(num_iterations=10, coarse_iterations=8)
    assert schedule.with_fields(num_iterations=4, prior_lambda=2.0) == RefinementSettings(
        num_iterations=4, coarse_iterations=2, prior_lambda=2.0
    )
    assert schedule.with_fields(num_iterations=4, coarse_iterations=1).coarse_iterations == 1  # given: as given
    assert schedule.with_fields(adam_eps=1e-5) == RefinementSettings(
        num_iterations=10, coarse_iterations=8, adam_eps=1e-5
    )


def test_a_coarse_window_is_not_used_by_finer_steps_on_the_same_grid():
    """With no finer grid (image_grid_factor 1: the coarse grid is the finer one), the coarse steps' window is theirs
    alone: the finer steps compare with lncc_kernel_size, so the schedule differs from the coarse window throughout."""
    net = _identity_net(2)
    moving, fixed = _pair((32, 48), axis=1)
    start = register_pair(net, moving, fixed)
    base = {"num_iterations": 12, "learning_rate": 0.1, "prior_lambda": 10.0, "posterior_weight": 0.0}

    def refined(**kwargs):
        return refine_registration(net, moving, fixed, start, RefinementSettings(**base, **kwargs)).velocity_mean

    mixed = refined(coarse_iterations=6, coarse_lncc_kernel_size=5)
    assert not torch.allclose(mixed, refined(lncc_kernel_size=5))
    assert not torch.allclose(mixed, refined())


def test_the_similarity_guard_gives_the_identity_for_a_scan_onto_a_copy_of_itself():
    """A pair of copies: the network invents a displacement and the refinement, pulled towards it, keeps some; every
    deformation leaves the copies less alike than none, so the guard returns the identity (zero velocity mean and
    displacement, the moving image itself); without the guard the invented displacement stays."""
    net = _trained_like_net(2)
    image, _ = _pair((32, 48), axis=0)
    output = register_pair(net, image, image)
    settings = RefinementSettings(num_iterations=3, learning_rate=0.1)
    unguarded = refine_registration(net, image, image, output, settings)
    assert unguarded.displacement.abs().max() > 0.05
    guarded = refine_registration(net, image, image, output, replace(settings, similarity_guard=True))
    assert not guarded.displacement.any() and not guarded.velocity_mean.any()
    torch.testing.assert_close(guarded.warped, image, rtol=0, atol=0)
    torch.testing.assert_close(guarded.velocity_log_var, unguarded.velocity_log_var)


@pytest.mark.parametrize(("shape", "axis"), [((32, 48), 1), ((32, 32, 48), 0)])
def test_the_similarity_guard_keeps_a_deformation_that_makes_the_images_more_alike(shape, axis):
    """A pair with something to register (a known shift): the guarded refinement is the unguarded one, bit for bit."""
    net = _identity_net(len(shape))
    moving, fixed = _pair(shape, axis)
    output = register_pair(net, moving, fixed)
    settings = RefinementSettings(num_iterations=20, learning_rate=0.1, posterior_weight=0.0)
    unguarded = refine_registration(net, moving, fixed, output, settings)
    guarded = refine_registration(net, moving, fixed, output, replace(settings, similarity_guard=True))
    assert guarded.displacement.abs().max() > 0.5
    torch.testing.assert_close(guarded.displacement, unguarded.displacement, rtol=0, atol=0)


def test_the_similarity_guard_decides_for_each_pair_of_a_batch():
    """A batch of a shifted pair and a pair of copies: the first keeps its deformation, the second gets the identity."""
    net = _trained_like_net(2)
    moving, fixed = _pair((32, 48), axis=1)
    moving, fixed = torch.cat([moving, fixed]), torch.cat([fixed, fixed])
    output = register_pair(net, moving, fixed)
    settings = RefinementSettings(num_iterations=20, learning_rate=0.1, posterior_weight=0.0, similarity_guard=True)
    refined = refine_registration(net, moving, fixed, output, settings)
    assert refined.displacement[0].abs().max() > 0.5
    assert not refined.displacement[1].any()
    torch.testing.assert_close(refined.warped[1], fixed[1], rtol=0, atol=0)


@pytest.mark.parametrize("spatial_dims", [2, 3])
def test_a_larger_prior_gives_a_smoother_refined_field(spatial_dims):
    """The prior's weight (the command's --smoothness scales prior_lambda): on a pair whose two blobs move apart, a
    much larger prior_lambda leaves a refined velocity of lower Laplacian energy (smoother) and a smaller spread of
    the Jacobian determinant."""
    shape = (32, 48) if spatial_dims == 2 else (32, 32, 48)
    axes = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")

    def blobs(offset: float) -> torch.Tensor:  # the two blobs shifted in opposite directions along the last axis
        centres = (
            [0.35 * n for n in shape[:-1]] + [0.35 * shape[-1] - offset],
            [0.65 * n for n in shape[:-1]] + [0.65 * shape[-1] + offset],
        )
        return sum(torch.exp(-sum((x - c) ** 2 for x, c in zip(axes, centre)) / 18.0) for centre in centres)[None, None]

    moving, fixed = blobs(1.5), blobs(0.0)
    net = _identity_net(spatial_dims)
    output = register_pair(net, moving, fixed)
    energy, spread = {}, {}
    for prior in (0.05, 50.0):
        settings = RefinementSettings(num_iterations=30, learning_rate=0.1, posterior_weight=0.0, prior_lambda=prior)
        refined = refine_registration(net, moving, fixed, output, settings)
        velocity = refined.velocity_mean[0]
        energy[prior] = sum(torch.diff(velocity, dim=d + 1).square().sum() for d in range(spatial_dims)).item()
        spread[prior] = jacobian_determinant(refined.displacement).std().item()
    assert energy[50.0] < 0.5 * energy[0.05] and spread[50.0] < spread[0.05]


# the MIND term from the identity: no pull (the untrained posterior would pin it), a prior that favours the translation
MIND_SETTINGS = RefinementSettings(
    num_iterations=1,
    learning_rate=0.1,
    prior_lambda=10.0,
    posterior_weight=0.0,
    image_loss="mind",
    image_weight=100.0,
    mind_dilation=1,
)


def _two_contrast_pair(shape: tuple[int, ...], axis: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_pair` with the moving image's contrast inverted (1 - image: bright where the fixed one is dark, as CSF
    between T2- and T1-weighted scans): a local correlation of the aligned pair is -1."""
    moving, fixed = _pair(shape, axis)
    return 1.0 - moving, fixed


@pytest.mark.parametrize(("shape", "axis"), [((32, 48), 1), ((32, 32, 48), 2)])
def test_the_mind_term_finds_a_known_shift_across_contrasts(shape, axis):
    """MIND compares the two contrasts: from the identity, the refined displacement inside the structure is +SHIFT
    along ``axis`` (the pull-back of the other terms) and the MIND term drops."""
    net = _identity_net(len(shape))
    moving, fixed = _two_contrast_pair(shape, axis)
    settings = replace(MIND_SETTINGS, num_iterations=60)
    start = register_pair(net, moving, fixed)
    refined = refine_registration(net, moving, fixed, start, settings)
    inside = fixed[0, 0] > 0.3
    for k in range(len(shape)):
        mean_k = refined.displacement[0, k][inside].mean().item()
        # 0.35 voxel: as the LNCC test's tolerance (prior bias, finite steps); a wrong sign or axis is off by >= 1.5
        assert mean_k == pytest.approx(SHIFT if k == axis else 0.0, abs=0.35), (k, mean_k)
    term = MINDLoss(dilation=1)
    assert term(refined.warped, fixed) < 0.5 * term(moving, fixed)


def test_the_similarity_guard_compares_two_contrasts_by_mind():
    """With the MIND term the guard compares by MIND: a right deformation across contrasts is kept, bit for bit; a
    pair of copies still gets the identity."""
    net = _identity_net(2)
    moving, fixed = _two_contrast_pair((32, 48), axis=1)
    output = register_pair(net, moving, fixed)
    settings = replace(MIND_SETTINGS, num_iterations=30)
    unguarded = refine_registration(net, moving, fixed, output, settings)
    guarded = refine_registration(net, moving, fixed, output, replace(settings, similarity_guard=True))
    assert guarded.displacement.abs().max() > 0.5
    torch.testing.assert_close(guarded.displacement, unguarded.displacement, rtol=0, atol=0)
    copies = refine_registration(
        _trained_like_net(2),
        fixed,
        fixed,
        register_pair(_trained_like_net(2), fixed, fixed),
        replace(settings, similarity_guard=True, num_iterations=3),
    )
    assert not copies.displacement.any()
