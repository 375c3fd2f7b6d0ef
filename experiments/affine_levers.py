"""The torch affine stage's speed levers against its accuracy: sample cap per level, pyramid levels.

Each setting registers (rigid then affine, :func:`monai_probreg.spatial.affine.align`, torch backend) every case onto
the atlas of ``--dataset-dir`` (S01): the native scans of ``--native-dir`` that have labels (S20), and ``--subjects``
of the dataset moved out of atlas space by seeded random rigid transforms (up to 15 degrees and 20 mm per axis) and
resampled onto a 0.9 x 1.5 x 0.9 mm AIL grid as raw intensities (``register_real_scan.misalign``, the end-to-end
benchmark's synthetic scan). Scored by the affine-only Dice over the labels of both maps (the atlas labels against the
moving labels pulled through the affine, nearest neighbour) and the seconds per case (one warm-up registration
first). Prints a table and writes ``OUT_DIR/affine_levers.json``; without the data it prints "skipped: ..." and
exits 0.

    PYTHONPATH=benchmarks python experiments/affine_levers.py --threads 2   # -> experiments/results/affine_levers.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_NATIVE

from monai_probreg.data.dataset import index_dataset
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.spatial.affine import AffineSettings, align
from monai_probreg.spatial.physical import apply_affine
from monai_probreg.spatial.point_sampling import sample_nearest
from monai_probreg.spatial.volume_io import read_image, read_label
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import library_versions

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
DEFAULT_SUBJECTS = ("S11", "S12", "S13", "S14", "S15")  # validation subjects
MOVE_SEED = 7
MAX_ROTATION_DEG, MAX_TRANSLATION_MM, MOVED_SPACING = 15.0, 20.0, (0.9, 1.5, 0.9)


def settings_to_compare() -> dict[str, AffineSettings]:
    default = AffineSettings()
    two_levels = {
        "shrink_factors": (4, 2),
        "smoothing_sigmas_mm": (2.0, 1.0),
        "rigid_iterations": (30, 15),
        "affine_iterations": (30, 15),
    }
    return {
        "no cap (5% of each level)": AffineSettings(max_samples=None),
        f"default: at most {default.max_samples} points per level": default,
        "at most 20000 points per level": AffineSettings(max_samples=20_000),
        "levels 4 2 (no full-resolution level), no cap": AffineSettings(max_samples=None, **two_levels),
    }


def load_cases(dataset_dir: Path, native_dir: Path, subjects: Sequence[str], atlas) -> list[tuple[str, object, object]]:
    """(id, moving Volume, moving labels Volume) of each case (module docstring)."""
    from register_real_scan import misalign  # benchmarks/ is on PYTHONPATH

    cases = []
    for scan in sorted(native_dir.glob("*.nii.gz")) if native_dir.is_dir() else []:
        labels = native_dir / (scan.name[: -len(".nii.gz")] + "_labels.nii.gz")
        if labels.is_file():
            cases.append((scan.name[: -len(".nii.gz")] + " native", read_image(scan), read_label(labels)))
    index = index_dataset(dataset_dir)
    rng = np.random.default_rng(MOVE_SEED)
    for sid in subjects:
        image, labels = read_image(index.images[sid]), read_label(index.labels[sid])
        moved, moved_labels, *_ = misalign(
            image, labels, atlas, rng, MAX_ROTATION_DEG, MAX_TRANSLATION_MM, MOVED_SPACING
        )
        cases.append((f"{sid} moved", moved, moved_labels))
    return cases


def affine_dice(fixed, matrix: np.ndarray, moving_labels) -> float:
    warped = sample_nearest(moving_labels, apply_affine(matrix, fixed.points))
    ids = sorted(set(fixed.label_ids) & {int(v) for v in np.unique(moving_labels.array) if v != 0})
    return mean_dice(
        label_dice(torch.from_numpy(warped.astype(np.int64)), torch.from_numpy(fixed.label.array.astype(np.int64)), ids)
    )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET, help="its atlas/ is the fixed image")
    ap.add_argument("--native-dir", type=Path, default=DEFAULT_NATIVE, help="native scans with <id>_labels.nii.gz")
    ap.add_argument("--subjects", nargs="*", default=list(DEFAULT_SUBJECTS), help="dataset subjects to move")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="where affine_levers.json goes")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default: %(default)s)")
    args = ap.parse_args(argv)
    if not args.dataset_dir.resolve().is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir.resolve()}", flush=True)
        return 0
    torch.set_num_threads(args.threads)
    index = index_dataset(args.dataset_dir.resolve())
    fixed = prepare_fixed(index.atlas_image, index.atlas_label)
    cases = load_cases(args.dataset_dir.resolve(), args.native_dir.resolve(), args.subjects, fixed.image)
    align(fixed.image, cases[0][1], AffineSettings(), fixed.itk_image)  # warm-up: first-call costs not in a row
    rows = {}
    for name, settings in settings_to_compare().items():
        per_case = {}
        for cid, moving, moving_labels in cases:
            start = time.perf_counter()
            result = align(fixed.image, moving, settings, fixed.itk_image)
            seconds = time.perf_counter() - start
            per_case[cid] = {"dice": affine_dice(fixed, result.matrix, moving_labels), "seconds": seconds}
        rows[name] = {
            "mean_dice": float(np.mean([c["dice"] for c in per_case.values()])),
            "mean_seconds": float(np.mean([c["seconds"] for c in per_case.values()])),
            "settings": settings.as_dict(),
            "cases": per_case,
        }
        print(
            f"{name}: affine-only Dice {rows[name]['mean_dice']:.4f}, {rows[name]['mean_seconds']:.2f} s per case",
            flush=True,
        )
    lines = ["| setting | mean affine-only Dice | s per case |", "|---|---|---|"]
    lines += [f"| {name} | {r['mean_dice']:.4f} | {r['mean_seconds']:.2f} |" for name, r in rows.items()]
    table = "\n".join(lines)
    result = {
        "cases": [cid for cid, *_ in cases],
        "threads": args.threads,
        "move_seed": MOVE_SEED,
        "rows": rows,
        "markdown": table,
        "versions": library_versions(),
    }  # write_text creates the folder
    path = write_text(args.out_dir / "affine_levers.json", json.dumps(result, indent=2) + "\n")
    print(f"\n{table}\n\nwrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
