"""Where the network's time goes, and what each inference lever is worth: a study behind ``ProbRegNet``'s defaults.

On the first pair of ``benchmarks/speed_compare.py`` (the same preprocessing, padded to the paper's 160 x 192 x 224),
with the paper-size network (UNet on the input grid, untrained weights):
  - each inference lever alone and together (ProbRegNet's ``unet_precision``, ``channels_last``, ``fast_sampling``),
    ``torch.no_grad`` against ``torch.inference_mode``, and ``torch.compile`` of the UNet (compile time apart);
  - K posterior samples fused in one batch against one integration at a time (``ProbRegNet.sample``'s
    ``samples_per_batch``; its default is the faster one on the device);
  - the time by stage (UNet, integration, upsampling, warp), plain and with the default levers;
  - the network's multiply-accumulates (conv hooks) and the CPU's measured peaks: a large matmul and the UNet's
    largest convolution alone, float32 and bf16, to say how close to the FLOP limit the UNet runs.
Every time is the median of ``repeats`` calls after one untimed warm-up call. The process keeps glibc's default
allocator (memory reuse is speed_compare.py's "ours, mean" against "ours, mean, memory reuse off"). It imports
speed_compare.py's pair preparation, so benchmarks/ goes on the path:

    PYTHONPATH=benchmarks python experiments/speed_levers.py --threads 2    # -> experiments/results/speed_levers.json
    PYTHONPATH=benchmarks python experiments/speed_levers.py --synthetic --size 64 64 64 --no-compile
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from common import DEFAULT_DATASET, REPO
from speed_compare import PAPER_SIZE, prepare_pairs, synthetic_pairs
from torch import nn

from monai_probreg import ProbRegNet, resize_displacement, warp_image
from monai_probreg.engines.registration import register_pair
from monai_probreg.utils.files import write_text

RESULTS = Path(__file__).resolve().parent / "results"

MATMUL_SIZE = 4096  # square matmul for the peak: large enough to run at the library's best rate
LEVER_SETTINGS = {  # row name -> ProbRegNet arguments
    "plain: float32, default layout, MONAI Warp": dict(unet_precision="fp32", channels_last=False, fast_sampling=False),
    "+ fast sampling only": dict(unet_precision="fp32", channels_last=False, fast_sampling=True),
    "+ channels-last only": dict(unet_precision="fp32", channels_last=True, fast_sampling=False),
    "+ bf16 UNet only": dict(unet_precision="bf16", channels_last=False, fast_sampling=False),
    "bf16 + channels-last": dict(unet_precision="bf16", channels_last=True, fast_sampling=False),
    # this process keeps glibc's allocator defaults: memory reuse is speed_compare.py's "ours, mean" against
    # "ours, mean, memory reuse off"
    "all model levers (memory reuse off here)": dict(unet_precision="auto", channels_last=True, fast_sampling=True),
}


def median_time(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall time of ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _net(**levers: Any) -> ProbRegNet:
    torch.manual_seed(0)
    return ProbRegNet(**levers).eval()


def conv_layers(net: ProbRegNet, moving: torch.Tensor, fixed: torch.Tensor) -> list[dict[str, Any]]:
    """Every convolution of one UNet pass (forward hooks): channels, stride, input grid, multiply-accumulates."""
    layers: list[dict[str, Any]] = []

    def hook(module: nn.Conv3d, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        layers.append(
            {
                "in": module.in_channels,
                "out": module.out_channels,
                "stride": module.stride[0],
                "input_grid": list(inputs[0].shape[2:]),
                "macs": output.numel() * module.in_channels // module.groups * math.prod(module.kernel_size),
            }
        )

    handles = [m.register_forward_hook(hook) for m in net.modules() if isinstance(m, nn.Conv3d)]
    with torch.inference_mode():
        net.unet(moving, fixed)
    for h in handles:
        h.remove()
    return layers


def hardware_peaks(layers: list[dict[str, Any]], repeats: int) -> dict[str, Any]:
    """GFLOP/s of a square matmul and of the UNet's largest convolution alone (channels-last), float32 and bf16."""
    peaks: dict[str, Any] = {}
    a = torch.randn(MATMUL_SIZE, MATMUL_SIZE)
    for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        x = a.to(dtype)
        peaks[f"matmul_{name}_gflops"] = 2 * MATMUL_SIZE**3 / median_time(lambda: x @ x, repeats) / 1e9
    big = max(layers, key=lambda layer: layer["macs"])
    layout = torch.channels_last_3d
    x = torch.randn(1, big["in"], *big["input_grid"]).contiguous(memory_format=layout)
    w = torch.randn(big["out"], big["in"], 3, 3, 3).contiguous(memory_format=layout)
    with torch.inference_mode():
        for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
            xi, wi = x.to(dtype), w.to(dtype)
            seconds = median_time(lambda: torch.nn.functional.conv3d(xi, wi, stride=big["stride"], padding=1), repeats)
            peaks[f"largest_conv_{name}_gflops"] = 2 * big["macs"] / seconds / 1e9
    peaks["largest_conv"] = (
        f"{big['in']}->{big['out']} channels, 3^3, on {'x'.join(map(str, big['input_grid']))}: "
        f"{big['macs'] / 1e9:.1f} GMAC"
    )
    return peaks


