"""Peak memory of the command on a whole-head 256^3, 1 mm pair: ``register`` once, and ``register-batch`` over 1 and 3
scans (its peak must not grow with the number of scans).

The pair is made from two whole-head label maps no training run saw, SynthSeg's ``training_seg_01`` (moving) and
``training_seg_02`` (fixed) from ``--label-maps`` (``git clone https://github.com/BBillot/SynthSeg``:
``SynthSeg/data/training_label_maps``, 256^3 at 1 mm), each rendered as a T1-like head on its own grid
(:func:`monai_probreg.cli.synth_space.render_head`, skull and scalp kept) and registered with both label maps, default
options (refinement on, as shipped). Each row is one fresh process of the command, its peak resident memory read from
the kernel when it exits (``os.wait4``: the "Maximum resident set size" of ``/usr/bin/time -v``). The batch rows give
the same scan under 1 and 3 names. Target: 2.5 GB for one ``register``.

    python benchmarks/peak_memory.py --label-maps SynthSeg/data/training_label_maps --threads 1

Prints one table and writes ``OUT_DIR/peak_memory.json``; without the label maps it prints "skipped: ..." and exits 0.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from common import DEFAULT_OUT, write_report

MAPS = ("training_seg_01", "training_seg_02")  # moving, fixed
TARGET_GB = 2.5  # one register on a 256^3 pair (the target)
BATCH_SIZES = (1, 3)


def peak_rss(cmd: Sequence[str]) -> tuple[float, float]:
    """Run ``cmd`` in a fresh process: (its peak resident memory in GB (10^9 bytes), its wall seconds). RuntimeError
    with the tail of its stderr when it fails."""
    start = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        process = subprocess.Popen(list(cmd), stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        if process.returncode != 0:
            err.seek(0)
            raise RuntimeError(f"{' '.join(cmd)} failed ({process.returncode}): {err.read()[-2000:].decode()}")
    return usage.ru_maxrss * 1024 / 1e9, time.perf_counter() - start  # Linux: ru_maxrss in KiB


def make_pair(label_maps: Path, folder: Path) -> tuple[dict[str, Path], dict]:
    """The moving and fixed heads and their label maps (module docstring), written into ``folder``; and the label
    maps' grid (shape, spacing)."""
    from monai_probreg.cli.synth_space import render_head
    from monai_probreg.registration.output_folder import label_dtype, write_volume
    from monai_probreg.spatial.volume_io import read_label

    paths, grid = {}, {}
    for role, (seed, name) in zip(("moving", "fixed"), enumerate(MAPS, start=1)):
        labels = read_label(label_maps / f"{name}.nii.gz")
        paths[role], paths[f"{role}_label"] = folder / f"{name}.nii.gz", folder / f"{name}_label.nii.gz"
        write_volume(paths[role], render_head(labels, seed))
        write_volume(paths[f"{role}_label"], labels, label_dtype(labels.array))
        grid = {"shape": list(labels.shape), "spacing_mm": [round(float(s), 4) for s in labels.spacing]}
    return paths, grid


def command(subcommand: str, *args: str, threads: int) -> list[str]:
    return [sys.executable, "-m", "monai_probreg.cli.main", subcommand, *args, "--threads", str(threads), "--quiet"]


def run(label_maps: Path, threads: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="peak_memory_") as tmp:
        folder = Path(tmp)
        pair, grid = make_pair(label_maps, folder)
        fixed = ["--fixed", str(pair["fixed"]), "--fixed-label", str(pair["fixed_label"])]
        rows = {}
        one = ["--moving", str(pair["moving"]), "--moving-label", str(pair["moving_label"]), *fixed]
        gb, wall = peak_rss(command("register", *one, "--out", str(folder / "one"), threads=threads))
        rows["register"] = {"peak_gb": round(gb, 3), "wall_s": round(wall, 1), "scans": 1}
        for size in BATCH_SIZES:
            scans, labels = folder / f"scans{size}", folder / f"labels{size}"
            scans.mkdir()
            labels.mkdir()
            for n in range(size):  # the same scan under several names: the peak may only grow with the scans' count
                (scans / f"scan{n}.nii.gz").symlink_to(pair["moving"])
                (labels / f"scan{n}.nii.gz").symlink_to(pair["moving_label"])
            args = [
                "--moving",
                str(scans),
                "--moving-label-dir",
                str(labels),
                *fixed,
                "--out",
                str(folder / f"b{size}"),
            ]
            gb, wall = peak_rss(command("register-batch", *args, threads=threads))
            rows[f"register-batch, {size} scan{'s' * (size > 1)}"] = {
                "peak_gb": round(gb, 3),
                "wall_s": round(wall, 1),
                "scans": size,
            }
    return {"pair": {**{k: v.name for k, v in pair.items()}, **grid}, "rows": rows}


def table(result: dict, threads: int) -> list[str]:
    pair = result["pair"]
    lines = [
        f"Peak resident memory, {pair['moving']} -> {pair['fixed']} (rendered heads {pair['shape']} at "
        f"{pair['spacing_mm']} mm), default options, --threads {threads}; target for one register: {TARGET_GB} GB",
        "",
        "| command | scans | peak RSS (GB) | wall (s) |",
        "|---|---|---|---|",
    ]
    for name, row in result["rows"].items():
        lines.append(f"| {name} | {row['scans']} | {row['peak_gb']:.2f} | {row['wall_s']:.0f} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label-maps", type=Path, default=None, help="SynthSeg's training_label_maps folder")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where peak_memory.json goes")
    ap.add_argument("--threads", type=int, default=1, help="--threads of every command (default: %(default)s)")
    args = ap.parse_args(argv)
    missing = [m for m in MAPS if args.label_maps is None or not (args.label_maps / f"{m}.nii.gz").is_file()]
    if missing:
        print(f"skipped: no {', '.join(missing)} in {args.label_maps} (git clone https://github.com/BBillot/SynthSeg)")
        return 0
    result = run(args.label_maps, args.threads)
    record = {**result, "threads": args.threads, "target_gb": TARGET_GB}
    write_report(args.out_dir, "peak_memory", record, table(result, args.threads))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
