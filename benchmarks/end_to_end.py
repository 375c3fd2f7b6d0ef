"""End-to-end benchmark on native scans: the whole command against ANTs, side by side in one run.

Each labelled native scan of ``--native-dir`` (default ``../shared/data/lpba40-native``: S20, raw, unaligned, with
its 48 cortical labels) is registered onto the atlas of ``--dataset-dir`` (default ``../shared/data/lpba40``: S01
and its labels) by
  - "ours": ``python -m monai_probreg.cli.main register --moving M --moving-label L --fixed A --fixed-label AL``
    in a fresh subprocess (wall time from process start to exit: imports, model, affine, network, outputs, QC);
  - "ours, again": the same command a second time: its warp.nii.gz and affine.tfm must be byte-identical to the
    first run's (issue "Same input, same output");
  - "ours, lean": with ``--no-inverse --no-maps --no-qc`` (the warp, the warped scan and labels, affine.tfm and
    the summary only);
  - "ours, ITK affine": with ``--affine-backend itk`` (ITK's v4 registration, metric in one work unit), and again
    with ``--nondeterministic-affine`` (ITK's metric multi-threaded): against it, the cost of determinism of the
    ITK backend; the default torch backend is deterministic with any number of threads;
  - "ours + refinement": the same with ``--refine N`` (:mod:`monai_probreg.engines.refinement`);
  - "ANTs Affine" and "ANTs SyN" (antspyx, ``ants.registration(fixed, moving, type_of_transform=...)`` on the raw
    files, the SyN call with its own affine stages), labels through ``ants.apply_transforms(...,
    interpolator="nearestNeighbor")``; time = the registration call (no process start, no file writing). Rows say
    "skipped" when antspyx cannot be imported (``pip install -e ".[bench]"``);
  - "ANTs SyN, whole process": the same SyN as a fresh process (:data:`ANTS_WHOLE_SCRIPT`: import, read, register,
    the labels and the composite warp written), the counterpart of our command's process wall.
The ratios: our command's process wall against both SyN rows, and ``register-batch``'s whole-process seconds per scan
against both.
Dice: per label on the atlas grid, over the labels both label maps have (S20: 48), and their mean; for ours also
after the affine alone (the command's ``summary.json``). Writes ``OUT_DIR/end_to_end.json`` and prints a table.
Without the data it prints "skipped: ..." and exits 0.

``register-batch`` over ``--batch-size`` aligned scans of ``--dataset-dir``'s images/ (model and atlas loaded
once): scans per minute after start-up (from the scans' own stage totals) and over the whole process.
Writes ``end_to_end.png``: each variant's wall time as stacked stages, "start-up" being the process wall time
outside the stages (imports, model, reading and preparing the fixed image).

With ``--synthetic S`` (default S11, a validation subject), subject S of ``--dataset-dir`` moved away from atlas
space by a seeded rigid transform (up to 15 degrees and 20 mm per axis) and resampled onto a 0.9 x 1.5 x 0.9 mm AIL
grid as raw int16 (``register_real_scan.misalign``) is one more scan, with its 56 labels.

    python benchmarks/end_to_end.py --threads 2
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_NATIVE, DEFAULT_OUT, DEFAULT_REFINE_ITERATIONS, ants_available, run_command

import monai_probreg
from monai_probreg.data.dataset import index_dataset
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.utils.files import write_text

ANTS_TYPES = {"ants_affine": "Affine", "ants_syn": "SyN"}
LEAN = ("--no-inverse", "--no-maps", "--no-qc")
DEFAULT_BATCH_SIZE = 8  # register-batch throughput over this many scans (the issue asks for >= 8)
STAGES = ("read", "affine", "resample", "model", "refine", "maps", "samples", "quality", "compose", "qc", "write")
# the floor of start-up: fresh processes that only import (each is timed from process start to exit)
IMPORT_FLOOR = {
    "python": "pass",
    "torch": "import torch",
    "monai": "import monai",
    "the command's modules": "import monai_probreg.registration.scan",
}
REPRODUCED_FILES = ("warp.nii.gz", "affine.tfm")  # compared byte for byte between "ours" and "ours, again"


def file_digests(folder: Path) -> dict[str, str]:
    return {name: hashlib.sha256((folder / name).read_bytes()).hexdigest() for name in REPRODUCED_FILES}


def native_scans(native_dir: Path) -> list[tuple[str, Path, Path]]:
    """(id, scan, labels) of every ``<id>.nii.gz`` with an ``<id>_labels.nii.gz`` next to it."""
    found = []
    for scan in sorted(native_dir.glob("*.nii.gz")):
        sid = scan.name[: -len(".nii.gz")]
        labels = native_dir / f"{sid}_labels.nii.gz"
        if not sid.endswith("_labels") and labels.is_file():
            found.append((sid, scan, labels))
    return found


def atlas_files(dataset_dir: Path) -> tuple[Path, Path]:
    index = index_dataset(dataset_dir)
    if index.atlas_label is None:
        raise SystemExit(f"the atlas of {dataset_dir} has no label map: Dice needs one")
    return index.atlas_image, index.atlas_label


def shared_dice(warped_label: np.ndarray, fixed_label: np.ndarray, moving_ids: set[int]) -> dict:
    """Dice per label over the labels of both maps (the moving map's ids before warping), with the package's rule."""
    ids = sorted(moving_ids & {int(v) for v in np.unique(fixed_label) if v != 0})
    per_label = label_dice(
        torch.from_numpy(np.rint(warped_label).astype(np.int64)), torch.from_numpy(fixed_label.astype(np.int64)), ids
    )
    return {
        "mean": mean_dice(per_label),
        "num_labels": len(ids),
        "per_label": {str(k): v for k, v in per_label.items()},
    }


def run_ours(
    scan: Path, labels: Path, atlas: Path, atlas_label: Path, out: Path, threads: int, extra: Sequence[str] = ()
) -> dict:
    """The command in a fresh process; its summary.json plus the process wall time."""
    _, wall = run_command(
        "register",
        *(
            "--moving",
            str(scan),
            "--moving-label",
            str(labels),
            "--fixed",
            str(atlas),
            "--fixed-label",
            str(atlas_label),
        ),
        *("--out", str(out), "--threads", str(threads), "--quiet", *extra),
    )
    summary = json.loads((out / "summary.json").read_text())
    return {"wall_s": wall, "summary": summary}


def run_ants(kind: str, scan: Path, labels: Path, atlas: Path) -> tuple[np.ndarray, float]:
    """ANTs ``kind`` ("Affine" or "SyN") of the raw scan onto the atlas: (labels on the atlas grid, seconds)."""
    import ants

    fixed, moving = ants.image_read(str(atlas)), ants.image_read(str(scan))
    with tempfile.TemporaryDirectory(prefix="ants_e2e_") as tmp:
        start = time.perf_counter()
        result = ants.registration(fixed, moving, type_of_transform=kind, outprefix=f"{tmp}/tx_")
        seconds = time.perf_counter() - start
        warped = ants.apply_transforms(
            fixed, ants.image_read(str(labels)), result["fwdtransforms"], interpolator="nearestNeighbor"
        )
    return warped.numpy(), seconds


# ANTs SyN as a user runs it from Python, whole: a fresh process that imports antspyx, reads both scans, registers,
# carries the labels through the transforms and writes them and the composite warp (what our command does for these)
ANTS_WHOLE_SCRIPT = """
import sys, ants
atlas, scan, labels, out = sys.argv[1:5]
fixed, moving = ants.image_read(atlas), ants.image_read(scan)
result = ants.registration(fixed, moving, type_of_transform="SyN", outprefix=out + "/tx_")
warped = ants.apply_transforms(fixed, ants.image_read(labels), result["fwdtransforms"], interpolator="nearestNeighbor")
ants.image_write(warped, out + "/warped_label.nii.gz")
ants.apply_transforms(fixed, moving, result["fwdtransforms"], compose=out + "/warp_")
"""


def run_ants_whole(scan: Path, labels: Path, atlas: Path, threads: int) -> tuple[np.ndarray, float]:
    """ANTs SyN as a whole process (:data:`ANTS_WHOLE_SCRIPT`, ITK on ``threads`` threads): (labels on the atlas
    grid, wall seconds from process start to exit)."""
    with tempfile.TemporaryDirectory(prefix="ants_whole_") as tmp:
        env = {**os.environ, "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS": str(threads)}
        cmd = [sys.executable, "-c", ANTS_WHOLE_SCRIPT, str(atlas), str(scan), str(labels), tmp]
        start = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            raise RuntimeError(f"ANTs SyN, whole process, failed ({done.returncode}): {done.stderr[-2000:]}")
        return np.asanyarray(nib.load(f"{tmp}/warped_label.nii.gz").dataobj), wall


def synthetic_scan(dataset_dir: Path, subject: str, atlas: Path, folder: Path) -> tuple[str, Path, Path]:
    """``subject`` moved out of atlas space and resampled as a raw scan (module docstring); (id, scan, labels)."""
    from register_real_scan import misalign  # benchmarks/ is this script's folder

    from monai_probreg.registration.output_folder import write_volume
    from monai_probreg.spatial.volume_io import read_image, read_label

    index = index_dataset(dataset_dir)
    image, labels = read_image(index.images[subject]), read_label(index.labels[subject])
    image = image.with_array((image.array - image.array.min()) / (image.array.max() - image.array.min()))
    moved, moved_labels, _, angles, translation = misalign(
        image, labels, read_image(atlas), np.random.default_rng(0), 15.0, 20.0, (0.9, 1.5, 0.9)
    )
    sid = f"{subject}_moved"
    print(
        f"{sid}: rotation {np.round(angles, 1).tolist()} deg, translation {np.round(translation, 1).tolist()} mm, "
        f"grid {list(moved.shape)}",
        flush=True,
    )
    return (
        sid,
        write_volume(folder / f"{sid}.nii.gz", moved, np.int16),
        write_volume(folder / f"{sid}_labels.nii.gz", moved_labels, np.int16),
    )


def run_batch(dataset_dir: Path, atlas: Path, threads: int, size: int) -> dict | None:
    """``register-batch`` over the first ``size`` images of ``dataset_dir`` (aligned scans; the affine stage runs
    as for any scan) in a fresh process; throughput after start-up from the scans' stage totals."""
    found = index_dataset(dataset_dir).images
    images = [found[sid] for sid in sorted(found)][:size]
    if len(images) < size:
        print(f"register-batch: skipped, {len(images)} images in {dataset_dir} (< {size})", flush=True)
        return None
    with tempfile.TemporaryDirectory(prefix="e2e_batch_") as tmp:
        scans = Path(tmp) / "scans"
        scans.mkdir()
        for image in images:
            (scans / Path(image).name).symlink_to(image)
        _, wall = run_command(
            "register-batch",
            *(
                "--moving",
                str(scans),
                "--fixed",
                str(atlas),
                "--out",
                f"{tmp}/out",
                "--threads",
                str(threads),
                "--quiet",
            ),
        )
        totals = [json.loads(p.read_text())["timings_s"]["total"] for p in Path(tmp, "out").glob("*/summary.json")]
    return {
        "num_scans": len(totals),
        "wall_s": wall,
        "scan_totals_s": totals,
        "scans_per_minute": 60.0 * len(totals) / sum(totals),
        "scans_per_minute_whole": 60.0 * len(totals) / wall,
    }


def import_floor(repeats: int = 3) -> dict[str, float]:
    """Seconds (median of ``repeats`` fresh processes) to start Python, import a module and exit: what the
    command pays before its first stage, whatever it does (:data:`IMPORT_FLOOR`)."""
    floor = {}
    for name, code in IMPORT_FLOOR.items():
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], check=True)
            times.append(time.perf_counter() - start)
        floor[name] = float(np.median(times))
    return floor


