"""Which test-time refinement pays for its cost, measured on *training* pairs only (no split the benchmarks report).

The refinement (:mod:`monai_probreg.engines.refinement`) has a few levers: the number of Adam steps, the fold guard
(``fold_local_steps``: give the change up only around folded voxels before halving all of it), and the grid its
velocity lives on (``velocity_grid_factor``: 1 = the network's velocity grid, 4 mm for the shipped weights; 2 = twice
finer, 2 mm, the paper's velocity grid). Each variant registers the same pairs through the whole command
(``register --fixed``):

- LPBA40 training subjects (pairs of ``--lpba40-pairs``): Dice over the 56 structures;
- synthetic heads rendered from SynthSeg label maps 01-10 (the maps ``train_synth.yaml`` trains on; 11-12 are the
  generalisation benchmark's, 13-20 are left alone): Dice over FreeSurfer's aseg structures;
- the identity cases: one training scan and one training head each registered onto an exact copy of itself, where
  the right answer is no displacement at all: the median length of ``warp.nii.gz``'s displacement inside the labels
  (mm), what a variant invents where there is nothing to register (a larger step won the pairs in bundle 0.20.0 and
  lost here: docs/accuracy.md).

It imports the generalisation benchmark's synthetic heads, so benchmarks/ goes on the path:

    PYTHONPATH=benchmarks python experiments/refinement_levers.py --threads 1 --label-maps SynthSeg/data/training_label_maps

Prints one table (Dice, folded voxels, refinement seconds) and writes ``OUT_DIR/refinement_levers.json`` (default
experiments/results).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import itk
import numpy as np
import torch
from common import DEFAULT_DATASET, parse_variant, write_report
from generalization import dice, synthetic_head

from monai_probreg.data.label_synthesis import ASEG_LABELS
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.scan import register_scan
from monai_probreg.spatial.physical import field_from_itk
from monai_probreg.spatial.volume_io import read_label

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
LPBA40_PAIRS = ("S12:S13", "S15:S17", "S18:S19")  # moving:fixed, training subjects (train.yaml's val_ids excluded)
SYNTH_PAIRS = ("training_seg_01:training_seg_02", "training_seg_03:training_seg_04")
SYNTH_SEED = 0  # the random deformation and contrast of each synthetic head (generalization.synthetic_head)
IDENTITY_SCANS = ("S12",)  # training subjects registered onto an exact copy of themselves
IDENTITY_MAPS = ("training_seg_01",)  # training label maps whose head is registered onto an exact copy of itself
IDENTITY = "identity"  # the name prefix of those cases
# name -> RefinementSettings fields replaced in the bundle's settings
VARIANTS = {
    "network": {"num_iterations": 0},
    "shipped": {},
    "x10 all finer": {"num_iterations": 10, "coarse_iterations": 0},
    "x10 all finer, halving guard only": {"num_iterations": 10, "coarse_iterations": 0, "fold_local_steps": 0},
    "c28of30": {"num_iterations": 30, "coarse_iterations": 28},
    "2mm x10": {"num_iterations": 10, "coarse_iterations": 0, "velocity_grid_factor": 2},
}


def fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def invented_displacement_mm(warp_path: Path, mask: np.ndarray) -> float:
    """Median length (mm) of the displacement ``D(p)`` of ``warp_path`` (the command's ``warp.nii.gz``, LPS mm on the
    fixed grid) over the voxels where ``mask`` (the fixed grid's shape, index order) is true."""
    warp = field_from_itk(itk.imread(str(warp_path))).array  # index order (x, y, z, 3), as read_label's arrays
    if warp.shape[:3] != mask.shape:
        raise ValueError(f"{warp_path}: expected a field of shape {mask.shape} (the mask's); got {warp.shape[:3]}")
    return float(np.median(np.linalg.norm(warp[mask], axis=-1)))


def cases(dataset: Path, label_maps: Path | None, tmp: Path) -> list[tuple[str, Path, Path, Path, Path, list[int]]]:
    """(name, moving, moving_label, fixed, fixed_label, labels) of every pair whose data is here, the identity cases
    (moving and fixed the same files) named ``IDENTITY ...``."""
    out = []
    if dataset.is_dir():
        for sid in IDENTITY_SCANS:
            paths = [dataset / kind / f"{sid}.nii.gz" for kind in ("images", "labels")]
            if all(p.is_file() for p in paths):
                out.append((f"{IDENTITY} lpba40 {sid}", *paths, *paths, []))
        for pair in LPBA40_PAIRS:
            m, f = pair.split(":")
            # moving image, moving labels, fixed image, fixed labels
            paths = [dataset / kind / f"{s}.nii.gz" for s in (m, f) for kind in ("images", "labels")]
            if all(p.is_file() for p in paths):
                labels = [int(v) for v in np.unique(read_label(paths[3]).array) if v > 0]
                out.append((f"lpba40 {m}->{f}", *paths, labels))
    if label_maps is not None:
        heads: dict[str, tuple[Path, Path]] = {}  # each map's head is rendered once, however many cases use it

        def head(name: str) -> tuple[Path, Path]:
            if name not in heads:
                heads[name] = synthetic_head(label_maps / f"{name}.nii.gz", SYNTH_SEED, tmp)
            return heads[name]

        for name in IDENTITY_MAPS:
            if (label_maps / f"{name}.nii.gz").is_file():
                out.append((f"{IDENTITY} synth {name[-2:]}", *head(name), *head(name), []))
        for pair in SYNTH_PAIRS:
            m, f = pair.split(":")
            if all((label_maps / f"{n}.nii.gz").is_file() for n in (m, f)):
                moving, fixed = head(m), head(f)
                out.append((f"synth {m[-2:]}->{f[-2:]}", *moving, *fixed, list(ASEG_LABELS)))
                out.append((f"synth {f[-2:]}->{m[-2:]}", *fixed, *moving, list(ASEG_LABELS)))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model-file", type=Path, default=None)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--label-maps", type=Path, default=None, help="folder with SynthSeg's training_seg_*.nii.gz")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), help="names of VARIANTS, or name=field:value,...")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load_model(model_file=args.model_file)
    unknown = [v for v in args.variants if "=" not in v and v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}: expected one of {list(VARIANTS)} or name=field:value,...")
    variants = dict(parse_variant(v) if "=" in v else (v, VARIANTS[v]) for v in args.variants)
    rows: dict[str, dict] = {
        name: {"per_pair": {}, "identity_mm": {}, "num_folding": 0, "refine_s": []} for name in variants
    }
    with tempfile.TemporaryDirectory(prefix="refinement_levers_") as tmp:
        for name, moving, moving_label, fixed_image, fixed_label, labels in cases(
            args.dataset_dir, args.label_maps, Path(tmp)
        ):
            target = read_label(fixed_label).array
            fixed = prepare_fixed(fixed_image, fixed_label)
            for variant, fields in variants.items():
                options = RegistrationOptions(qc=False, inverse=False, maps=False)
                options = dataclasses.replace(options, refinement=model.refinement.with_fields(**fields))
                out = Path(tmp) / f"{name}_{variant}".replace(" ", "_").replace(">", "")
                start = time.perf_counter()
                summary = register_scan(model, fixed, moving, out, moving_label, options)
                row = rows[variant]
                if name.startswith(IDENTITY):
                    score = row["identity_mm"][name] = invented_displacement_mm(out / "warp.nii.gz", target > 0)
                    what = "invented mm"
                else:
                    score = row["per_pair"][name] = dice(read_label(out / "warped_label.nii.gz").array, target, labels)
                    what = "dice"
                row["num_folding"] += int(summary["jacobian"]["num_nonpositive"])
                row["refine_s"].append(summary["timings_s"].get("refine", 0.0))
                print(f"{name:24s} {variant:12s} {what} {score:.4f} ({time.perf_counter() - start:.1f} s)", flush=True)
    lines = ["| variant | settings | LPBA40 Dice | synthetic Dice | identity: invented mm | folds | refine s |"]
    lines.append("|---|---|---|---|---|---|---|")
    for variant, row in rows.items():
        scores = row["per_pair"]
        lp = [v for k, v in scores.items() if k.startswith("lpba40")]
        sy = [v for k, v in scores.items() if k.startswith("synth")]
        row["lpba40"] = float(np.mean(lp)) if lp else None
        row["synthetic"] = float(np.mean(sy)) if sy else None
        row["identity"] = float(np.mean(list(row["identity_mm"].values()))) if row["identity_mm"] else None
        row["refine_s"] = float(np.mean(row["refine_s"])) if row["refine_s"] else None
        lines.append(
            f"| {variant} | {variants[variant]} | {fmt(row['lpba40'])} | {fmt(row['synthetic'])} | "
            f"{fmt(row['identity'])} | {row['num_folding']} | {fmt(row['refine_s'])} |"
        )
    write_report(
        args.out_dir, "refinement_levers", {"variants": variants, "rows": rows, "threads": args.threads}, lines
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
