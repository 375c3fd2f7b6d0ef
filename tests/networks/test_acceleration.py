"""Inference speed levers give the plain path's outputs: float32 levers to rounding, bf16 within stated bounds.

Levers (``ProbRegNet`` arguments): ``channels_last`` (UNet layout), ``fast_sampling`` (one-pass grids, threaded
grid_sample), ``unet_precision`` ("auto" / "bf16" / "fp32"). "Plain" = all three off. Speed is never asserted here
(the benchmark shows it); these tests pin that a lever cannot change the registration beyond its tolerance.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from monai_probreg import ProbRegNet, jacobian_determinant, jacobian_stats, label_dice, warp_labels
from monai_probreg.networks import acceleration
from monai_probreg.networks.acceleration import unet_autocast_dtype

ROOT = Path(__file__).resolve().parents[2]
SHIPPED_WEIGHTS = ROOT / "bundle" / "models" / "model.pt"
PLAIN = {"unet_precision": "fp32", "channels_last": False, "fast_sampling": False}

pytestmark = pytest.mark.usefixtures("single_thread")


def _net(seed: int = 0, **levers) -> ProbRegNet:
    """Random weights with a mean head strong enough for displacements of a few voxels (the paper's init gives ~0)."""
    torch.manual_seed(seed)
    net = ProbRegNet(**{**PLAIN, **levers}, bidirectional=True)
    with torch.no_grad():
        net.unet.mean_head.weight.normal_(0.0, 2.0)
    return net.eval()


def _pair(shape=(32, 32, 48), seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, 1, *shape, generator=g), torch.rand(1, 1, *shape, generator=g)


def _phantom(shape, shift, scale):
    """An ellipsoid with two halves and an inner core (labels 1, 2, 3) and its image, shifted and scaled."""
    grid = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")
    centre = [n / 2 - 0.5 + s for n, s in zip(shape, shift)]
    radii = [0.3 * n * k for n, k in zip(shape, scale)]
    outer = sum(((g - c) / r) ** 2 for g, c, r in zip(grid, centre, radii)) < 1
    inner = sum(((g - c) / (0.45 * r)) ** 2 for g, c, r in zip(grid, centre, radii)) < 1
    labels = outer.long() + (outer & (grid[0] > centre[0])).long()
    labels[inner] = 3
    return (0.5 * outer.float() + 0.4 * inner.float())[None, None], labels[None, None]


@pytest.mark.parametrize("lever", ["channels_last", "fast_sampling"])
def test_float32_levers_match_the_plain_path(lever):
    moving, fixed = _pair()
    with torch.no_grad():
        plain = _net()(moving, fixed)
        fast = _net(**{lever: True})(moving, fixed)
    assert plain.displacement.abs().max() > 1.0, "displacements too small for the comparison to mean anything"
    # channels_last: the same float32 products, possibly summed in another order (measured: bit-identical here);
    # fast_sampling: sampling coordinates a few ulps apart (tests/blocks/test_warp.py), carried through seven
    # squarings and the resize (measured 7e-6 voxels, 4e-6 on intensities). 1e-4 voxels (and 1e-4 on intensities in
    # [0, 1]) leaves 10x room and is far below anything visible
    for name in ("velocity_mean", "velocity_log_var", "displacement", "inverse_displacement", "warped", "warped_fixed"):
        torch.testing.assert_close(getattr(fast, name), getattr(plain, name), atol=1e-4, rtol=1e-5, msg=name)


def test_all_float32_levers_together_and_outputs_are_plain_float32_tensors():
    moving, fixed = _pair()
    with torch.inference_mode():
        plain = _net()(moving, fixed)
        fast = _net(channels_last=True, fast_sampling=True)(moving, fixed)
    torch.testing.assert_close(fast.displacement, plain.displacement, atol=1e-4, rtol=1e-5)  # as above
    for name in ("velocity_mean", "velocity_log_var", "displacement", "warped"):
        value = getattr(fast, name)
        assert value.dtype == torch.float32 and value.is_contiguous(), name


def test_levers_never_touch_training():
    """With gradients recorded the UNet runs plain float32 (bit-identical), and the module's weights keep their layout."""
    net = _net(channels_last=True, unet_precision="bf16")
    moving, fixed = _pair()
    with torch.no_grad():
        net(moving, fixed)  # an inference call first: it must leave nothing behind
    assert all(p.is_contiguous() for p in net.parameters())
    trained = net.posterior(moving, fixed)  # grad enabled
    assert trained.mean.requires_grad and trained.mean.dtype == torch.float32
    assert torch.equal(trained.mean, net.unet(moving, fixed).mean)


def test_auto_precision_is_bf16_only_on_cpus_with_native_bf16(monkeypatch):
    monkeypatch.delenv(acceleration.PRECISION_ENV, raising=False)  # the machine decides
    monkeypatch.setattr(acceleration, "native_bf16_supported", lambda: True)
    assert unet_autocast_dtype("auto", "cpu") is torch.bfloat16
    assert unet_autocast_dtype("auto", "cuda") is None  # not measured on GPUs: float32 unless asked for
    monkeypatch.setattr(acceleration, "native_bf16_supported", lambda: False)
    assert unet_autocast_dtype("auto", "cpu") is None  # emulated bf16 would be slower
    assert unet_autocast_dtype("bf16", "cpu") is torch.bfloat16 and unet_autocast_dtype("fp32", "cpu") is None
    with pytest.raises(ValueError, match=r"one of \['auto', 'bf16', 'fp32'\]; got 'fp16'"):
        ProbRegNet(unet_precision="fp16")


@pytest.mark.parametrize("native", [True, False])
def test_the_environment_decides_what_auto_means_on_any_machine(monkeypatch, native):
    monkeypatch.setattr(acceleration, "native_bf16_supported", lambda: native)
    monkeypatch.setenv(acceleration.PRECISION_ENV, "bf16")
    assert unet_autocast_dtype("auto", "cpu") is torch.bfloat16
    assert unet_autocast_dtype("auto", "cuda") is torch.bfloat16
    assert unet_autocast_dtype("fp32", "cpu") is None  # an explicit setting still wins
    monkeypatch.setenv(acceleration.PRECISION_ENV, "fp32")
    assert unet_autocast_dtype("auto", "cpu") is None and unet_autocast_dtype("bf16", "cpu") is torch.bfloat16
    monkeypatch.setenv(acceleration.PRECISION_ENV, "auto")
    with pytest.raises(
        ValueError,
        match=r"MONAI_PROBREG_UNET_PRECISION must be one of \['bf16', 'fp32'\] or unset; "
        r"got 'auto'",
    ):
        unet_autocast_dtype("auto", "cpu")


def test_bf16_unet_moves_the_displacement_by_a_fraction_of_a_voxel_random_weights():
    moving, fixed = _pair()
    with torch.no_grad():
        plain = _net()(moving, fixed)
        bf16 = _net(unet_precision="bf16", channels_last=True, fast_sampling=True)(moving, fixed)
    # 8 mantissa bits in the convolutions (float32 accumulation): measured 0.020 voxels on fields up to 2.3 voxels
    # (rough, random weights); 0.06 voxels leaves 3x room
    assert (bf16.displacement - plain.displacement).abs().max() < 0.06
    assert bf16.velocity_mean.dtype == torch.float32  # integration and warp in float32


@pytest.mark.skipif(not SHIPPED_WEIGHTS.is_file(), reason=f"{SHIPPED_WEIGHTS} not in this checkout")
def test_bf16_keeps_dice_and_folding_on_a_synthetic_pair_with_the_shipped_weights():
    """The trained weights register a shifted, scaled phantom onto another: bf16 vs float32 Dice and |J| <= 0."""
    shape = (64, 64, 64)
    moving, moving_label = _phantom(shape, shift=(3, -2, 1), scale=(1.1, 0.9, 1.0))
    fixed, fixed_label = _phantom(shape, shift=(0, 0, 0), scale=(1, 1, 1))
    results = {}
    for precision in ("fp32", "bf16"):
        net = ProbRegNet(unet_precision=precision)
        net.load_state_dict(torch.load(SHIPPED_WEIGHTS, weights_only=True))
        with torch.inference_mode():
            disp = net.eval()(moving, fixed).displacement
        warped = warp_labels(moving_label, disp)
        results[precision] = (
            disp,
            warped,
            label_dice(warped, fixed_label),
            jacobian_stats(jacobian_determinant(disp)).num_folding,
        )
    (d32, w32, dice32, fold32), (d16, w16, dice16, fold16) = results["fp32"], results["bf16"]
    before = label_dice(moving_label, fixed_label)
    assert all(dice32[k] > before[k] + 0.05 for k in before), "the registration must do something to compare"
    # measured, 0.13.0 / 0.14.0 weights: max |diff| 0.020 / 0.019 voxels (fields up to 3.6 voxels); warped labels
    # differing at 16 / 27 of ~28 500 labelled voxels; Dice within 0.0005 / 0.0021 per label (the smallest structure
    # has 2608 voxels: 0.002 is 5 of them); 0 folds both. Bounds: 3x the displacement gap; 0.5% of the labelled
    # voxels (a nearest-neighbour label flips wherever a sample point moves across a rounding boundary); Dice 0.005
    assert (d16 - d32).abs().max() < 0.05
    assert int((w16 != w32).sum()) <= 0.005 * int((w32 > 0).sum())
    assert all(abs(dice16[k] - dice32[k]) < 0.005 for k in dice32), (dice16, dice32)
    assert fold16 == fold32


@pytest.mark.parametrize("config", ["inference.yaml", "evaluate.yaml"])
def test_bundle_configs_and_command_line_switch_the_precision(config):
    from monai_probreg.cli.main import build_parser
    from monai_probreg.fitting.stages import bundle_parser

    parser = bundle_parser(ROOT / "bundle", [config])
    assert parser.get_parsed_content("network_def").unet_precision == "auto"
    parser["unet_precision"] = "fp32"  # what --unet_precision fp32 on the monai.bundle command line does
    assert parser.get_parsed_content("network_def", lazy=False).unet_precision == "fp32"
    common = ["register", "--moving", "m.nii.gz", "--fixed", "f.nii.gz", "--out", "out"]
    assert build_parser().parse_args(common).unet_precision is None  # None: the config's setting
    assert build_parser().parse_args([*common, "--unet-precision", "bf16"]).unet_precision == "bf16"
    with pytest.raises(SystemExit):
        build_parser().parse_args([*common, "--unet-precision", "fp16"])
