"""Robust to the scans users bring? Dice under intensity perturbations of the moving image, the fixed image or both.

Validation pairs (each validation subject -> atlas, and each onto the next validation subject: 12 by default; never
trained on), clean and under each perturbation below, applied after evaluate.yaml's preprocessing (images in
[0, 1]) and followed by the same percentile scaling, as another scanner's scan would be (seeded per pair):

- ``bias``: a smooth multiplicative bias field (MONAI ``RandBiasField``, degree 3, coefficients up to 0.3);
- ``gamma``: contrast change (``RandAdjustContrast``, gamma in [0.5, 2]);
- ``noise``: Gaussian noise, std 0.05 (``RandGaussianNoise``);
- ``blur``: resolution loss, Gaussian blur of 1.5 voxels (``GaussianSmooth``);
- ``thick_slices``: every 3rd slice kept along one random axis, linearly interpolated back (thick-slice scans);
- ``all``: all of the above, one after the other.

Methods, side by side on the same perturbed pairs: each ``--model-file`` (default: the shipped weights; add
candidates to compare training recipes; with ``--refine N`` each also with its mean refined for the pair),
"affine alone" (the input: the scans are pre-aligned, so no registration
is the affine-only result), and ANTs SyN with ``--ants`` (antspyx defaults; ~40 s per pair on 2 threads).
Reported per perturbation and side: mean Dice, and the number of pairs whose deformable Dice ends below the affine
alone (the target is 0).

    python benchmarks/robustness.py --threads 2 --model-file bundle/models/model.pt --model-file CANDIDATE.pt
    python benchmarks/robustness.py --threads 2 --ants --conditions clean all --name robustness_ants  # ANTs, a subset
    python benchmarks/robustness.py --threads 2 --ants --refine 10 --conditions clean all --name robustness_ants

``--conditions`` runs a subset (each condition keeps the seeds of a full run, so its perturbed images are the same);
``--name`` is the stem of the JSON and PNG written.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO, ants_register, bundle_parser
from monai.transforms import (
    GaussianSmooth,
    RandAdjustContrast,
    RandBiasField,
    RandGaussianNoise,
    ScaleIntensityRangePercentiles,
)

from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.engines.registration import register_pair
from monai_probreg.fitting.quality_cases import load_scans
from monai_probreg.metrics.scores import score_pair
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE
from monai_probreg.utils.files import write_text
from monai_probreg.weights.loading import load_weights

SIDES = ("moving", "fixed", "both")
_rescale = ScaleIntensityRangePercentiles(LOWER_PERCENTILE, UPPER_PERCENTILE, 0.0, 1.0, clip=True)


def _seeded(transform, seed: int):
    transform.set_random_state(seed=seed)
    return transform


def _thick_slices(image: torch.Tensor, seed: int) -> torch.Tensor:
    axis = int(np.random.default_rng(seed).integers(3))
    kept = image.index_select(1 + axis, torch.arange(0, image.shape[1 + axis], 3))
    size = list(image.shape[1:])
    return torch.nn.functional.interpolate(kept[None], size=size, mode="trilinear", align_corners=True)[0]


PERTURBATIONS: dict[str, Callable[[torch.Tensor, int], torch.Tensor]] = {  # (1, *S) in [0, 1], seed -> (1, *S)
    "bias": lambda x, s: _seeded(RandBiasField(degree=3, coeff_range=(0.2, 0.3), prob=1.0), s)(x),
    "gamma": lambda x, s: _seeded(RandAdjustContrast(prob=1.0, gamma=(0.5, 2.0)), s)(x),
    "noise": lambda x, s: _seeded(RandGaussianNoise(prob=1.0, std=0.05), s)(x),
    "blur": lambda x, s: GaussianSmooth(sigma=1.5)(x),
    "thick_slices": _thick_slices,
}


def perturb(image: torch.Tensor, name: str, seed: int) -> torch.Tensor:
    """(1, 1, *S) -> (1, 1, *S), then the preprocessing's percentile scaling."""
    x = image[0]
    names = list(PERTURBATIONS) if name == "all" else [name]
    for k, n in enumerate(names):
        x = torch.as_tensor(PERTURBATIONS[n](x, seed + 1000 * k)).float()
    return torch.as_tensor(_rescale(x))[None].float()


