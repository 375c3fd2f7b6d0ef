"""How long the test-time refinement takes per LPBA40 pair, settings side by side in one process.

Each variant refines the same network output of the same pairs (validation subjects onto each other, images as the
command feeds them: the percentile scale of ``spatial.intensity``, the aligned 160 x 192 x 160 grid), one untimed
warm-up, then every variant once per pair in turn (so a slow moment of the machine hits them all), ``--rounds`` times
over the pairs, with the median of every pair's runs reported (the Dice of the first round):

- ``0.21.0, MONAI path``: bundle 0.21.0's steps (:data:`FORMER`: 10, all on the finer grid) with the network's
  ``fast_sampling=False``: MONAI's integration and ``Warp``, and the image term as MONAI computes it
  (``BoxLNCCLoss`` differentiated by autograd over the whole grid);
- ``0.21.0 steps``: the same steps through the refinement as it is (the hand-written LNCC in the fixed image's box);
- ``shipped``: the bundle's refinement (``inference.yaml``: coarse to fine);
- any ``--variants name=field:value,...`` (``RefinementSettings`` fields replaced in the shipped ones).

The image term's levers alone, on the first pair's images and a smooth random displacement (forward and backward,
median of ``REPEATS``): MONAI's LNCC by autograd over the whole grid, :class:`FixedImageLNCC` over the whole grid,
and over the box around the fixed image's nonzero voxels (what the refinement runs). The integration's squarings on
the velocity grid (forward and backward, median of ``SQUARING_REPEATS``), ``grid_sample`` as one piece (one thread)
against split over the threads (the shipped path, :data:`~monai_probreg.blocks.warp.MIN_POINTS_PER_THREAD`).

Also the mean Dice over the 56 structures after each variant (labels warped by its displacement, nearest
neighbour), to see what a faster variant costs. ``--profile`` prints torch's profiler table of one shipped refinement
(where the time goes).

    python benchmarks/refinement_speed.py --threads 2      # table + benchmarks/results/refinement_speed.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from common import DEFAULT_DATASET, DEFAULT_OUT, parse_variant, write_report

from monai_probreg.blocks import warp
from monai_probreg.blocks.warp import warp_box, warp_image, warp_labels
from monai_probreg.engines.refinement import refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.losses.lncc import BoxLNCCLoss, FixedImageLNCC, support_box
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.registration.model import load_model
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.volume_io import read_image, read_label
from monai_probreg.utils.memory import reuse_freed_memory

REPEATS = 3
SQUARING_REPEATS = 10
PAIRS = ("S11:S14", "S16:S21", "S28:S29")  # moving:fixed, validation subjects (train.yaml's val_ids)
AUTOGRAD = "0.21.0 steps, MONAI path (fast_sampling=False)"
FORMER_STEPS = "0.21.0 steps"
FORMER = {"num_iterations": 10, "coarse_iterations": 0}  # bundle 0.21.0's refinement: 10 steps, all on the finer grid
SHIPPED = "shipped"


def load_pair(dataset: Path, pair: str) -> tuple[torch.Tensor, ...]:
    """(moving, fixed, moving labels, fixed labels) (1, 1, *S): images on the command's intensity scale."""
    moving, fixed = pair.split(":")
    images = [normalise_intensity(read_image(dataset / "images" / f"{s}.nii.gz").array) for s in (moving, fixed)]
    labels = [read_label(dataset / "labels" / f"{s}.nii.gz").array.astype(np.int64) for s in (moving, fixed)]
    return tuple(torch.from_numpy(np.ascontiguousarray(a))[None, None] for a in (*images, *labels))


