"""Where there is nothing to register: does the whole command leave the identity (or the known rigid motion) alone?

Users register follow-up scans of one subject and images that are already aligned. Each case is registered by the
whole command (``monai-probreg register``, the default path: affine, network, refinement) and scored against the
transform it must find:

- ``template onto itself``: the MNI152 template nilearn ships as the moving scan, with no ``--fixed`` (the template
  is the default fixed image): the answer is the identity;
- ``template moved (header)``: the template whose header is turned by ``--degrees`` about an oblique axis and
  shifted by ``--shift-mm`` (the voxels untouched), onto the template: the answer is that rigid motion;
- ``SXX moved (header)``: the same for an LPBA40 validation scan (``--subject``, default S11) onto itself (needs
  ``../shared/data/lpba40``; skipped without it).

Score: the error of ``warp.nii.gz`` (fixed -> moving, LPS mm, on the fixed grid) against the true displacement,
median and 95th percentile over the fixed image's brain (its labels, or the template's nonzero voxels); the
command's own warning (the quality estimate's, none expected) with its predicted Dice and failure probability (two
unrelated pairs should not get the same answer to many digits); the refinement's and the whole command's seconds.

    python benchmarks/identity_cases.py --threads 2     # table + benchmarks/results/identity_cases.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import itk
import nibabel as nib
import numpy as np
from common import DEFAULT_DATASET, DEFAULT_OUT, run_command, write_report

from monai_probreg.data.template import mni152_template_path
from monai_probreg.fitting.command_cases import moved_header  # the header moved, the voxels untouched
from monai_probreg.spatial.physical import apply_affine, field_from_itk, grid_points
from monai_probreg.spatial.volume_io import read_image, read_label

TURN_AXIS_RAS = (1.0, 2.0, 3.0)  # an oblique axis (normalised): the turn is not about one image axis
SHIFT_DIRECTION_RAS = (2.0, -1.0, 2.0)  # the shift's direction (normalised)
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse


def rigid_motion_ras(degrees: float, shift_mm: float, centre: np.ndarray) -> np.ndarray:
    """(4, 4) RAS world transform: a turn by ``degrees`` about :data:`TURN_AXIS_RAS` through ``centre``, then a shift
    of ``shift_mm`` along :data:`SHIFT_DIRECTION_RAS` (Rodrigues' formula)."""
    axis = np.asarray(TURN_AXIS_RAS) / np.linalg.norm(TURN_AXIS_RAS)
    angle = math.radians(degrees)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
    shift = shift_mm * np.asarray(SHIFT_DIRECTION_RAS) / np.linalg.norm(SHIFT_DIRECTION_RAS)
    motion = np.eye(4)
    motion[:3, :3] = rotation
    motion[:3, 3] = centre - rotation @ centre + shift
    return motion


def grid_centre_ras(scan: Path) -> np.ndarray:
    image = nib.load(scan)
    return (image.affine @ np.r_[(np.asarray(image.shape[:3]) - 1) / 2, 1.0])[:3]


def warp_error_mm(warp_path: Path, motion_ras: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(median, 95th percentile) over ``mask`` (the fixed grid, index order) of the length of ``warp.nii.gz``'s
    displacement minus the true one, ``M x - x`` with ``M`` = ``motion_ras`` in LPS."""
    warp = field_from_itk(itk.imread(str(warp_path)))
    if warp.array.shape[:3] != mask.shape:
        raise ValueError(
            f"{warp_path}: expected a field of shape {mask.shape} (the mask's); got {warp.array.shape[:3]}"
        )
    points = grid_points(mask.shape, warp.index_to_lps)[mask]
    truth = apply_affine(LPS_FROM_RAS @ motion_ras @ LPS_FROM_RAS, points) - points
    error = np.linalg.norm(warp.array[mask] - truth, axis=-1)
    return float(np.median(error)), float(np.percentile(error, 95))


def register(moving: Path, fixed: Path | None, out: Path, threads: int) -> tuple[dict, float]:
    args = ["--moving", str(moving), "--out", str(out), "--threads", str(threads), "--quiet", "--no-qc"]
    if fixed is not None:
        args += ["--fixed", str(fixed)]
    _, wall = run_command("register", *args)
    return json.loads((out / "summary.json").read_text()), wall


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--subject", default="S11", help="LPBA40 validation subject moved by its header onto itself")
    ap.add_argument("--degrees", type=float, default=4.0, help="the rigid motion's turn")
    ap.add_argument("--shift-mm", type=float, default=4.0, help="the rigid motion's shift")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    template = Path(mni152_template_path())
    template_brain = read_image(template).array > 0
    # name -> (moving scan or None for the fixed itself, fixed scan or None for the default template, motion, brain)
    rows = []
    with tempfile.TemporaryDirectory(prefix="identity_cases_") as tmp:
        motion = rigid_motion_ras(args.degrees, args.shift_mm, grid_centre_ras(template))
        cases = [
            ("template onto itself", template, None, np.eye(4), template_brain),
            ("template moved (header)", moved_header(template, motion, Path(tmp) / "template_moved.nii.gz"), None,
             motion, template_brain),
        ]  # fmt: skip
        scan = args.dataset_dir / "images" / f"{args.subject}.nii.gz"
        labels = args.dataset_dir / "labels" / f"{args.subject}.nii.gz"
        if scan.is_file() and labels.is_file():
            motion = rigid_motion_ras(args.degrees, args.shift_mm, grid_centre_ras(scan))
            moved = moved_header(scan, motion, Path(tmp) / f"{args.subject}_moved.nii.gz")
            cases.append((f"{args.subject} moved (header)", moved, scan, motion, read_label(labels).array > 0))
        else:
            print(f"skipped the LPBA40 case: {scan} or {labels} not found", flush=True)
        for n, (name, moving, fixed, truth, brain) in enumerate(cases):
            out = Path(tmp) / f"case{n}"
            summary, wall = register(moving, fixed, out, args.threads)
            median, p95 = warp_error_mm(out / "warp.nii.gz", truth, brain)
            row = {
                "case": name,
                "median_error_mm": median,
                "p95_error_mm": p95,
                "warning": summary["warning"],
                "num_folded": int(summary["jacobian"]["num_nonpositive"]),
                "refine_s": summary["timings_s"].get("refine", 0.0),
                "command_s": wall,
                # the quality estimate (None without a quality model): its answer should depend on the pair
                "predicted_dice": (summary["quality"] or {}).get("predicted_dice"),
                "failure_probability": (summary["quality"] or {}).get("failure_probability"),
            }
            rows.append(row)
            print(f"{name}: median {median:.3f} mm, p95 {p95:.3f} mm, warning {row['warning']}", flush=True)
    lines = [
        "| case | median error, mm | 95th pct, mm | warning | folded voxels | predicted Dice | failure probability | "
        "refine s | command s |"
    ]
    lines.append("|---|---|---|---|---|---|---|---|---|")

    def number(value: float | None, digits: str) -> str:
        return "–" if value is None else format(value, digits)

    for r in rows:
        lines.append(
            f"| {r['case']} | {r['median_error_mm']:.3f} | {r['p95_error_mm']:.3f} | {r['warning'] or 'none'} | "
            f"{r['num_folded']} | {number(r['predicted_dice'], '.4f')} | {number(r['failure_probability'], '.2e')} | "
            f"{r['refine_s']:.1f} | {r['command_s']:.1f} |"
        )
    result = {"rows": rows, "degrees": args.degrees, "shift_mm": args.shift_mm, "threads": args.threads}
    write_report(args.out_dir, "identity_cases", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