def stage_times(net: ProbRegNet, moving: torch.Tensor, fixed: torch.Tensor, repeats: int) -> dict[str, float]:
    """Each stage of one registration timed alone (and the whole), seconds."""
    size = moving.shape[2:]
    with torch.inference_mode():
        posterior = net.posterior(moving, fixed)
        small = net.integrate(posterior.mean)
        displacement = resize_displacement(small, size)
        grid = "x".join(map(str, posterior.mean.shape[2:]))
        return {
            "UNet (moving, fixed) -> posterior": median_time(lambda: net.posterior(moving, fixed), repeats),
            f"integration ({grid}, {net.integrate.num_steps} squarings)": median_time(
                lambda: net.integrate(posterior.mean), repeats
            ),
            "upsampling of the displacement": median_time(lambda: resize_displacement(small, size), repeats),
            "warp of the moving image": median_time(
                lambda: warp_image(moving, displacement, fast=net.fast_sampling), repeats
            ),
            "whole registration": median_time(lambda: register_pair(net, moving, fixed), repeats),
        }


def sample_fusion(moving: torch.Tensor, fixed: torch.Tensor, k: int, repeats: int) -> dict[str, float]:
    """K samples through ``ProbRegNet.sample``: one batch of K fields against one integration at a time."""
    net = _net()
    with torch.inference_mode():
        return {
            "fused_s": median_time(lambda: net.sample(moving, fixed, k, samples_per_batch=k), repeats),
            "one_by_one_s": median_time(lambda: net.sample(moving, fixed, k, samples_per_batch=1), repeats),
            "mean_only_s": median_time(lambda: register_pair(net, moving, fixed), repeats),
        }


def compiled_unet(moving: torch.Tensor, fixed: torch.Tensor, repeats: int) -> dict[str, Any]:
    """``torch.compile`` (inductor, weight freezing) of the UNet with the default levers: compile time and speed."""
    import torch._inductor.config as inductor_config

    inductor_config.freezing = True
    net = _net()
    eager = median_time(lambda: net.posterior(moving, fixed), repeats)
    # channels-last weights on the module itself: the per-call converted copies of the eager path would be new
    # constants for the frozen graph at every call (a recompilation each time)
    net = _net(channels_last=False)
    net.unet.to(memory_format=torch.channels_last_3d)
    net.unet = torch.compile(net.unet)
    with torch.inference_mode():
        start = time.perf_counter()
        net.posterior(moving, fixed)
        compile_s = time.perf_counter() - start
        compiled = median_time(lambda: net.posterior(moving, fixed), repeats)
    return {"unet_eager_s": eager, "unet_compiled_s": compiled, "compile_s": compile_s}


def run_levers(pair: dict, args: argparse.Namespace) -> dict[str, Any]:
    moving, fixed = pair["moving"], pair["fixed"]
    result: dict[str, Any] = {"size": list(moving.shape[2:]), "levers": {}}
    for name, settings in LEVER_SETTINGS.items():
        net = _net(**settings)
        result["levers"][name] = median_time(lambda: register_pair(net, moving, fixed), args.repeats)
    net = _net()
    with torch.no_grad():
        result["levers"]["all levers, torch.no_grad instead of inference_mode"] = median_time(
            lambda: net(moving, fixed), args.repeats
        )
    result["stages"] = {
        "plain": stage_times(
            _net(**LEVER_SETTINGS["plain: float32, default layout, MONAI Warp"]), moving, fixed, args.repeats
        ),
        "default": stage_times(net, moving, fixed, args.repeats),
    }
    result["samples"] = {"k": args.samples, **sample_fusion(moving, fixed, args.samples, args.repeats)}
    layers = conv_layers(net, moving, fixed)
    result["unet_macs"] = sum(layer["macs"] for layer in layers)
    result["peaks"] = hardware_peaks(layers, args.repeats)
    if not args.no_compile:
        result["compile"] = compiled_unet(moving, fixed, args.repeats)
    return result


def levers_markdown(levers: dict[str, Any]) -> str:
    """The levers table and the stages table of one :func:`run_levers` result."""
    plain = levers["levers"]["plain: float32, default layout, MONAI Warp"]
    lines = ["| setting | s per pair | × faster than plain |", "|---|---|---|"]
    lines += [f"| {name} | {t:.3f} | {plain / t:.2f} |" for name, t in levers["levers"].items()]
    stages = levers["stages"]
    lines += ["", "| stage | plain (s) | default levers (s) |", "|---|---|---|"]
    lines += [
        f"| {a} | {stages['plain'][a]:.3f} | {stages['default'][b]:.3f} |"
        for a, b in zip(stages["plain"], stages["default"])
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET, help="atlas/, images/, labels/")
    ap.add_argument("--subject", default=None, help="the pair's moving subject (default: the first of val_ids)")
    ap.add_argument("--size", type=int, nargs=3, default=PAPER_SIZE, help="pad/crop the pair to this grid")
    ap.add_argument("--threads", type=int, default=1, help="CPU threads")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each measurement")
    ap.add_argument("--samples", type=int, default=10, help="K of the fused-samples measurement")
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile measurement")
    ap.add_argument("--synthetic", action="store_true", help="a random pair, no dataset")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="where speed_levers.json goes")
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    args = ap.parse_args(argv)
    if args.synthetic:
        pair = synthetic_pairs(1, args.size)[0]
    elif not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}", flush=True)
        return 0
    else:
        subjects = None if args.subject is None else [args.subject]
        pair = prepare_pairs(args.dataset_dir.resolve(), subjects, 1, args.size, args.bundle_root.resolve())[0][0]
    torch.set_num_threads(args.threads)
    result = run_levers(pair, args)
    result.update(pair=pair["id"], threads=torch.get_num_threads(), markdown=levers_markdown(result))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = write_text(args.out_dir / "speed_levers.json", json.dumps(result, indent=2) + "\n")
    print(f"{result['markdown']}\n\nwrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
