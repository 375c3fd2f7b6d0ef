"""The refinement's cost-function masks (:class:`~monai_probreg.engines.refinement.RefinementMasks`): an artefact
only the moving image has pulls the unmasked refinement off a known shift; left out by the moving mask (or by a fixed
mask over where it lands), the shift is found; both LNCC paths (hand-written, MONAI's) and the Gaussian term agree with
masks; no masks is the same call as before."""

from __future__ import annotations

import pytest
import torch
from test_refinement import SHIFT, _identity_net, _pair

from monai_probreg.engines.refinement import RefinementMasks, RefinementSettings, refine_registration
from monai_probreg.engines.registration import register_pair

pytestmark = pytest.mark.usefixtures("single_thread")

SHAPE = (32, 48)
SETTINGS = RefinementSettings(num_iterations=60, learning_rate=0.1, prior_lambda=10.0, posterior_weight=0.0)
ARTEFACT_CENTRE = (14.0, 30.0)  # voxels: on the wide blob's edge, off both blobs' centres
ARTEFACT_RADIUS = 4.0
# voxels: a window centred outside the mask still reads the voxels inside it (as ANTs' masks), so the masks cover the
# artefact by the local NCC's window radius (9 // 2) and one voxel more
ARTEFACT_MARGIN = SETTINGS.lncc_kernel_size // 2 + 1.0
ARTEFACT_BRIGHTNESS = 3.0  # times the blobs' peak: what an unmasked local NCC cannot ignore


def _artefact(shape: tuple[int, ...], radius: float) -> torch.Tensor:
    axes = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")
    return (sum((x - c) ** 2 for x, c in zip(axes, ARTEFACT_CENTRE)) < radius**2)[None, None]


def _case():
    """(moving with a bright artefact, fixed, the artefact's mask with its margin) for the known shift along axis 1."""
    moving, fixed = _pair(SHAPE, axis=1)
    artefact = _artefact(SHAPE, ARTEFACT_RADIUS)
    moving = torch.where(artefact, torch.full_like(moving, ARTEFACT_BRIGHTNESS), moving)
    return moving, fixed, _artefact(SHAPE, ARTEFACT_RADIUS + ARTEFACT_MARGIN)


def _shift_error(refined, fixed: torch.Tensor) -> tuple[float, float]:
    """(mean, max) error of the displacement along axis 1 against the known shift, over the blobs (fixed > 0.3)."""
    error = (refined.displacement[0, 1][fixed[0, 0] > 0.3] - SHIFT).abs()
    return error.mean().item(), error.max().item()


PULLED_OFF = (0.5, 2.0)  # voxels, mean and max: the unmasked refinement's error (measured: 0.70, 2.58)
FOUND = (0.25, 0.6)
ROUNDING_STEPS = (
    2e-3  # velocity voxels after 10 steps of 0.1 (measured: 4e-4)  # the masked one's (measured: 0.16, 0.46)
)


def test_a_moving_mask_over_an_artefact_recovers_the_shift_it_pulls_the_unmasked_refinement_off():
    net = _identity_net(2)
    moving, fixed, around = _case()
    start = register_pair(net, moving, fixed)
    plain = refine_registration(net, moving, fixed, start, SETTINGS)
    masks = RefinementMasks(moving=(~around).float())
    masked = refine_registration(net, moving, fixed, start, SETTINGS, masks)
    plain_error, masked_error = _shift_error(plain, fixed), _shift_error(masked, fixed)
    assert plain_error[0] > PULLED_OFF[0] and plain_error[1] > PULLED_OFF[1], plain_error
    assert masked_error[0] < FOUND[0] and masked_error[1] < FOUND[1], masked_error


def test_a_fixed_mask_leaves_out_where_the_artefact_lands():
    net = _identity_net(2)
    moving, fixed, around = _case()
    # where the artefact lands in the fixed frame: its mask moved by the shift, and where it starts
    landed = torch.roll(around, shifts=-round(SHIFT), dims=3) | around
    masked = refine_registration(
        net, moving, fixed, register_pair(net, moving, fixed), SETTINGS, RefinementMasks(fixed=(~landed).float())
    )
    error = _shift_error(masked, fixed)
    assert error[0] < FOUND[0] and error[1] < FOUND[1], error


@pytest.mark.parametrize("image_loss", ["lncc", "gaussian"])
def test_masked_refinement_paths_agree(image_loss):
    """The hand-written LNCC (the moving image and mask warped only in the fixed image's box) gives the answer of
    MONAI's warp and LNCC over the whole grid (``fast_sampling=False``), masks included; the Gaussian term's
    per-voxel path is differentiable and moves."""
    moving, fixed, around = _case()
    fixed = torch.where(fixed > 0.05, fixed, torch.zeros_like(fixed))
    settings = RefinementSettings(num_iterations=10, learning_rate=0.1, posterior_weight=0.0, image_loss=image_loss)
    masks = RefinementMasks(fixed=(fixed > 0.1).float(), moving=(~around).float())
    answers = []
    for fast in (True, False):
        net = _identity_net(2, fast_sampling=fast)
        answers.append(refine_registration(net, moving, fixed, register_pair(net, moving, fixed), settings, masks))
    # Adam turns a gradient of float rounding (where the masks leave the image term ~0) into a step of its own size
    # relative to that gradient's history: a few voxels of the two paths differ by a fraction of a thousandth
    torch.testing.assert_close(answers[0].velocity_mean, answers[1].velocity_mean, rtol=0, atol=ROUNDING_STEPS)
    assert answers[0].velocity_mean.abs().max() > 0.1  # it moved


def test_no_masks_and_empty_masks_are_the_unmasked_refinement():
    net = _identity_net(2)
    moving, fixed, _ = _case()
    start = register_pair(net, moving, fixed)
    settings = RefinementSettings(num_iterations=5, learning_rate=0.1, posterior_weight=0.0)
    plain = refine_registration(net, moving, fixed, start, settings)
    for masks in (None, RefinementMasks()):
        again = refine_registration(net, moving, fixed, start, settings, masks)
        torch.testing.assert_close(again.velocity_mean, plain.velocity_mean, rtol=0, atol=0)


def test_a_mask_on_another_grid_is_named():
    net = _identity_net(2)
    moving, fixed, _ = _case()
    with pytest.raises(ValueError, match=r"masks.moving: expected shape \(1, 1, 32, 48\)"):
        refine_registration(
            net,
            moving,
            fixed,
            register_pair(net, moving, fixed),
            SETTINGS,
            RefinementMasks(moving=torch.ones(1, 1, 8, 8)),
        )
