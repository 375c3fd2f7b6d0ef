"""The measurements of ``benchmarks/speed_compare.py``, each run in a process of its own.

One process per method, so that its peak resident memory is its own and not the maximum of everything measured
before it. Within the process, the peak is reset (``/proc/self/clear_refs``) before each pair's timed runs and read
(``VmHWM``) right after them, so the scoring that follows (Dice, Jacobians, the float32 check) is not counted; the
whole process's peak is kept as ``process_peak_rss_mb``. Started by speed_compare.py as

    python benchmarks/speed_workers.py METHOD --pairs PAIRS.pt --out RESULT.json --threads N --repeats R

PAIRS.pt holds the prepared pairs (moving, fixed, labels; already padded/cropped to the benchmark size); RESULT.json
gets the wall times per pair (warm-up excluded), the scores of the trained methods and the memory figures.
Methods: see :data:`METHODS`.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from common import ants_register, bundle_parser

METHODS = ("ours_mean", "ours_mean_no_reuse", "ours_samples", "ours_trained", "voxelmorph", "ants")
REUSES_MEMORY = ("ours_mean", "ours_samples", "ours_trained")  # as monai-probreg and the bundle run them
KIB_PER_MB = 1024  # ru_maxrss is in KiB on Linux


def rss_mb() -> float:
    """Current resident set size of this process, MB (VmRSS)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / KIB_PER_MB
    return float("nan")


_peaks_before_resets_mb = [0.0]  # the high-water marks that reset_peak_rss cleared


def peak_rss_mb() -> float:
    """Peak resident set size since the last :func:`reset_peak_rss` (VmHWM), MB; the process's peak without it."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / KIB_PER_MB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / KIB_PER_MB


def process_peak_rss_mb() -> float:
    """Peak resident set size of this process since it started, MB (ru_maxrss alone would miss what a reset
    cleared: it reads the same high-water mark)."""
    return max(peak_rss_mb(), *_peaks_before_resets_mb)


def reset_peak_rss() -> bool:
    """Reset the kernel's high-water mark of this process's resident set (Linux >= 4.0); False where it can't."""
    before = peak_rss_mb()
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    _peaks_before_resets_mb.append(before)
    return True


class PeakWindows:
    """The largest peak resident set over windows opened by :meth:`start` and closed by :meth:`stop`."""

    def __init__(self) -> None:
        self.peak_mb = 0.0
        self.resets = True

    def start(self) -> None:
        self.resets = reset_peak_rss() and self.resets

    def stop(self) -> None:
        self.peak_mb = max(self.peak_mb, peak_rss_mb())

    def record(self, result: dict[str, Any]) -> None:
        result["peak_rss_mb"] = self.peak_mb
        result["peak_rss_scope"] = (
            "timed runs only" if self.resets else "whole process (the peak could not be reset here)"
        )


