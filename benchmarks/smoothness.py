"""What ``--smoothness S`` does on LPBA40: Dice, folding and the Jacobian's spread for each S, side by side.

``monai-probreg register --smoothness S`` multiplies the refinement's smoothness prior (the config's
``refine_prior_lambda``) by S. This benchmark refines the network's mean of the same validation pairs (images as the
command feeds them, the aligned 160 x 192 x 160 grid; :func:`refinement_speed.load_pair`) with each S of
``--values`` and reports, per S, over the pairs: the mean Dice over the 56 structures (labels warped by nearest
neighbour), the folded voxels (|J| <= 0) of the displacement on the image grid, and the spread of the warp inside the
fixed brain (the standard deviation of log |J| over the fixed image's labelled voxels); the network alone as a first
row. A user reads off how much Dice a smoother (or sharper) warp costs (or buys).

    python benchmarks/smoothness.py --threads 2     # table + benchmarks/results/smoothness.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path

import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, write_report
from refinement_speed import load_pair

from monai_probreg.blocks.warp import warp_labels
from monai_probreg.engines.refinement import refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
from monai_probreg.registration.model import load_model

# moving:fixed, the validation subjects (train.yaml's val_ids) each once as moving and once as fixed
PAIRS = ("S11:S14", "S14:S16", "S16:S21", "S21:S28", "S28:S29", "S29:S11")
VALUES = (0.25, 0.5, 1.0, 2.0, 4.0)  # S: the prior's weight relative to the shipped one


def scores(displacement: torch.Tensor, moving_label: torch.Tensor, fixed_label: torch.Tensor) -> dict[str, float]:
    """Dice over the fixed labels, folded voxels on the grid, std of log |J| in the fixed brain."""
    ids = [int(v) for v in torch.unique(fixed_label) if v > 0]
    dice = mean_dice(label_dice(warp_labels(moving_label, displacement), fixed_label, ids))
    det = jacobian_determinant(displacement)[0]
    whole, brain = jacobian_stats(det), jacobian_stats(det, fixed_label[0, 0] > 0)
    return {"dice": dice, "folded": whole.num_folding, "std_log_jacobian": brain.std_log_jacobian}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), help="moving:fixed subject ids")
    ap.add_argument("--values", nargs="+", type=float, default=list(VALUES), help="the values of S")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    if not (args.dataset_dir / "images").is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}", flush=True)
        return 0
    if any(not v > 0 for v in args.values):
        ap.error(f"--values: expected numbers > 0, got {args.values}")
    torch.set_num_threads(args.threads)
    model = load_model()
    shipped = model.refinement
    rows: dict[str, list[dict]] = {"network alone": [], **{f"S = {v:g}": [] for v in args.values}}
    for pair in args.pairs:
        moving, fixed, moving_label, fixed_label = load_pair(args.dataset_dir, pair)
        output = register_pair(model.network, moving, fixed)
        rows["network alone"].append(scores(output.displacement, moving_label, fixed_label))
        for value in args.values:
            settings = shipped.with_fields(prior_lambda=shipped.prior_lambda * value)
            refined = refine_registration(model.network, moving, fixed, output, settings)
            rows[f"S = {value:g}"].append(scores(refined.displacement, moving_label, fixed_label))
            print(f"{pair} S={value:g}: {rows[f'S = {value:g}'][-1]}", flush=True)
    lines = [
        f"| refinement (prior_lambda {shipped.prior_lambda:g} x S) | mean Dice | folded voxels (all pairs) | "
        "std of log \\|J\\| in the brain (median) |",
        "|---|---|---|---|",
    ]
    summary = {}
    for name, per_pair in rows.items():
        summary[name] = {
            "dice": statistics.fmean(r["dice"] for r in per_pair),
            "folded": sum(r["folded"] for r in per_pair),
            "std_log_jacobian": statistics.median(r["std_log_jacobian"] for r in per_pair),
        }
        s = summary[name]
        lines.append(f"| {name} | {s['dice']:.4f} | {s['folded']} | {s['std_log_jacobian']:.3f} |")
    result = {"rows": summary, "per_pair": rows, "pairs": args.pairs, "threads": args.threads}
    write_report(args.out_dir, "smoothness", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
