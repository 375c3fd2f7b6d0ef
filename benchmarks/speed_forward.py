"""Forward-time benchmark: our mean registration vs MONAI's VoxelMorph, side by side in one run.

Measures, on random inputs of the paper's size (160 x 192 x 224, batch 1, float32, CPU), the wall time of
one registration (network + integration + upsampling + warp; no sampling) for
  - ours: ``ProbRegNet`` in eval mode (mean velocity, half-resolution velocity head), and
  - MONAI: ``monai.networks.nets.VoxelMorph()`` with its defaults (full-resolution integration),
under ``torch.inference_mode``, with the machine's threads. Warm-up runs are excluded; the median of
``--repeats`` runs is reported. Weights don't matter for speed (untrained).

    python benchmarks/speed_forward.py                 # table + benchmarks/results/speed_forward.json
    python benchmarks/speed_forward.py --size 80 96 112 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import monai
import torch

from monai_probreg import ProbRegNet, resize_displacement, warp_image


def time_call(fn: Callable[[], object], warmup: int, repeats: int) -> list[float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, nargs=3, default=[160, 192, 224], help="spatial size (multiple of 16)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per method (median reported)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs first")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "speed_forward.json")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    moving = torch.rand(1, 1, *args.size)
    fixed = torch.rand(1, 1, *args.size)
    methods = {
        "ours (ProbRegNet, mean)": ProbRegNet().eval(),
        "MONAI VoxelMorph()": monai.networks.nets.VoxelMorph().eval(),
    }
    rows = []
    with torch.inference_mode():
        for name, net in methods.items():
            times = time_call(lambda: net(moving, fixed), args.warmup, args.repeats)
            rows.append({"method": name, "median_s": statistics.median(times), "runs_s": times})
            print(f"  {name}: {', '.join(f'{t:.2f}' for t in times)} s", flush=True)
        ours = methods["ours (ProbRegNet, mean)"]
        posterior = ours.posterior(moving, fixed)
        velocity_ddf = ours.integrate(posterior.mean)
        ddf = resize_displacement(velocity_ddf, args.size)
        stage_fns = {
            "UNet (moving, fixed) -> posterior": lambda: ours.posterior(moving, fixed),
            f"integration ({'x'.join(map(str, posterior.mean.shape[2:]))}, {ours.integrate.num_steps} steps)":
                lambda: ours.integrate(posterior.mean),
            "upsampling of the displacement": lambda: resize_displacement(velocity_ddf, args.size),
            "warp of the moving image": lambda: warp_image(moving, ddf),
        }
        stages = [{"stage": name, "median_s": statistics.median(time_call(fn, args.warmup, args.repeats))}
                  for name, fn in stage_fns.items()]
    base = rows[0]["median_s"]
    for row in rows:
        row["ratio_to_ours"] = row["median_s"] / base
    result = {
        "size": args.size,
        "threads": torch.get_num_threads(),
        "warmup": args.warmup,
        "repeats": args.repeats,
        "torch": torch.__version__,
        "monai": monai.__version__,
        "cpu": platform.processor() or platform.machine(),
        "rows": rows,
        "stages_ours": stages,
    }
    print(f"\nForward time at {'x'.join(map(str, args.size))}, batch 1, {result['threads']} threads, "
          f"median of {args.repeats} (warm-up {args.warmup}):")
    print("| method | median time (s) | x ours |\n|---|---|---|")
    for row in rows:
        print(f"| {row['method']} | {row['median_s']:.2f} | {row['ratio_to_ours']:.1f} |")
    print("\nOurs by stage (each timed alone, median):\n| stage | median time (s) |\n|---|---|")
    for stage in stages:
        print(f"| {stage['stage']} | {stage['median_s']:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
