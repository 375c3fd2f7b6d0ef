"""Data-parallel training scaling: the bundle's multi_gpu_train.yaml under torchrun, 1 process against N (gloo on CPU).

Trains train.yaml + multi_gpu_train.yaml for a few epochs on the same ``--train-ids`` of a dataset folder, once with
1 process and once with ``--nproc`` processes (``--threads`` CPU threads each, no validation), and reads the trainer's
epoch times from the log (ignite's "Epoch[e] Complete. Time taken"); the first epoch (data caching, allocations) is
left out. One epoch covers the training subjects once in both runs (each rank trains on its own shard), so
speed-up = t(1) / t(N) and scaling efficiency = speed-up / N.

It imports the benchmarks' shared paths, so benchmarks/ goes on the path:

    PYTHONPATH=benchmarks python experiments/ddp_scaling.py     # table + experiments/results/ddp_scaling.json
    PYTHONPATH=benchmarks python experiments/ddp_scaling.py --nproc 2 --network-size 64 80 64 --epochs 3
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from common import DEFAULT_DATASET, REPO

EPOCH_LINE = re.compile(r"SupervisedTrainer - INFO - Epoch\[(\d+)\] Complete\. Time taken: (\d+):(\d+):([\d.]+)")
WARMUP_EPOCHS = 1  # epochs left out of the timing
RUN_TIMEOUT_S = 1800
RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script


def epoch_times(log: str) -> dict[int, float]:
    """Trainer epoch -> seconds (the slowest rank when several ranks log the same epoch)."""
    times: dict[int, float] = {}
    for epoch, h, m, s in EPOCH_LINE.findall(log):
        seconds = int(h) * 3600 + int(m) * 60 + float(s)
        times[int(epoch)] = max(times.get(int(epoch), 0.0), seconds)
    return times


def train(nproc: int, args: argparse.Namespace, work: Path) -> dict[int, float]:
    configs = [str(REPO / "bundle" / "configs" / n) for n in ("train.yaml", "multi_gpu_train.yaml")]
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc_per_node={nproc}",
        "-m",
        "monai.bundle",
        "run",
        "--config_file",
        "[" + ",".join(f"'{c}'" for c in configs) + "]",
        "--bundle_root",
        str(REPO / "bundle"),
        "--dataset_dir",
        str(args.dataset_dir),
        "--ckpt_dir",
        str(work / f"ckpt{nproc}"),
        "--output_dir",
        str(work / f"runs{nproc}"),
        "--network_size",
        str(list(args.network_size)),
        "--train_ids",
        str(list(args.train_ids)),
        "--val_ids",
        str([args.val_id]),
        "--val_interval",
        str(args.epochs + 1),
        "--max_epochs",
        str(args.epochs),
        "--num_workers",
        "0",
        "--resume",
        "false",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "CUDA_VISIBLE_DEVICES": ""}
    print(f"training with {nproc} process(es) x {args.threads} thread(s) ...", flush=True)
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
    log = done.stdout + done.stderr
    if done.returncode != 0:
        raise SystemExit(f"training with {nproc} processes failed:\n{log[-3000:]}")
    return epoch_times(log)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--train-ids", nargs="+", default=["S12", "S13", "S15", "S17"], help="an even number is fairest")
    ap.add_argument("--val-id", default="S11", help="required by train.yaml; validation is not run")
    ap.add_argument("--network-size", type=int, nargs=3, default=[64, 80, 64])
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--nproc", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="CPU threads per process")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir.resolve()}", flush=True)
        return 0
    with tempfile.TemporaryDirectory(prefix="ddp_scaling_") as tmp:
        runs = {n: train(n, args, Path(tmp)) for n in (1, args.nproc)}
    timed = {n: statistics.median([t for e, t in times.items() if e > WARMUP_EPOCHS]) for n, times in runs.items()}
    speedup = timed[1] / timed[args.nproc]
    result = {
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "epoch_times_s": {str(n): runs[n] for n in runs},
        "median_epoch_s": {str(n): timed[n] for n in timed},
        "speedup": speedup,
        "efficiency": speedup / args.nproc,
    }
    table = (
        "| processes x threads | s per epoch (median, epochs > 1) | speed-up | efficiency |\n|---|---|---|---|\n"
        + "\n".join(
            f"| {n} x {args.threads} | {timed[n]:.2f} | {timed[1] / timed[n]:.2f} | {timed[1] / timed[n] / n:.0%} |"
            for n in (1, args.nproc)
        )
    )
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = args.out_dir / "ddp_scaling.json"
    path.write_text(json.dumps({**result, "markdown": table}, indent=2) + "\n")
    print(f"\n{table}\n\nwrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