def row_names(refine_iterations: int) -> dict[str, str]:
    """Table and figure labels of the rows."""
    return {
        "ours": "ours (command, process wall)",
        "ours_again": "ours, again (same files as the first run?)",
        "ours_lean": "ours, lean (" + " ".join(LEAN) + ")",
        "ours_itk": "ours, --affine-backend itk",
        "ours_itk_nondeterministic": "ours, --affine-backend itk --nondeterministic-affine",
        "ours_refined": f"ours + refinement ({refine_iterations} steps)",
        "ants_affine": "ANTs Affine (registration call)",
        "ants_syn": "ANTs SyN (registration call)",
        "ants_syn_whole": "ANTs SyN (whole process: import, read, register, labels and warp written)",
    }


def stage_figure(rows: dict, names: dict, path: Path) -> Path:
    """Stacked stage times of each of our variants (first scan), start-up = wall - the stages' total."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in rows if k.startswith("ours")]
    fig, ax = plt.subplots(figsize=(10, 0.6 * len(keys) + 2.2))
    colours = dict(zip(("start-up", *STAGES), plt.get_cmap("tab20").colors))
    labelled: set[str] = set()
    for row, key in enumerate(keys):
        r = next(iter(rows[key].values()))
        left = 0.0
        parts = [("start-up", r["wall_s"] - r["stages_s"]["total"])] + [
            (s, r["stages_s"][s]) for s in STAGES if s in r["stages_s"]
        ]
        for stage, seconds in parts:
            ax.barh(row, seconds, left=left, color=colours[stage], label=None if stage in labelled else stage)
            labelled.add(stage)
            left += seconds
        ax.text(left + 0.3, row, f"{r['wall_s']:.1f} s", va="center")
    ax.set_yticks(range(len(keys)), [names[k] for k in keys])
    ax.invert_yaxis()
    ax.set_xlabel("seconds (process wall, 2 threads)")
    ax.legend(ncol=6, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12 - 0.3 / len(keys)))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET, help="its atlas/ is the fixed image")
    ap.add_argument("--native-dir", type=Path, default=DEFAULT_NATIVE, help="native scans with <id>_labels.nii.gz")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where end_to_end.json goes")
    ap.add_argument("--threads", type=int, default=2, help="threads for every tool (default: %(default)s)")
    ap.add_argument(
        "--refine-iterations",
        type=int,
        default=DEFAULT_REFINE_ITERATIONS,
        help="--refine of the 'ours + refinement' row (default: %(default)s)",
    )
    ap.add_argument("--no-ants", action="store_true", help="leave the ANTs rows out")
    ap.add_argument(
        "--synthetic",
        default="S11",
        help="subject moved and resampled as one more scan ('' for none; default: %(default)s)",
    )
    ap.add_argument(
        "--batch-size",
        type=int,
        default=DEFAULT_BATCH_SIZE,
        help="scans for the register-batch throughput (0: leave it out; default: %(default)s)",
    )
    args = ap.parse_args(argv)
    for folder in (args.dataset_dir, args.native_dir):
        if not folder.resolve().is_dir():
            print(f"skipped: dataset not found at {folder.resolve()}", flush=True)
            return 0
    scans = native_scans(args.native_dir.resolve())
    if not scans:
        print(f"skipped: no labelled native scan in {args.native_dir.resolve()}", flush=True)
        return 0
    atlas, atlas_label = atlas_files(args.dataset_dir.resolve())
    fixed_label = np.asanyarray(nib.load(atlas_label).dataobj)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)
    antspyx = None
    if not args.no_ants:
        ok, message = ants_available()  # loads antspyx now, not inside a timed run
        antspyx = message if ok else f"skipped: {message}"

    rows: dict[str, dict] = {}
    work = tempfile.TemporaryDirectory(prefix="e2e_scans_")
    if args.synthetic:
        scans.append(synthetic_scan(args.dataset_dir.resolve(), args.synthetic, atlas, Path(work.name)))
    for sid, scan, labels in scans:
        moving_ids = {int(v) for v in np.unique(np.asanyarray(nib.load(labels).dataobj)) if v != 0}
        with tempfile.TemporaryDirectory(prefix="e2e_") as tmp:
            variants = (
                ("ours", []),
                ("ours_again", []),
                ("ours_lean", list(LEAN)),
                ("ours_itk", ["--affine-backend", "itk"]),
                ("ours_itk_nondeterministic", ["--affine-backend", "itk", "--nondeterministic-affine"]),
                ("ours_refined", ["--refine", str(args.refine_iterations)]),
            )
            for key, extra in variants:
                out = Path(tmp) / key
                ran = run_ours(scan, labels, atlas, atlas_label, out, args.threads, extra)
                warped = np.asanyarray(nib.load(out / "warped_label.nii.gz").dataobj)
                summary = ran["summary"]
                rows.setdefault(key, {})[sid] = {
                    "dice": shared_dice(warped, fixed_label, moving_ids),
                    "dice_affine_only": summary["dice"]["mean_affine_only"],
                    "dice_command_summary": summary["dice"]["mean"],
                    "num_folding": summary["jacobian"]["num_nonpositive"],
                    "wall_s": ran["wall_s"],
                    "stages_s": summary["timings_s"],
                    "sha256": file_digests(out),
                }
                print(
                    f"{sid} {key}: Dice {rows[key][sid]['dice']['mean']:.3f} (affine only "
                    f"{rows[key][sid]['dice_affine_only']:.3f}), |J|<=0 {rows[key][sid]['num_folding']}, "
                    f"{ran['wall_s']:.1f} s wall",
                    flush=True,
                )
        for key, kind in ANTS_TYPES.items():
            if antspyx is None or antspyx.startswith("skipped"):
                continue
            warped, seconds = run_ants(kind, scan, labels, atlas)
            rows.setdefault(key, {})[sid] = {"dice": shared_dice(warped, fixed_label, moving_ids), "wall_s": seconds}
            print(f"{sid} ANTs {kind}: Dice {rows[key][sid]['dice']['mean']:.3f}, {seconds:.1f} s", flush=True)
        if antspyx is not None and not antspyx.startswith("skipped"):
            warped, seconds = run_ants_whole(scan, labels, atlas, args.threads)
            rows.setdefault("ants_syn_whole", {})[sid] = {
                "dice": shared_dice(warped, fixed_label, moving_ids),
                "wall_s": seconds,
            }
            print(f"{sid} ANTs SyN, whole process: {seconds:.1f} s", flush=True)

    work.cleanup()
    for sid, again in rows.get("ours_again", {}).items():
        again["identical_to_first_run"] = again["sha256"] == rows["ours"][sid]["sha256"]
    names = row_names(args.refine_iterations)
    lines = [
        "| scan | method | mean Dice (labels of both maps) | affine-only Dice | \\|J\\|<=0 | s |",
        "|---|---|---|---|---|---|",
    ]
    for key, per_scan in rows.items():
        for sid, r in per_scan.items():
            affine = f"{r['dice_affine_only']:.3f}" if "dice_affine_only" in r else "–"
            folding = r.get("num_folding", "–")
            same = {True: ": identical", False: ": DIFFERENT"}.get(r.get("identical_to_first_run"), "")
            lines.append(
                f"| {sid} | {names[key]}{same} | {r['dice']['mean']:.3f} ({r['dice']['num_labels']} labels) | "
                f"{affine} | {folding} | {r['wall_s']:.1f} |"
            )
    if antspyx is not None and antspyx.startswith("skipped"):
        lines.append(f"| all | ANTs | {antspyx} | | | |")
    for sid, r in rows.get("ours_itk_nondeterministic", {}).items():
        lines.append(
            f"| {sid} | ITK backend's cost of determinism: one work unit / multi-threaded, process wall | "
            f"{rows['ours_itk'][sid]['wall_s'] / r['wall_s']:.2f}x | affine stage "
            f"{rows['ours_itk'][sid]['stages_s']['affine'] / r['stages_s']['affine']:.2f}x | | |"
        )
        lines.append(
            f"| {sid} | ours (torch affine, deterministic) / ITK multi-threaded, process wall | "
            f"{rows['ours'][sid]['wall_s'] / r['wall_s']:.2f}x | affine stage "
            f"{rows['ours'][sid]['stages_s']['affine'] / r['stages_s']['affine']:.2f}x | | |"
        )
    for base in ("ants_syn", "ants_syn_whole"):
        for sid, r in rows.get(base, {}).items():
            for key in ("ours", "ours_lean"):
                if sid in rows.get(key, {}):
                    ratio = r["wall_s"] / rows[key][sid]["wall_s"]
                    lines.append(f"| {sid} | {names[key]}: faster than {names[base]} by | {ratio:.1f}x | | | |")
    batch = run_batch(args.dataset_dir.resolve(), atlas, args.threads, args.batch_size) if args.batch_size else None
    if batch is not None:
        lines.append(
            f"| {batch['num_scans']} aligned scans | register-batch: {batch['scans_per_minute']:.1f} scans/min "
            f"after start-up ({batch['scans_per_minute_whole']:.1f} over the whole process) | | | | "
            f"{batch['wall_s']:.1f} |"
        )
        per_scan = batch["wall_s"] / batch["num_scans"]
        for base in ("ants_syn", "ants_syn_whole"):
            for sid, r in rows.get(base, {}).items():
                lines.append(
                    f"| {sid} | register-batch, per scan over the whole process ({per_scan:.1f} s): faster than "
                    f"{names[base]} by | {r['wall_s'] / per_scan:.1f}x | | | |"
                )
    floor = import_floor()
    lines.append(
        "| floor | fresh process, import and exit: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in floor.items())
        + " | | | | |"
    )
    table = "\n".join(lines)
    result = {
        "import_floor_s": floor,
        "atlas": str(atlas),
        "atlas_label": str(atlas_label),
        "scans": [str(s) for _, s, _ in scans],
        "threads": args.threads,
        "refine_iterations": args.refine_iterations,
        "rows": rows,
        "batch": batch,
        "markdown": table,
        "versions": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "monai_probreg": monai_probreg.__version__,
            "antspyx": antspyx,
            "platform": platform.platform(),
        },
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = write_text(args.out_dir / "end_to_end.json", json.dumps(result, indent=2) + "\n")
    figure = stage_figure(rows, names, args.out_dir / "end_to_end.png")
    print(f"\n{table}\n\nwrote {path} and {figure}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