ALL_CONDITIONS = [("clean", "none")] + [(p, side) for p in [*PERTURBATIONS, "all"] for side in SIDES]


def select_conditions(selected: list[str] | None) -> list[tuple[str, str]]:
    """``NAME[:SIDE]`` -> the (perturbation, side) conditions, in the order of a full run (all when None)."""
    if not selected:
        return list(ALL_CONDITIONS)
    chosen = set()
    for item in selected:
        name, _, side = item.partition(":")
        matches = [c for c in ALL_CONDITIONS if c[0] == name and (not side or c[1] == side)]
        if not matches:
            raise SystemExit(
                f"--conditions: expected NAME[:SIDE] with NAME in {sorted({c[0] for c in ALL_CONDITIONS})}"
                f" and SIDE in {list(SIDES)}; got {item!r}"
            )
        chosen.update(matches)
    return [c for c in ALL_CONDITIONS if c in chosen]


def pairs_for(ids: list[str]) -> list[tuple[str, str]]:
    return [(s, ATLAS_ID) for s in ids] + [(s, ids[(n + 1) % len(ids)]) for n, s in enumerate(ids)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument(
        "--model-file",
        type=Path,
        action="append",
        default=None,
        help="weights to compare (repeatable; default: evaluate.yaml's model_file)",
    )
    ap.add_argument(
        "--label",
        action="append",
        default=None,
        help="a name for each --model-file in the table and figure, in order (default: the file names)",
    )
    ap.add_argument("--subjects", nargs="+", default=None, help="default: val_ids of train.yaml")
    ap.add_argument("--ants", action="store_true", help="add ANTs SyN (antspyx) side by side")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    ap.add_argument(
        "--conditions",
        nargs="+",
        default=None,
        metavar="NAME[:SIDE]",
        help="only these conditions, e.g. 'clean all:moving all:both' (a name alone: every side); "
        "default all. With --ants, ANTs' ~40 s per pair makes a subset worth it",
    )
    ap.add_argument("--name", default="robustness", help="stem of the JSON and PNG written (default: %(default)s)")
    ap.add_argument(
        "--refine",
        type=int,
        default=0,
        metavar="N",
        help="also each model with its mean refined for the pair (N steps, evaluate.yaml's other "
        "refine_* settings; monai_probreg.engines.refinement); default 0: not run",
    )
    args = ap.parse_args(argv)
    if args.refine < 0:
        raise SystemExit(f"--refine must be >= 0 steps; got {args.refine}")
    if not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    torch.set_num_threads(args.threads)
    start = time.time()
    bundle_root = args.bundle_root.resolve()
    evaluate = bundle_parser(
        bundle_root,
        ["evaluate.yaml"],
        {"dataset_dir": str(args.dataset_dir.resolve()), "refine_iterations": args.refine},
    )
    model_files = [p.resolve() for p in (args.model_file or [Path(evaluate.get_parsed_content("model_file"))])]
    names = args.label or [p.name for p in model_files]
    if len(names) != len(model_files) or len(set(names)) != len(names):
        raise SystemExit(f"--label: one distinct name per --model-file ({len(model_files)}); got {names}")
    networks = {
        name: load_weights(evaluate.get_parsed_content("network_def", lazy=False), p, "cpu")
        for name, p in zip(names, model_files)
    }
    refinement = evaluate.get_parsed_content("refinement")
    refined = {f"{net} + refine {args.refine}": net for net in networks} if refinement.enabled else {}
    models = [*networks, *refined]
    ids = args.subjects or list(bundle_parser(bundle_root, ["train.yaml"]).get_parsed_content("val_ids"))
    scans = load_scans(args.dataset_dir, ids, int(evaluate.get_parsed_content("divisor")))
    conditions = select_conditions(args.conditions)
    records: list[dict[str, Any]] = []
    for c, (name, side) in enumerate(conditions):
        for n, (moving_id, fixed_id) in enumerate(pairs_for(ids)):
            seed = args.seed + 100 * n + 10_000 * ALL_CONDITIONS.index((name, side))  # as in a full run
            moving, fixed = scans[moving_id]["image"], scans[fixed_id]["image"]
            if side in ("moving", "both"):
                moving = perturb(moving, name, seed)
            if side in ("fixed", "both"):
                fixed = perturb(fixed, name, seed + 1)
            labels = scans[moving_id]["label"], scans[fixed_id]["label"]
            row = {
                "perturbation": name,
                "side": side,
                "moving": moving_id,
                "fixed": fixed_id,
                "affine_alone": score_pair(None, *labels).mean_dice,
            }
            for key, network in networks.items():
                row[key] = score_pair(register_pair(network, moving, fixed).displacement, *labels).mean_dice
            for key, base in refined.items():
                output = register_pair(networks[base], moving, fixed, refinement)
                row[key] = score_pair(output.displacement, *labels).mean_dice
            if args.ants:
                warped_label, _, _ = ants_register(moving, fixed, labels[0])
                row["ANTs SyN"] = score_pair(None, warped_label, labels[1]).mean_dice
            records.append(row)
        done = [r for r in records if (r["perturbation"], r["side"]) == (name, side)]
        print(
            f"[{c + 1}/{len(conditions)}] {name} ({side}): "
            + ", ".join(
                f"{_name(k)} {np.mean([r[k] for r in done]):.3f}"
                for k in ["affine_alone", *models, *(["ANTs SyN"] if args.ants else [])]
            ),
            flush=True,
        )
    methods = ["affine_alone", *models, *(["ANTs SyN"] if args.ants else [])]
    table = table_markdown(records, conditions, methods, models)
    print(table)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_text(
        args.out_dir / f"{args.name}.json",
        json.dumps(
            {
                "pairs": [f"{m}_to_{f}" for m, f in pairs_for(ids)],
                "methods": methods,
                "markdown": table,
                "model_files": {name: str(p) for name, p in zip(names, model_files)},
                "refinement": refinement.as_dict() if refined else None,
                "threads": args.threads,
                "seconds": round(time.time() - start, 1),
                "records": records,
            },
            indent=1,
        )
        + "\n",
    )
    figure(records, conditions, methods, args.out_dir / f"{args.name}.png")
    print(f"wrote {args.out_dir / args.name}.json and {args.name}.png")
    return 0


def _name(method: str) -> str:
    return {"affine_alone": "affine alone"}.get(method, method)


def table_markdown(records: list[dict], conditions, methods: list[str], models: list[str]) -> str:
    head = "| perturbation | side | " + " | ".join(_name(m) for m in methods) + " | pairs below the affine alone |"
    lines = [head, "|" + "---|" * (len(methods) + 3)]
    for name, side in conditions:
        rs = [r for r in records if (r["perturbation"], r["side"]) == (name, side)]
        below = ", ".join(f"{sum(r[m] < r['affine_alone'] for r in rs)}" for m in models)
        lines.append(
            f"| {name} | {side} | "
            + " | ".join(f"{np.mean([r[m] for r in rs]):.3f}" for m in methods)
            + f" | {below} |"
        )
    return "\n".join(lines)


def figure(records: list[dict], conditions, methods: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{n}\n({s})" if s != "none" else n for n, s in conditions]
    fig, ax = plt.subplots(figsize=(max(8, 0.55 * len(conditions)), 4.5))
    width = 0.8 / len(methods)
    for k, m in enumerate(methods):
        means = [np.mean([r[m] for r in records if (r["perturbation"], r["side"]) == c]) for c in conditions]
        ax.bar(np.arange(len(conditions)) + k * width, means, width, label=_name(m))
    ax.set_xticks(np.arange(len(conditions)) + 0.4 - width / 2, labels, fontsize=7)
    ax.set_ylabel("mean Dice")
    ax.set_ylim(0.4, 0.75)
    ax.legend(fontsize=8)
    ax.set_title("validation pairs under intensity perturbations")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
