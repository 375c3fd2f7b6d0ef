"""Speed and memory, side by side in one run: ours, MONAI's VoxelMorph and ANTs SyN on the same real pairs.

Pairs: subjects of a dataset folder (default: the first ``--pairs`` of ``val_ids`` in configs/train.yaml) registered to
its atlas, each through evaluate.yaml's preprocessing (RAS, intensities to [0, 1], padded to 16) and then padded or
cropped (``ResizeWithPadOrCrop``, zeros) to the paper's 160 x 192 x 224 (LPBA40: 160 x 192 x 160 -> 32 zero slices on
each side of the last axis). Every method sees the same arrays. Rows:
  - ours, mean: ``ProbRegNet()`` (the paper's network; UNet on the input grid, half-resolution velocity), untrained:
    the speed target; network + integration + upsampling + warp (``register_pair``, inference levers on by default,
    and the process keeps freed memory for reuse as ``monai-probreg`` and the bundle do, :mod:`monai_probreg.utils.memory`);
  - ours, mean, memory reuse off: the same with glibc's default allocator settings (what that lever is worth);
  - ours, K posterior samples: ``ProbRegNet.sample(moving, fixed, K)`` (UNet once, K fields integrated; on a CPU one at a time);
  - ours, shipped weights: configs' network and ``model_file`` (evaluate.yaml); its network grid is scaled with the
    input (trained at 80 x 96 x 80 for 160 x 192 x 160 -> 80 x 96 x 112 here: the same 2 mm the weights know), with
    Dice / |J| <= 0, and the same model in float32 (untimed) to show what the bf16 UNet changes on real pairs;
  - MONAI ``VoxelMorph()`` with its defaults (full-resolution integration), untrained (speed only);
  - ANTs SyN, ``ants.registration(fixed, moving, type_of_transform="SyN")`` (antspyx, optional extra ``[bench]``), as
    benchmarks/accuracy_table.py runs it, with Dice and |J| <= 0 of its composed field.
Timing: wall time of the registration call, one untimed warm-up (ANTs: on a 4x smaller pair), then ``--repeats``
runs per pair (ANTs: ``--ants-repeats``); the median over all pairs and runs; threads as given (torch, MKL, ITK).
Memory: each method runs in a process of its own (benchmarks/speed_workers.py) and reports the peak resident set
of its timed runs (Python, torch, the pairs and the method together; the scoring afterwards is not counted). What each
inference lever is worth and where the time goes: experiments/speed_levers.py.

    python benchmarks/speed_compare.py --threads 2         # table + benchmarks/results/speed_compare.{json,png}
    python benchmarks/speed_compare.py --methods ours_mean voxelmorph --pairs 1
    python benchmarks/speed_compare.py --synthetic --size 64 64 64     # random inputs: speed only, no dataset needed
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO, bundle_parser, parse_overrides

HERE = Path(__file__).resolve().parent
PAPER_SIZE = [160, 192, 224]
ANTS_WARMUP_SHRINK = 4  # ANTs' warm-up pair is this many times smaller per axis (loads the code, costs seconds)
WORKER_TIMEOUT_S = 3600
ROWS = {  # method key -> row name (table order)
    "ours_mean": "ours, mean (paper network, untrained)",
    "ours_mean_no_reuse": "ours, mean, memory reuse off",
    "ours_samples": "ours, K = {k} posterior samples",
    "ours_trained": "ours, shipped weights (the configs' model_file)",
    "voxelmorph": "MONAI VoxelMorph() (untrained)",
    "ants": 'ANTs SyN (antspyx, type_of_transform="SyN")',
}


def prepare_pairs(
    dataset_dir: Path, subjects: Sequence[str] | None, num_pairs: int, size: Sequence[int], bundle_root: Path
) -> tuple[list[dict], list[int]]:
    """evaluate.yaml-preprocessed pairs padded/cropped to ``size``: dicts of (1, 1, *size) tensors; native grid."""
    from monai.data import Dataset
    from monai.transforms import ResizeWithPadOrCrop

    from monai_probreg.data.dataset import index_dataset, labelled_pairs

    config = bundle_parser(bundle_root, ["evaluate.yaml"], {"dataset_dir": str(dataset_dir)})
    if subjects is None:
        subjects = list(bundle_parser(bundle_root, ["train.yaml"])["val_ids"])[:num_pairs]
    dataset = Dataset(labelled_pairs(index_dataset(dataset_dir), subjects), config.get_parsed_content("preprocessing"))
    pad_or_crop = ResizeWithPadOrCrop(spatial_size=list(size))
    pairs, native = [], None
    for item in dataset:
        native = list(item["moving"].shape[1:])
        pair = {
            k: pad_or_crop(item[k]).as_tensor()[None].float()
            for k in ("moving", "fixed", "moving_label", "fixed_label")
        }
        pairs.append({"id": item["id"], **pair})
    return pairs, native


def synthetic_pairs(num_pairs: int, size: Sequence[int]) -> list[dict]:
    g = torch.Generator().manual_seed(0)
    return [
        {
            "id": f"random{i}",
            "moving": torch.rand(1, 1, *size, generator=g),
            "fixed": torch.rand(1, 1, *size, generator=g),
        }
        for i in range(num_pairs)
    ]


def run_worker(method: str, pairs_file: Path, work: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One method in its own process (speed_workers.py); its result, or a status saying why there is none."""
    out = work / f"{method}.json"
    repeats = args.ants_repeats if method == "ants" else args.repeats
    cmd = [
        sys.executable,
        str(HERE / "speed_workers.py"),
        method,
        "--pairs",
        str(pairs_file),
        "--out",
        str(out),
        "--threads",
        str(args.threads),
        "--repeats",
        str(repeats),
        "--samples",
        str(args.samples),
    ]
    threads = str(args.threads)
    env = {
        **os.environ,
        "OMP_NUM_THREADS": threads,
        "MKL_NUM_THREADS": threads,
        "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS": threads,
    }
    print(f"running {method} ...", flush=True)
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=WORKER_TIMEOUT_S)
    if done.returncode != 0 or not out.is_file():
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        return {"method": method, "status": f"failed: {tail[0][:200]}"}
    return {**json.loads(out.read_text()), "status": "ok"}


