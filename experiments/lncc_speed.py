"""The refinement's image term on a CPU: MONAI's LNCC against ``BoxLNCCLoss`` (the same loss, window sums by pooling).

Both losses get the same random images; each is timed forward and backward (the gradient with respect to the
warped image, as in a refinement step), the median of ``--repeats`` runs after a warm-up, and their values and
gradients are compared. Sizes: the shipped network's grid (80x96x80, ``refine_image_grid_factor: 1``), twice finer
(160x192x160, ``refine_image_grid_factor: 2``) and two between, where the two cross (``POOLED_FROM_VOXELS``: the loss
pools from there on; here it is forced to pool at every size). The ratio is what to read: both run in the same
process, alternately.

    python experiments/lncc_speed.py --threads 2   # -> experiments/results/lncc_speed.json

Prints one table and writes ``OUT_DIR/lncc_speed.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch
from monai.losses import LocalNormalizedCrossCorrelationLoss

from monai_probreg.losses.lncc import BoxLNCCLoss
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import library_versions

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
SIZES = {
    "network grid": (80, 96, 80),
    "1.2x": (96, 112, 96),
    "1.5x": (120, 144, 120),
    "twice finer": (160, 192, 160),
}
KERNEL_SIZE = 9  # the configs' refine_lncc_kernel_size


def time_loss(loss: torch.nn.Module, pred: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor]:
    """(forward + backward s, gradient) of one evaluation."""
    pred = pred.detach().requires_grad_(True)
    start = time.perf_counter()
    loss(pred, target).backward()
    return time.perf_counter() - start, pred.grad


def measure(size: tuple[int, ...], repeats: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    target = torch.rand((1, 1, *size), generator=generator)
    pred = 0.6 * target + 0.4 * torch.rand((1, 1, *size), generator=generator)
    losses = {
        "MONAI": LocalNormalizedCrossCorrelationLoss(3, KERNEL_SIZE),
        "pooled": BoxLNCCLoss(3, KERNEL_SIZE, pooled_from_voxels=0),
    }
    times: dict[str, list[float]] = {name: [] for name in losses}
    gradients = {}
    for run in range(repeats + 1):  # run 0 warms up
        for name, loss in losses.items():
            seconds, gradients[name] = time_loss(loss, pred, target)
            if run:
                times[name].append(seconds)
    values = {name: float(loss(pred, target)) for name, loss in losses.items()}
    median = {name: statistics.median(t) for name, t in times.items()}
    return {
        "size": list(size),
        "seconds": median,
        "speedup": median["MONAI"] / median["pooled"],
        "value_difference": abs(values["MONAI"] - values["pooled"]),
        "gradient_max_difference": float((gradients["MONAI"] - gradients["pooled"]).abs().max()),
        "gradient_max": float(gradients["MONAI"].abs().max()),
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit(f"--repeats must be >= 1; got {args.repeats}")
    torch.set_num_threads(args.threads)
    rows = {name: measure(SIZES[name], args.repeats) for name in args.sizes}
    lines = [
        "| grid | MONAI s (forward + backward) | pooled s | speed-up | |value difference| | max |gradient difference| |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} {'x'.join(map(str, r['size']))} | {r['seconds']['MONAI']:.3f} | {r['seconds']['pooled']:.3f} | "
            f"{r['speedup']:.1f}x | {r['value_difference']:.1e} | {r['gradient_max_difference']:.1e} "
            f"(of {r['gradient_max']:.1e}) |"
        )
    table = "\n".join(lines)
    print(table, flush=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    result = {"rows": rows, "threads": args.threads, "repeats": args.repeats, "kernel_size": KERNEL_SIZE}
    result |= {"versions": library_versions(), "markdown": table}
    path = write_text(args.out_dir / "lncc_speed.json", json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
