"""How far our answer is from ANTs SyN's on a pair without labels: the two fixed -> moving fields, point by point.

For a real scan nobody has labelled (a T2-weighted head of another site onto MNI152, say), no Dice can be computed;
what can be measured is how much two methods disagree. Each row registers ``--moving`` onto ``--fixed`` (default:
the MNI152 template that nilearn ships) with ``monai-probreg register`` in a fresh process (``--contrast same``, or
``other``, or ``other --match-contrast``; lean: ``--no-inverse --no-maps --no-qc``), and ANTs SyN registers the same
files (``ants.registration(fixed, moving, type_of_transform="SyN")``, antspyx's defaults: Mattes mutual information),
its transforms composed into one displacement field on the fixed grid (``ants.apply_transforms(..., compose=...)``).
Both fields are ITK displacement fields, ``p + D(p)`` being the moving point of the fixed point ``p`` (LPS mm), so
their difference ``|D_ours(p) - D_ants(p)|`` is how far apart the two methods send ``p``: its median and 95th
percentile over the fixed image's foreground (above its minimum: the brain of a skull-stripped template) are
reported (:func:`field_disagreement`). Two good registrations of one pair disagree too (two methods, two
regularisers); a pair of the same scanner and contrast, e.g. the raw S20 scan onto the S01 atlas, gives the scale:

    python benchmarks/ants_agreement.py --moving ../shared/data/lpba40-native/S20.nii.gz \\
        --fixed ../shared/data/lpba40/atlas/S01_image.nii.gz --rows same --threads 2 --name ants_agreement_s20
    python benchmarks/ants_agreement.py --moving niivue-demo-images/register/T2w.nii.gz --threads 2

Writes ``OUT_DIR/NAME.json`` (default ``benchmarks/results/ants_agreement.json``) and prints a table; without
antspyx or the moving scan it prints "skipped: ..." and exits 0.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
from common import ANTS_INSTALL_HINT, ants_available, run_command, write_report

from monai_probreg.spatial.volume_io import read_field  # as ITK reads it, so as ANTs does

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "results"
ROWS = {  # row name -> the command's contrast options
    "same": ("--contrast", "same"),
    "other": ("--contrast", "other"),
    "other-matched": ("--contrast", "other", "--match-contrast"),
}
LEAN = ("--no-inverse", "--no-maps", "--no-qc")  # only warp.nii.gz (and the summary) are read


def field_disagreement(ours: np.ndarray, theirs: np.ndarray, inside: np.ndarray) -> dict[str, float]:
    """Median and 95th percentile of ``|ours - theirs|`` (mm) over ``inside``: two displacement fields (*S, 3) of one
    grid (the last axis the vector), ``inside`` (*S) bool. ValueError for shapes that differ or an empty ``inside``."""
    ours, theirs = np.asarray(ours, np.float64), np.asarray(theirs, np.float64)
    inside = np.asarray(inside, bool)
    if ours.shape != theirs.shape or ours.ndim < 2 or ours.shape[:-1] != inside.shape:
        raise ValueError(
            f"expected two (*S, 3) fields and an (*S) mask of one grid; got {ours.shape}, {theirs.shape}, {inside.shape}"
        )
    if not inside.any():
        raise ValueError("the mask selects no voxel")
    distance = np.linalg.norm((ours - theirs)[inside], axis=-1)
    return {"median_mm": float(np.median(distance)), "p95_mm": float(np.percentile(distance, 95))}


def ants_field(fixed: Path, moving: Path, folder: Path) -> tuple[np.ndarray, float]:
    """ANTs SyN's fixed -> moving transforms composed into one displacement field on the fixed grid; (field, seconds
    of the registration call)."""
    import ants

    fixed_image, moving_image = ants.image_read(str(fixed)), ants.image_read(str(moving))
    start = time.perf_counter()
    result = ants.registration(fixed_image, moving_image, type_of_transform="SyN", outprefix=f"{folder}/tx_")
    seconds = time.perf_counter() - start
    composed = ants.apply_transforms(fixed_image, moving_image, result["fwdtransforms"], compose=f"{folder}/warp_")
    return read_field(composed).array, seconds


def run(args: argparse.Namespace) -> dict:
    fixed_args = () if args.fixed is None else ("--fixed", str(args.fixed))
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="ants_agreement_") as tmp:
        root = Path(tmp)
        for row in args.rows:
            out = root / row
            done, wall = run_command(
                "register", "--moving", str(args.moving), *fixed_args, "--out", str(out), "--threads",
                str(args.threads), *LEAN, *ROWS[row],
            )  # fmt: skip
            rows[row] = {"wall_s": round(wall, 2), "warp": out / "warp.nii.gz"}
            print(f"ours {row}: {wall:.1f} s", flush=True)
        fixed_path = Path(args.fixed) if args.fixed is not None else _template()
        theirs, seconds = ants_field(fixed_path, Path(args.moving), root)
        print(f"ANTs SyN: {seconds:.1f} s", flush=True)
        fixed = np.asanyarray(nib.load(str(fixed_path)).dataobj)
        inside = fixed > fixed.min()
        for record in rows.values():
            record.update(field_disagreement(read_field(record.pop("warp")).array, theirs, inside))
    return {
        "moving": str(args.moving),
        "fixed": str(fixed_path),
        "foreground_voxels": int(inside.sum()),
        "ants_syn_seconds": round(seconds, 2),
        "threads": args.threads,
        "rows": rows,
    }


def _template() -> Path:
    from monai_probreg.data.template import mni152_template_path

    return mni152_template_path()


def markdown(result: dict) -> list[str]:
    lines = [
        f"moving {result['moving']} onto {result['fixed']}: |D_ours(p) - D_ANTs SyN(p)| over the fixed foreground",
        "",
        "| ours | median (mm) | 95th percentile (mm) | s (process wall) |",
        "|---|---|---|---|",
    ]
    for row, r in result["rows"].items():
        lines.append(f"| {' '.join(ROWS[row])} | {r['median_mm']:.2f} | {r['p95_mm']:.2f} | {r['wall_s']:.1f} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--moving", type=Path, required=True, help="the scan to register")
    ap.add_argument("--fixed", type=Path, default=None, help="default: the MNI152 template that nilearn ships")
    ap.add_argument("--rows", nargs="+", choices=list(ROWS), default=["same", "other"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--name", default="ants_agreement", help="the record's file name (without .json)")
    args = ap.parse_args(argv)
    missing = [str(p) for p in (args.moving, args.fixed) if p is not None and not Path(p).is_file()]
    if missing:
        print(f"skipped: no {', '.join(missing)}")
        return 0
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)  # ANTs' too; read when ITK first loads
    available, why = ants_available()  # which loads it
    if not available:
        print(f"skipped: {why} ({ANTS_INSTALL_HINT})")
        return 0
    result = run(args)
    write_report(args.out_dir, args.name, result, markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