def timed(fn: Callable[[], Any], repeats: int) -> tuple[list[float], Any]:
    """Wall times of ``repeats`` calls of ``fn`` and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return times, result


def _scores(displacement: torch.Tensor, pair: dict) -> dict[str, Any]:
    from monai_probreg.metrics.scores import score_pair

    s = score_pair(displacement, pair["moving_label"], pair["fixed_label"])
    return {"mean_dice": s.mean_dice, "num_folding": s.num_folding, "std_log_jacobian": s.std_log_jacobian}


def _network(
    kind: str, size: list[int], native: list[int], bundle_root: Path, overrides: dict[str, Any]
) -> torch.nn.Module:
    """``paper``: an untrained ProbRegNet whose UNet runs on the input grid (the paper's setting); ``trained``: the
    configs' network (evaluate.yaml, with ``overrides``) and weights, its network grid scaled with the input."""
    from monai_probreg import ProbRegNet
    from monai_probreg.weights.loading import load_weights

    if kind == "paper":
        torch.manual_seed(0)
        return ProbRegNet().eval()
    parser = bundle_parser(bundle_root, ["evaluate.yaml"], overrides)
    trained_on, divisor = parser["network_size"], parser["divisor"]  # network grid for the native grid
    network = load_weights(parser.get_parsed_content("network_def"), parser.get_parsed_content("model_file"))
    # Loaded with the trained grid (the settings check next to the weights passes), then the grid is scaled with the
    # padded input: the same voxel size as in training, rounded to a multiple of the network's divisor. Only this
    # benchmark does that (its input is the native grid padded to the paper's size); the UNet is convolutional.
    network.network_size = tuple(
        max(divisor, round(s * t / n / divisor) * divisor) for s, t, n in zip(size, trained_on, native)
    )
    return network


def run_torch_method(method: str, pairs: list[dict], meta: dict, args: argparse.Namespace) -> dict[str, Any]:
    """Ours (mean, K samples, trained) or MONAI's VoxelMorph: warm-up on the first pair, then ``repeats`` per pair."""
    from monai_probreg.engines.registration import register_pair

    result_reuse = False
    if method == "voxelmorph":
        import monai

        torch.manual_seed(0)
        net = monai.networks.nets.VoxelMorph().eval()
        call = lambda p: net(p["moving"], p["fixed"])  # noqa: E731 - (warped, ddf), full-resolution integration
    else:
        if method in REUSES_MEMORY:
            from monai_probreg.utils.memory import reuse_freed_memory

            result_reuse = reuse_freed_memory()
        net = _network(
            "trained" if method == "ours_trained" else "paper",
            meta["size"],
            meta["native"],
            Path(meta["bundle_root"]),
            meta["overrides"],
        )
        if method == "ours_samples":
            call = lambda p: net.sample(p["moving"], p["fixed"], args.samples)  # noqa: E731
        else:
            call = lambda p: register_pair(net, p["moving"], p["fixed"])  # noqa: E731
    result: dict[str, Any] = {"rss_before_mb": rss_mb(), "times_s": {}, "scores": {}, "memory_reuse": result_reuse}
    window = PeakWindows()
    displacements = {}
    with torch.inference_mode():
        call(pairs[0])  # warm-up: first-call allocations, oneDNN primitive creation
        for pair in pairs:  # all timing first: with memory reuse, what scoring frees would stay in the process
            window.start()
            times, out = timed(lambda: call(pair), args.repeats)
            window.stop()
            result["times_s"][pair["id"]] = times
            if method == "ours_trained":
                displacements[pair["id"]] = out.displacement
            del out
        window.record(result)
        for pair in pairs:
            if method != "ours_trained" or pair.get("moving_label") is None:
                continue
            displacement = displacements[pair["id"]]
            result["scores"][pair["id"]] = _scores(displacement, pair)
            # the bf16 check on real pairs: the same model in float32, untimed
            unet_precision, net.unet_precision = net.unet_precision, "fp32"
            reference = register_pair(net, pair["moving"], pair["fixed"]).displacement
            net.unet_precision = unet_precision
            result["scores"][pair["id"]]["fp32"] = _scores(reference, pair)
            result["scores"][pair["id"]]["max_abs_diff_vs_fp32_voxels"] = float((displacement - reference).abs().max())
    if method == "ours_trained":
        result["network_size"] = list(net.network_size)
        result["unet_precision"] = net.unet_precision
    return result


def run_ants(pairs: list[dict], meta: dict, args: argparse.Namespace) -> dict[str, Any]:
    """ANTs SyN (antspyx defaults) as benchmarks/accuracy_table.py runs it; warm-up on a 4x smaller pair."""
    import torch.nn.functional as F

    from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
    from monai_probreg.metrics.scores import score_pair

    warm = {
        k: F.interpolate(pairs[0][k].float(), scale_factor=1 / meta["ants_warmup_shrink"], mode="nearest")
        for k in ("moving", "fixed", "moving_label")
    }
    result: dict[str, Any] = {"rss_before_mb": rss_mb(), "times_s": {}, "scores": {}}
    window = PeakWindows()
    ants_register(warm["moving"], warm["fixed"], warm["moving_label"])  # loads ITK/ANTs code, not timed
    for pair in pairs:
        times = []
        window.start()
        for _ in range(args.repeats):
            warped_label, displacement, runtime = ants_register(pair["moving"], pair["fixed"], pair["moving_label"])
            times.append(runtime)
        window.stop()
        result["times_s"][pair["id"]] = times
        if pair.get("fixed_label") is not None:
            s = score_pair(None, warped_label, pair["fixed_label"])
            stats = jacobian_stats(jacobian_determinant(displacement))
            result["scores"][pair["id"]] = {
                "mean_dice": s.mean_dice,
                "num_folding": stats.num_folding,
                "std_log_jacobian": stats.std_log_jacobian,
            }
    import ants

    window.record(result)
    result["antspyx"] = getattr(ants, "__version__", "unknown")
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("method", choices=METHODS)
    ap.add_argument("--pairs", type=Path, required=True, help="the prepared pairs (torch.save by speed_compare.py)")
    ap.add_argument("--out", type=Path, required=True, help="where to write the result JSON")
    ap.add_argument("--threads", type=int, required=True)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=10)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    data = torch.load(args.pairs, weights_only=True)
    meta, pairs = data["meta"], data["pairs"]
    if args.method == "ants":
        result = run_ants(pairs, meta, args)
    else:
        result = run_torch_method(args.method, pairs, meta, args)
    result.update(method=args.method, threads=torch.get_num_threads(), process_peak_rss_mb=process_peak_rss_mb())
    all_times = [t for times in result.get("times_s", {}).values() for t in times]
    if all_times:
        result["median_s"] = statistics.median(all_times)
    tmp = Path(tempfile.mkstemp(dir=args.out.parent, suffix=".tmp")[1])
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