def _mean(values: list[float]) -> float | None:
    return statistics.fmean(values) if values else None


def summarise(results: dict[str, dict], k: int) -> list[dict[str, Any]]:
    """Table rows: median time, ratio to ours (mean) measured in this run, peak memory, scores."""
    base = results.get("ours_mean", {}).get("median_s")
    rows = []
    for key, name in ROWS.items():
        if key not in results:
            continue
        r = results[key]
        row = {"key": key, "name": name.format(k=k), "status": r["status"]}
        if r["status"] == "ok":
            scores = list(r.get("scores", {}).values())
            row.update(
                median_s=r["median_s"],
                ratio_to_ours=r["median_s"] / base if base else None,
                peak_rss_gb=r["peak_rss_mb"] / 1024,
                threads=r["threads"],
                mean_dice=_mean([s["mean_dice"] for s in scores]),
                folding_per_pair=_mean([s["num_folding"] for s in scores]),
            )
        rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    def fmt(value: float | None, spec: str) -> str:
        return "–" if value is None else format(value, spec)

    lines = [
        "| method | s per pair (median) | × ours (mean) | peak memory (GB) | mean Dice | \\|J\\|≤0 per pair | threads |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row["status"] != "ok":
            lines.append(f"| {row['name']} | {row['status']} | | | | | |")
            continue
        lines.append(
            f"| {row['name']} | {fmt(row['median_s'], '.3g')} | {fmt(row['ratio_to_ours'], '.1f')} | "
            f"{row['peak_rss_gb']:.2f} | {fmt(row['mean_dice'], '.3f')} | {fmt(row['folding_per_pair'], '.1f')} "
            f"| {row['threads']} |"
        )
    return "\n".join(lines)


def bar_chart(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Time per pair (log scale) and peak memory per method; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r["status"] == "ok"]
    names = [r["name"].replace(" (", "\n(") for r in ok]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(13, 4.8), layout="constrained")
    for ax, key, label, log in (
        (ax_t, "median_s", "seconds per pair (median, log scale)", True),
        (ax_m, "peak_rss_gb", "peak resident memory (GB)", False),
    ):
        values = [r[key] for r in ok]
        ax.barh(range(len(ok)), values, color=[f"C{i}" for i in range(len(ok))], alpha=0.85)
        for i, v in enumerate(values):
            ax.text(v, i, f" {v:.3g}", va="center", fontsize=9)
        ax.set_yticks(range(len(ok)), names, fontsize=8)
        ax.invert_yaxis()
        ax.set_xscale("log" if log else "linear")
        ax.set_xlabel(label)
        ax.grid(axis="x", alpha=0.3)
    fig.suptitle(title, fontsize=11)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET, help="atlas/, images/, labels/")
    ap.add_argument("--subjects", nargs="+", default=None, help="subject ids (default: the first --pairs of val_ids)")
    ap.add_argument("--pairs", type=int, default=2, help="how many subjects when --subjects is not given")
    ap.add_argument("--size", type=int, nargs=3, default=PAPER_SIZE, help="pad/crop every pair to this grid")
    ap.add_argument("--methods", nargs="+", choices=list(ROWS), default=list(ROWS))
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads of every method")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per pair (torch methods)")
    ap.add_argument("--ants-repeats", type=int, default=1, help="timed runs per pair for ANTs SyN")
    ap.add_argument("--samples", type=int, default=10, help="K of the posterior-samples row")
    ap.add_argument("--synthetic", action="store_true", help="random pairs, no dataset: speed and memory only")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where speed_compare.{json,png} go")
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an evaluate.yaml value (YAML) for the shipped-weights row, e.g. unet_precision=fp32",
    )
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.override)

    dataset_dir = args.dataset_dir.resolve()
    bundle_root = args.bundle_root.resolve()
    if args.synthetic:
        pairs, native = synthetic_pairs(args.pairs, args.size), list(args.size)
        methods = [m for m in args.methods if m not in ("ours_trained", "ants")]
    elif not dataset_dir.is_dir():
        print(f"skipped: dataset not found at {dataset_dir}", flush=True)
        return 0
    else:
        pairs, native = prepare_pairs(dataset_dir, args.subjects, args.pairs, args.size, bundle_root)
        methods = list(args.methods)
    results: dict[str, dict] = {}
    if "ants" in methods and importlib.util.find_spec("ants") is None:
        results["ants"] = {"status": "skipped: antspyx not installed (pip install -e '.[bench]')"}
        methods.remove("ants")
    meta = {
        "size": list(args.size),
        "native": native,
        "bundle_root": str(bundle_root),
        "overrides": overrides,
        "ants_warmup_shrink": ANTS_WARMUP_SHRINK,
        "subjects": [p["id"] for p in pairs],
    }
    print(
        f"{len(pairs)} pairs {meta['subjects']} at {'x'.join(map(str, args.size))}, {args.threads} threads", flush=True
    )
    with tempfile.TemporaryDirectory(prefix="speed_compare_") as tmp:
        work = Path(tmp)
        torch.save({"meta": meta, "pairs": pairs}, work / "pairs.pt")
        for method in methods:
            results[method] = run_worker(method, work / "pairs.pt", work, args)
            r = results[method]
            timing = f"{r['median_s']:.3f} s, " if "median_s" in r else ""
            print(
                f"  {method}: "
                + (f"{timing}peak {r['peak_rss_mb'] / 1024:.2f} GB" if r["status"] == "ok" else r["status"]),
                flush=True,
            )
    rows = summarise(results, args.samples)
    table = markdown(rows)
    report = {
        "settings": {
            "size": args.size,
            "native_grid": native,
            "threads": args.threads,
            "repeats": args.repeats,
            "ants_repeats": args.ants_repeats,
            "samples": args.samples,
            "synthetic": args.synthetic,
            "dataset_dir": None if args.synthetic else str(dataset_dir),
            "subjects": meta["subjects"],
            "overrides": overrides,
        },
        "versions": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "cpu": platform.processor() or platform.machine(),
            "platform": platform.platform(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        },
        "rows": rows,
        "results": results,
        "markdown": table,
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    json_path = args.out_dir / "speed_compare.json"
    tmp_json = args.out_dir / ".speed_compare.json.tmp"
    tmp_json.write_text(json.dumps(report, indent=2) + "\n")
    os.replace(tmp_json, json_path)
    png_path = args.out_dir / "speed_compare.png"
    bar_chart(rows, png_path, f"{len(pairs)} pairs at {'x'.join(map(str, args.size))}, {args.threads} threads")
    print(f"\n{table}\n")
    print(f"wrote {json_path}\nwrote {png_path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