def image_term_levers(moving: torch.Tensor, fixed: torch.Tensor, kernel_size: int) -> dict[str, float]:
    """Seconds (median of REPEATS) of one forward and backward of the image term on the images' grid, per lever."""
    generator = torch.Generator().manual_seed(0)
    coarse = torch.randn((1, moving.ndim - 2, *[max(n // 8, 2) for n in moving.shape[2:]]), generator=generator)
    displacement = F.interpolate(2.0 * coarse, size=moving.shape[2:], mode="trilinear", align_corners=True)
    region = support_box(fixed, margin=2 * (kernel_size // 2))
    monai_lncc = BoxLNCCLoss(moving.ndim - 2, kernel_size)
    whole, boxed = FixedImageLNCC(fixed, kernel_size), FixedImageLNCC(fixed, kernel_size, region=region)
    levers = {
        "MONAI's LNCC by autograd, whole grid": lambda u: monai_lncc(warp_image(moving, u), fixed),
        "FixedImageLNCC, whole grid": lambda u: whole(warp_image(moving, u)),
        "FixedImageLNCC, fixed image's box": lambda u: boxed(warp_box(moving, boxed.crop(u), region[0])),
    }
    seconds = {}
    for name, term in levers.items():
        spans = []
        for _ in range(REPEATS + 1):  # the first: warm-up
            u = displacement.clone().requires_grad_(True)
            start = time.perf_counter()
            term(u).backward()
            spans.append(time.perf_counter() - start)
        seconds[name] = statistics.median(spans[1:])
    return seconds


def squaring_levers(network: torch.nn.Module, velocity: torch.Tensor) -> dict[str, float]:
    """Seconds (median of SQUARING_REPEATS) of the integration of ``velocity`` (the network's, on its velocity grid)
    forward and backward, as each refinement step runs it, with ``grid_sample`` run as one piece (one thread) and
    split over the threads (:func:`~monai_probreg.blocks.warp.split_grid_sample`, the shipped path)."""
    seconds = {}
    for name, minimum in (("one piece (one thread)", 2**62), ("split over the threads", warp.MIN_POINTS_PER_THREAD)):
        shipped, warp.MIN_POINTS_PER_THREAD = warp.MIN_POINTS_PER_THREAD, minimum
        try:
            spans = []
            for _ in range(SQUARING_REPEATS + 1):  # the first: warm-up
                v = velocity.detach().clone().requires_grad_(True)
                start = time.perf_counter()
                network.velocity_to_displacement(v, tuple(v.shape[2:])).square().sum().backward()
                spans.append(time.perf_counter() - start)
        finally:
            warp.MIN_POINTS_PER_THREAD = shipped
        seconds[name] = statistics.median(spans[1:])
    return seconds


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), help="moving:fixed subject ids")
    ap.add_argument("--variants", nargs="*", default=[], help="name=field:value,... (RefinementSettings fields)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--profile", action="store_true", help="print the profiler table of one shipped refinement")
    ap.add_argument("--rounds", type=int, default=1, help="times over the pairs (the median of all runs is reported)")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    ap.add_argument(
        "--no-memory-reuse",
        action="store_true",
        help="glibc's allocator as it comes (the command and the bundle keep freed memory for reuse by default)",
    )
    args = ap.parse_args(argv)
    if not (args.dataset_dir / "images").is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}", flush=True)
        return 0
    torch.set_num_threads(args.threads)
    if not args.no_memory_reuse:  # as monai-probreg and inference.yaml run (reuse_cpu_memory: true)
        reuse_freed_memory()
    model = load_model()
    network = model.network
    former = model.refinement.with_fields(**FORMER)
    settings = {AUTOGRAD: former, FORMER_STEPS: former, SHIPPED: model.refinement}
    settings.update(
        {name: model.refinement.with_fields(**fields) for name, fields in map(parse_variant, args.variants)}
    )
    times: dict[str, list[float]] = {name: [] for name in settings}
    dice: dict[str, list[float]] = {name: [] for name in settings}
    for n, pair in enumerate(args.pairs):
        moving, fixed, moving_label, fixed_label = load_pair(args.dataset_dir, pair)
        ids = [int(v) for v in torch.unique(fixed_label) if v > 0]
        output = register_pair(network, moving, fixed)
        if n == 0:  # warm-up: first calls allocate and pick kernels; the image term's levers on this pair
            levers = image_term_levers(moving, fixed, model.refinement.lncc_kernel_size)
            squaring = squaring_levers(network, output.velocity_mean)
            refine_registration(network, moving, fixed, output, model.refinement)
            if args.profile:
                from torch.profiler import ProfilerActivity, profile

                with profile(activities=[ProfilerActivity.CPU]) as prof:
                    refine_registration(network, moving, fixed, output, model.refinement)
                print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15), flush=True)
        for round_ in range(args.rounds):
            for name, variant in settings.items():
                network.fast_sampling = name != AUTOGRAD  # MONAI's warp and autograd LNCC over the whole grid
                start = time.perf_counter()
                refined = refine_registration(network, moving, fixed, output, variant)
                times[name].append(time.perf_counter() - start)
                if round_ == 0:
                    warped = warp_labels(moving_label, refined.displacement)
                    dice[name].append(mean_dice(label_dice(warped, fixed_label, ids)))
                print(f"{pair} {name}: {times[name][-1]:.2f} s, Dice {dice[name][-1]:.4f}", flush=True)
            network.fast_sampling = True
    base = statistics.median(times[AUTOGRAD])
    rows = []
    lines = ["| refinement | s per pair (median) | x faster than the first row | mean Dice |", "|---|---|---|---|"]
    for name, variant in settings.items():
        median = statistics.median(times[name])
        row = {"variant": name, "s_per_pair": median, "speedup": base / median, "dice": float(np.mean(dice[name]))}
        row["settings"] = variant.as_dict()
        rows.append(row)
        lines.append(f"| {name} | {median:.2f} | {base / median:.1f} | {row['dice']:.4f} |")
    lines += ["", "| image term (forward + backward, 1 mm grid) | s | x faster |", "|---|---|---|"]
    first = next(iter(levers.values()))
    lines += [f"| {name} | {sec:.3f} | {first / sec:.1f} |" for name, sec in levers.items()]
    lines += ["", "| the integration's squarings (forward + backward, velocity grid) | s | x faster |", "|---|---|---|"]
    first = next(iter(squaring.values()))
    lines += [f"| {name} | {sec:.4f} | {first / sec:.1f} |" for name, sec in squaring.items()]
    result = {
        "rows": rows,
        "image_term_s": levers,
        "squaring_s": squaring,
        "pairs": args.pairs,
        "threads": args.threads,
        "memory_reuse": not args.no_memory_reuse,
        "rounds": args.rounds,
        "seconds": times,
    }
    write_report(args.out_dir, "refinement_speed", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
