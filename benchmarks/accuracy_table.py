"""Accuracy benchmark: no registration vs ANTs SyN vs our model, side by side on the same pairs and grid.

Two tasks over the validation subjects (``val_ids`` of train.yaml unless ``--subjects``; never trained on):
  - "atlas": every subject -> the dataset's atlas (S01 for LPBA40; moving = subject, fixed = atlas),
  - "pairs": every ordered pair of distinct subjects (moving -> fixed, the fixed image is not the atlas),
and four methods:
  - "no registration" (the identity),
  - "ANTs SyN" (antspyx, ``ants.registration(fixed, moving, type_of_transform="SyN")``, antspyx defaults; optional
    extra ``pip install -e ".[bench]"``; the row says "skipped" when antspyx cannot be imported),
  - "ours" (evaluate.yaml's ``model_file``: the shipped default weights, or ``--model-file``),
  - "ours + refinement" (the same weights, the posterior mean refined per pair: evaluate.yaml's ``refinement`` with
    ``--refine-iterations`` steps, :mod:`monai_probreg.engines.refinement`),
and reports per method and task: mean Dice over the fixed image's labels (mean and population std over pairs),
|J| <= 0 voxels per pair, std of log|J| (over the voxels where J > 0), wall time per pair and threads.

Everything comes from the bundle configs (nothing duplicated here): the network settings, device, preprocessing and
refinement settings are those of ``configs/evaluate.yaml`` (override a value with ``--override KEY=VALUE``, as on the
``monai.bundle run`` command line).

Same grid for every method: each pair goes once through evaluate.yaml's preprocessing (RAS, intensities
percentile-scaled to [0, 1], padded to the divisor) and every method is scored on that fixed grid with
:func:`monai_probreg.metrics.scores.score_pair` (labels warped nearest neighbour, Dice per fixed label). ANTs gets
the same arrays as images of spacing 1 mm, origin 0, identity direction, so its physical space is our voxel
space (no geometry mismatch).

Wall time per pair: ours = :func:`~monai_probreg.engines.registration.timed_register_pair` (network + integration + warp,
and the refinement for that row; after one untimed warm-up pass), as evaluate.yaml reports it; ANTs = the
``ants.registration`` call (affine + SyN stages, transform files included). Neither includes loading or scoring.

    python benchmarks/accuracy_table.py --threads 2            # table + benchmarks/results/accuracy_table.{json,png}
    python benchmarks/accuracy_table.py --subjects S11 S14 --tasks pairs --methods identity ants
    python benchmarks/accuracy_table.py --override network_size=null   # a model trained on the native grid
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import monai
import numpy as np
import torch
from common import (
    ANTS_INSTALL_HINT,
    DEFAULT_DATASET,
    DEFAULT_OUT,
    DEFAULT_REFINE_ITERATIONS,
    REPO,
    ants_available,
    ants_register,
    bundle_parser,
    parse_overrides,
)
from monai.bundle import ConfigParser
from monai.data import Dataset

import monai_probreg
from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import ATLAS_ID, subject_pairs
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.engines.registration import evaluate_pair, register_pair
from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
from monai_probreg.metrics.scores import PairScores, score_pair
from monai_probreg.utils.files import write_text
from monai_probreg.weights.loading import load_weights

METHODS = {  # --methods key -> row name, in table order
    "identity": "no registration",
    "ants": "ANTs SyN",
    "ours": "ours",
    "refined": "ours + refinement",
}
TASKS = {  # --tasks key -> column name, in table order
    "atlas": "validation -> atlas",
    "pairs": "pairs between validation subjects",
}
ANTS_SETTINGS = {
    "call": 'ants.registration(fixed, moving, type_of_transform="SyN")',
    "parameters": "antspyx defaults (affine + SyN stages; default random sampling, so results vary slightly per run)",
    "image_geometry": "evaluate.yaml-preprocessed arrays, spacing 1 mm, origin 0, identity direction",
    "labels": 'ants.apply_transforms(fixed, moving_label, fwdtransforms, interpolator="nearestNeighbor")',
    "jacobian": "monai_probreg jacobian_determinant of the composed (affine + SyN) forward displacement field "
    "(ants.apply_transforms(..., compose=...)), in voxels since 1 voxel = 1 mm here",
    "threads": "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS",
}


# ------------------------------------------------------------------------------------------------ methods
def _ants_scores(pair: dict, labels: Sequence[int] | None) -> PairScores:
    warped_label, displacement, runtime = ants_register(pair["moving"], pair["fixed"], pair["moving_label"])
    # Dice of ANTs' own nearest-neighbour label warp; folding of its composed field
    scores = score_pair(None, warped_label, pair["fixed_label"], runtime, labels)
    return scores._replace(**jacobian_stats(jacobian_determinant(displacement))._asdict())


# ------------------------------------------------------------------------------------------------ reporting
def _stat(values: Sequence[float]) -> dict[str, float | None]:
    arr = np.asarray([v for v in values if not math.isnan(v)], dtype=np.float64)
    return {"mean": float(arr.mean()), "std": float(arr.std())} if arr.size else {"mean": None, "std": None}


def _pair_record(s: PairScores) -> dict[str, Any]:
    def num(v: float) -> float | None:
        return None if math.isnan(v) else float(v)

    return {
        "mean_dice": num(s.mean_dice),
        "dice": {str(k): num(v) for k, v in s.dice.items()},
        "num_folding": int(s.num_folding),
        "percent_folding": float(s.percent_folding),
        "std_log_jacobian": num(s.std_log_jacobian),
        "runtime_s": float(s.runtime_s),
    }


def _aggregate(scores: Sequence[PairScores]) -> dict[str, dict[str, float | None]]:
    fields = ("mean_dice", "num_folding", "percent_folding", "std_log_jacobian", "runtime_s")
    return {f: _stat([float(getattr(s, f)) for s in scores]) for f in fields}


def markdown_table(methods: dict[str, dict[str, Any]], tasks: Sequence[str]) -> str:
    """The README table: one row per method, a Dice column per task; rows that did not run say why."""
    names = [TASKS[t] for t in tasks]
    lines = [
        "| method | "
        + " | ".join(f"{n}: mean Dice (std)" for n in names)
        + " | \\|J\\|<=0 per pair | std log\\|J\\| | s per pair | threads |",
        "|---|" + "---|" * (len(names) + 4),
    ]
    for row in methods.values():
        if row["status"] != "ok":
            lines.append(f"| {row['name']} | {row['status']} |" + " |" * (len(names) + 3))
            continue
        agg, timed = row["aggregate"], row["key"] != "identity"
        dice = [f"{agg[t]['mean_dice']['mean']:.3f} ({agg[t]['mean_dice']['std']:.3f})" for t in tasks]
        every = row["aggregate_all"]
        folding = f"{every['num_folding']['mean']:.1f}"
        std_log = "n/a" if every["std_log_jacobian"]["mean"] is None else f"{every['std_log_jacobian']['mean']:.3f}"
        seconds = f"{every['runtime_s']['mean']:.2f}" if timed else "–"
        lines.append(
            f"| {row['name']} | " + " | ".join(dice) + f" | {folding} | {std_log} | {seconds} | "
            f"{row['threads'] or '–'} |"
        )
    return "\n".join(lines)


def bar_chart(methods: dict[str, dict[str, Any]], tasks: Sequence[str], path: Path, title: str) -> None:
    """Mean Dice per method and task (error bars: std over pairs, dots: pairs); written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in methods.values() if r["status"] == "ok"]
    fig, axes = plt.subplots(
        1, len(tasks), figsize=(1.5 + 1.6 * max(len(rows), 1) * len(tasks), 4.5), layout="constrained", squeeze=False
    )
    for ax, task in zip(axes[0], tasks):
        for i, row in enumerate(rows):
            agg = row["aggregate"][task]["mean_dice"]
            ax.bar(i, agg["mean"], yerr=agg["std"], capsize=6, color=f"C{i}", alpha=0.8)
            dots = [
                p["mean_dice"] for p in row["per_pair"].values() if p["task"] == task and p["mean_dice"] is not None
            ]
            ax.scatter(np.full(len(dots), i) + np.linspace(-0.2, 0.2, len(dots)), dots, s=8, color="black", zorder=3)
            ax.text(i, min(agg["mean"] + agg["std"] + 0.02, 0.97), f"{agg['mean']:.3f}", ha="center", fontsize=9)
        ax.set_xticks(range(len(rows)), [r["name"].replace(" + ", "\n+ ") for r in rows], fontsize=9)
        ax.set_ylim(0, 1)
        ax.set_ylabel("mean Dice over the fixed image's labels")
        ax.set_title(TASKS[task], fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(title, fontsize=11)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------------ main
def _methods(
    keys: Sequence[str],
    evaluate: ConfigParser,
    model_file: Path,
    refinement: RefinementSettings,
    device: torch.device,
    labels: Sequence[int] | None,
    threads: int,
):
    """Table rows (in :data:`METHODS` order) and, for the rows that can run, ``pair dict -> PairScores``.

    Returns (rows, runners, networks to warm up, antspyx version or None). A row that cannot run keeps a status
    saying why (antspyx not importable, weights file missing)."""
    rows: dict[str, dict[str, Any]] = {}
    runners: dict[str, Callable[[dict], PairScores]] = {}
    warmup: dict[str, torch.nn.Module] = {}
    antspyx, network = None, None
    for key in (k for k in METHODS if k in keys):
        row = rows[key] = {"key": key, "name": METHODS[key], "status": "ok", "threads": None, "per_pair": {}}
        if key == "identity":
            runners[key] = lambda p: score_pair(None, p["moving_label"], p["fixed_label"], 0.0, labels)
        elif key == "ants":
            ok, message = ants_available()
            if not ok:
                row["status"] = f"skipped: {message}; {ANTS_INSTALL_HINT}"
                continue
            antspyx, row["threads"] = message, threads
            runners[key] = lambda p: _ants_scores(p, labels)
        else:
            row["model_file"] = str(model_file)
            if not model_file.is_file():
                row["status"] = f"not trained (no {model_file})"
                continue
            if network is None:
                network = load_weights(evaluate.get_parsed_content("network_def", lazy=False), model_file, device)
                warmup[key] = network  # the first pass allocates: run once untimed
            settings = refinement if key == "refined" else None
            if settings is not None:
                row["refinement"] = settings.as_dict()
            row["threads"] = threads if device.type == "cpu" else str(device)
            runners[key] = (
                lambda net, r: (
                    lambda p: evaluate_pair(
                        net, p["moving"], p["fixed"], p["moving_label"], p["fixed_label"], labels, r
                    )[0]
                )
            )(network, settings)
    return rows, runners, warmup, antspyx


def _task_pairs(dataset_dir: Path, subjects: Sequence[str], tasks: Sequence[str]) -> list[dict]:
    """The labelled pairs of each task, tagged with it: subject -> atlas first, then the ordered subject pairs."""
    index = index_dataset(dataset_dir)
    everything = subject_pairs(index, subjects, include_atlas=True, require_labels=True)
    atlas_ids = {f"{s}_to_{ATLAS_ID}" for s in subjects}
    pairs = [{**p, "task": "atlas"} for p in everything if p["id"] in atlas_ids and "atlas" in tasks]
    pairs += [{**p, "task": "pairs"} for p in everything if p["id"] not in atlas_ids and "pairs" in tasks]
    if not pairs:
        raise SystemExit(f"no labelled pair for {list(tasks)} among {list(subjects)} in {dataset_dir}")
    return pairs


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--dataset-dir", type=Path, default=DEFAULT_DATASET, help="atlas/, images/, labels/ (default: %(default)s)"
    )
    ap.add_argument("--subjects", nargs="+", default=None, help="subject ids (default: val_ids of configs/train.yaml)")
    ap.add_argument("--tasks", nargs="+", choices=list(TASKS), default=list(TASKS), help="columns to compute")
    ap.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS), help="rows to compute")
    ap.add_argument(
        "--threads", type=int, default=None, help="CPU threads for torch and ITK (default: torch's default)"
    )
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where accuracy_table.{json,png} go")
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle", help="bundle with configs/ and models/")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument(
        "--refine-iterations",
        type=int,
        default=DEFAULT_REFINE_ITERATIONS,
        help="steps of the 'ours + refinement' row (default: %(default)s; the other settings: "
        "evaluate.yaml's refine_*)",
    )
    ap.add_argument("--device", default=None, help="torch device for our models (default: evaluate.yaml's)")
    ap.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an evaluate.yaml value (YAML), e.g. network_size=[80,96,80]; repeatable",
    )
    args = ap.parse_args(argv)

    dataset_dir = args.dataset_dir.resolve()
    if not dataset_dir.is_dir():
        print(f"skipped: dataset not found at {dataset_dir}", flush=True)
        return 0
    if args.refine_iterations < 1:
        raise SystemExit(f"--refine-iterations must be >= 1; got {args.refine_iterations}")

    threads = args.threads or torch.get_num_threads()
    torch.set_num_threads(threads)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(threads)  # ITK reads it once, at its first use
    bundle_root = args.bundle_root.resolve()
    overrides = parse_overrides(args.override)
    evaluate = bundle_parser(
        bundle_root,
        ["evaluate.yaml"],
        {**overrides, "dataset_dir": str(dataset_dir), "refine_iterations": args.refine_iterations},
    )
    subjects = args.subjects or list(bundle_parser(bundle_root, ["train.yaml"]).get_parsed_content("val_ids"))
    tasks = [t for t in TASKS if t in args.tasks]
    model_file = args.model_file or Path(evaluate.get_parsed_content("model_file"))
    refinement = evaluate.get_parsed_content("refinement")
    device = torch.device(args.device) if args.device else evaluate.get_parsed_content("device")
    labels = evaluate.get_parsed_content("label_values")
    pairs = _task_pairs(dataset_dir, subjects, tasks)
    dataset = Dataset(pairs, transform=evaluate.get_parsed_content("preprocessing"))
    rows, runners, warmup, antspyx = _methods(args.methods, evaluate, model_file, refinement, device, labels, threads)
    versions = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "monai": monai.__version__,
        "numpy": np.__version__,
        "monai_probreg": monai_probreg.__version__,
        "antspyx": antspyx,
    }
    for row in rows.values():
        if row["status"] != "ok":
            print(f"{row['name']}: {row['status']}", flush=True)

    print(
        f"{len(pairs)} pairs ({', '.join(tasks)}) of {len(subjects)} subjects; {threads} threads; device {device}",
        flush=True,
    )
    scores: dict[str, dict[str, list[PairScores]]] = {key: {t: [] for t in tasks} for key in runners}
    for i, item in enumerate(dataset):
        pair = {
            k: (v[None].to(device) if k in ("moving", "fixed") else v[None]) if isinstance(v, torch.Tensor) else v
            for k, v in item.items()
        }
        for key, run in runners.items():
            if key in warmup:
                register_pair(warmup.pop(key), pair["moving"], pair["fixed"])
            s = run(pair)
            scores[key][pair["task"]].append(s)
            rows[key]["per_pair"][pair["id"]] = {"task": pair["task"], **_pair_record(s)}
            print(
                f"[{i + 1}/{len(pairs)}] {pair['id']} {METHODS[key]}: Dice {s.mean_dice:.3f}, "
                f"|J|<=0 {s.num_folding}, {s.runtime_s:.2f} s",
                flush=True,
            )
    for key, row in rows.items():
        if key in scores:
            row["aggregate"] = {t: _aggregate(scores[key][t]) for t in tasks}
            row["aggregate_all"] = _aggregate([s for t in tasks for s in scores[key][t]])

    table = markdown_table(rows, tasks)
    network_keys = ("network_size", "int_downsize", "num_steps", "enc_channels", "dec_channels", "divisor")
    result = {
        "dataset_dir": str(dataset_dir),
        "subjects": list(subjects),
        "tasks": {t: [p["id"] for p in pairs if p["task"] == t] for t in tasks},
        "settings": {
            "threads": threads,
            "device": str(device),
            "model_file": str(model_file),
            "network (evaluate.yaml)": {k: evaluate.get_parsed_content(k) for k in network_keys},
            "refinement (evaluate.yaml, refined row)": refinement.as_dict(),
            "overrides": overrides,
            "preprocessing (evaluate.yaml)": evaluate["preprocessing"],  # every method is scored on this grid
            "labels_scored": "every non-zero label of the fixed image" if labels is None else list(labels),
            "dice": "score_pair: nearest-neighbour warped moving labels vs fixed labels; std = population std over "
            "the pairs of a task",
            "folding": "|J| <= 0 voxels over the whole fixed grid; std log|J| over voxels with J > 0; both over "
            "every pair of every task",
            "runtime": "ours: network + integration + warp (+ refinement) after one warm-up pass; ANTs: the "
            "ants.registration call",
            "ants": ANTS_SETTINGS,
        },
        "versions": {**versions, "platform": platform.platform(), "cpu": platform.processor() or platform.machine()},
        "methods": rows,
        "markdown": table,
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    json_path = write_text(args.out_dir / "accuracy_table.json", json.dumps(result, indent=2) + "\n")
    png_path = args.out_dir / "accuracy_table.png"
    bar_chart(rows, tasks, png_path, f"{dataset_dir.name}: {len(subjects)} validation subjects, {len(pairs)} pairs")
    print(f"\n{table}\n\nwrote {json_path}\nwrote {png_path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
