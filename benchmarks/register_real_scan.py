"""Real-data check of ``monai-probreg register``: a subject moved out of atlas space comes back to it.

One subject of an LPBA40-layout dataset (default S11, the first of train.yaml's ``val_ids``: never trained on) is
turned into what a scanner would give: a random rotation (uniform in +-15 degrees about each axis) and translation
(+-20 mm per axis) about the atlas centre, resampled (linear; labels nearest neighbour) onto a 0.9 x 1.5 x 0.9 mm grid
of another orientation code ("AIL" instead of LPBA40's "RAS": axes permuted and flipped) covering the moved head,
with intensities in a raw scanner range (int16, 50..3050). Then:

1. **aligned, bundle path**: the original (aligned) subject through evaluate.yaml's preprocessing, ``register_pair``
   and ``score_pair`` (the number evaluate.yaml reports);
2. **aligned, command**: the original subject through ``monai-probreg register`` (in-process; affine included);
3. **misaligned, command**: the moved scan through ``python -m monai_probreg.cli.main register`` in a subprocess, timed
   as a user would time it (Python start-up, imports and model loading included);

and reports mean Dice to the atlas labels of each (target: 3 within 0.02 of 2; 3 also with the subject's original
labels pulled through the moved scan's transform, which leaves out the label map's own nearest-neighbour trip through
the 1.5 mm grid), how far the moved scan's affine is from the known misalignment composed with the aligned
subject's own affine (the subject is not the atlas, so the latter is not the identity; mm over the atlas brain),
ITK's reproduction of our ``warped.nii.gz`` from the moved scan and ``warp.nii.gz`` (``ResampleImageFilter`` +
``DisplacementFieldTransform``; and ``ants.apply_transforms`` when antspyx is importable), and the time by stage.
Writes ``OUT_DIR/register_real_scan.json`` (numbers only; the scans and outputs stay in a temporary folder unless
``--keep-dir``). Without the dataset it prints "skipped: ..." and exits 0.

    python benchmarks/register_real_scan.py --model-file bundle/models/model.pt --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO, ants_available

# index -> LPS direction of the moved scan: axis 0 toward anterior, 1 toward inferior, 2 toward left ("AIL")
DIRECTION = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def misalign(
    image,
    labels,
    atlas,
    rng: np.random.Generator,
    max_rotation: float,
    max_translation: float,
    spacing: Sequence[float],
    margin_mm: float = 10.0,
):
    """(moved image Volume int16, moved labels Volume, true fixed -> moving (4, 4), angles, translation)."""
    from scipy.spatial.transform import Rotation

    from monai_probreg.spatial.physical import apply_affine, grid_points
    from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
    from monai_probreg.spatial.volume_io import Volume

    angles = rng.uniform(-max_rotation, max_rotation, 3)
    translation = rng.uniform(-max_translation, max_translation, 3)
    points = grid_points(atlas.shape, atlas.index_to_lps)
    centre = points.reshape(-1, 3).mean(0)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    truth[:3, 3] = centre - truth[:3, :3] @ centre + translation
    head = apply_affine(truth, points[image.array > 0.01])
    axes = DIRECTION * np.asarray(spacing, dtype=np.float64)
    local = head @ np.linalg.inv(axes).T  # head points in the new grid's index units (before the origin shift)
    low, high = local.min(0) - margin_mm / np.asarray(spacing), local.max(0) + margin_mm / np.asarray(spacing)
    shape = tuple(int(n) for n in np.ceil(high - low) + 1)
    grid = np.eye(4)
    grid[:3, :3] = axes
    grid[:3, 3] = axes @ low
    back = apply_affine(np.linalg.inv(truth), grid_points(shape, grid))
    raw = np.round(sample_linear(image, back) * 3000.0 + 50.0).astype(np.int16)
    moved_labels = sample_nearest(labels, back)
    return Volume(raw, grid), Volume(moved_labels, grid), truth, angles, translation


def aligned_bundle_dice(model, subject: Path, label: Path, atlas: Path, atlas_label: Path, ids: list[int]) -> float:
    """evaluate.yaml's path: registration_transforms -> register_pair -> score_pair."""
    from monai_probreg.data.transforms import registration_transforms
    from monai_probreg.engines.registration import register_pair
    from monai_probreg.metrics.scores import score_pair

    data = registration_transforms(with_labels=True, divisor=model.divisor)(
        {"moving": str(subject), "fixed": str(atlas), "moving_label": str(label), "fixed_label": str(atlas_label)}
    )
    output = register_pair(model.network, data["moving"][None].to(model.device), data["fixed"][None].to(model.device))
    return score_pair(output.displacement, data["moving_label"][None], data["fixed_label"][None], labels=ids).mean_dice


def transform_dice(warp: Path, truth: np.ndarray, labels, atlas_labels, ids: list[int]) -> float:
    """Mean Dice of the subject's ORIGINAL labels pulled through our transform: fixed p -> p + D(p) in the moved
    scan -> truth^-1 -> the original subject (known). One nearest-neighbour resampling, as in the aligned case, so
    the score measures the transform alone, without the label map's own trip through the 1.5 mm grid."""
    import itk

    from monai_probreg.metrics.scores import score_pair
    from monai_probreg.spatial.physical import apply_affine, field_from_itk, grid_points
    from monai_probreg.spatial.point_sampling import sample_nearest

    field = field_from_itk(itk.imread(str(warp)))
    points = grid_points(field.shape, field.index_to_lps) + field.array
    pulled = sample_nearest(labels, apply_affine(np.linalg.inv(truth), points))

    def as_tensor(a):
        return torch.from_numpy(a.astype(np.int64))[None, None]

    return score_pair(None, as_tensor(pulled), as_tensor(atlas_labels.array), labels=ids).mean_dice


def itk_reproduction(moving: Path, moving_label: Path, atlas: Path, out: Path, with_ants: bool) -> dict:
    """Max abs difference between our warped.nii.gz and ITK's (and ANTs') resampling with warp.nii.gz."""
    import itk

    from monai_probreg.spatial.physical import displacement_transform, resample_with_itk

    transform = displacement_transform(itk.imread(str(out / "warp.nii.gz")))
    reference = itk.imread(str(atlas), itk.F)
    ours = itk.array_from_image(itk.imread(str(out / "warped.nii.gz"), itk.F))
    theirs = itk.array_from_image(resample_with_itk(itk.imread(str(moving), itk.F), reference, transform))
    labels = itk.array_from_image(
        resample_with_itk(itk.imread(str(moving_label), itk.SS), reference, transform, nearest=True)
    )
    our_labels = itk.array_from_image(itk.imread(str(out / "warped_label.nii.gz"), itk.SS))
    result = {
        "max_abs_diff": float(np.abs(theirs - ours).max()),
        "intensity_range": float(ours.max() - ours.min()),
        "label_mismatches": int((labels != our_labels).sum()),
        "voxels": int(labels.size),
    }
    if with_ants:
        ok, message = ants_available()
        if not ok:
            result["ants"] = f"skipped: {message}"
        else:
            import ants

            warped = ants.apply_transforms(
                ants.image_read(str(atlas)),
                ants.image_read(str(moving)),
                [str(out / "warp.nii.gz")],
                interpolator="linear",
            ).numpy()
            ours_ants = ants.image_read(str(out / "warped.nii.gz")).numpy()
            result["ants_max_abs_diff"] = float(np.abs(warped - ours_ants).max())
    return result


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET, help="atlas/, images/, labels/")
    ap.add_argument("--subject", default="S11", help="subject id (default: S11, a validation subject)")
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: BUNDLE/models/model.pt, shipped)")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads for torch and ITK (default: all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random misalignment")
    ap.add_argument("--max-rotation", type=float, default=15.0, help="degrees about each axis (default 15)")
    ap.add_argument("--max-translation", type=float, default=20.0, help="mm along each axis (default 20)")
    ap.add_argument("--spacing", type=float, nargs=3, default=[0.9, 1.5, 0.9], help="mm of the moved scan's grid")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where register_real_scan.json goes")
    ap.add_argument("--keep-dir", type=Path, default=None, help="keep the scans and outputs here (default: temp)")
    ap.add_argument("--no-ants", action="store_true", help="skip the antsApplyTransforms check")
    ap.add_argument(
        "--in-process",
        action="store_true",
        help="run the moved scan's command in this process "
        "(faster; its wall time then excludes Python start-up, imports and ITK's module loading)",
    )
    ap.add_argument(
        "--extra",
        nargs=argparse.REMAINDER,
        default=[],
        help="more monai-probreg options, e.g. --extra --affine-levels 2 1 (must come last)",
    )
    args = ap.parse_args(argv)

    dataset = args.dataset_dir.resolve()
    atlas, atlas_label = dataset / "atlas" / "S01_image.nii.gz", dataset / "atlas" / "S01_label.nii.gz"
    if not dataset.is_dir():
        print(f"skipped: dataset not found at {dataset}", flush=True)
        return 0
    atlases = sorted((dataset / "atlas").glob("*_image.nii.gz"))
    atlas = atlases[0] if atlases else atlas
    atlas_label = atlas.with_name(atlas.name.replace("_image", "_label"))
    subject, label = dataset / "images" / f"{args.subject}.nii.gz", dataset / "labels" / f"{args.subject}.nii.gz"

    from monai_probreg.cli.main import main as cli_main
    from monai_probreg.registration.model import load_model
    from monai_probreg.registration.output_folder import write_volume
    from monai_probreg.spatial.physical import apply_affine, grid_points
    from monai_probreg.spatial.volume_io import read_image, read_label

    threads = args.threads or torch.get_num_threads()
    torch.set_num_threads(threads)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(threads)
    model_file = args.model_file or args.bundle_root / "models" / "model.pt"
    common = [
        "--fixed",
        str(atlas),
        "--fixed-label",
        str(atlas_label),
        "--bundle-root",
        str(args.bundle_root),
        "--model-file",
        str(model_file),
        "--threads",
        str(threads),
        *args.extra,
    ]
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep_dir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        atlas_volume, atlas_labels = read_image(atlas), read_label(atlas_label)
        ids = [int(v) for v in np.unique(atlas_labels.array) if v != 0]
        image, labels = read_image(subject), read_label(label)
        image = image.with_array((image.array - image.array.min()) / (image.array.max() - image.array.min()))
        moved, moved_labels, truth, angles, translation = misalign(
            image,
            labels,
            atlas_volume,
            np.random.default_rng(args.seed),
            args.max_rotation,
            args.max_translation,
            args.spacing,
        )
        moved_path = write_volume(work / f"{args.subject}_moved.nii.gz", moved, np.int16)
        moved_label_path = write_volume(work / f"{args.subject}_moved_label.nii.gz", moved_labels, np.int16)
        print(
            f"{args.subject} moved: rotation {np.round(angles, 1).tolist()} deg, translation "
            f"{np.round(translation, 1).tolist()} mm, grid {list(moved.shape)} x {args.spacing} mm "
            f"{read_image(moved_path).axcodes}, intensities {int(moved.array.min())}..{int(moved.array.max())}",
            flush=True,
        )

        start = time.perf_counter()
        argv = [
            "register",
            "--moving",
            str(moved_path),
            "--moving-label",
            str(moved_label_path),
            "--out",
            str(work / "misaligned"),
            *common,
        ]
        if args.in_process:
            if cli_main(argv) != 0:
                return 1
        else:
            done = subprocess.run(
                [sys.executable, "-m", "monai_probreg.cli.main", *argv], capture_output=True, text=True
            )
            if done.returncode != 0:
                print(done.stderr[-3000:], file=sys.stderr)
                return 1
            print(done.stderr.strip() + "\n" + done.stdout.strip(), flush=True)
        wall = time.perf_counter() - start
        misaligned = json.loads((work / "misaligned" / "summary.json").read_text())

        model = load_model(args.bundle_root, model_file, None, "cpu")
        bundle_dice = aligned_bundle_dice(model, subject, label, atlas, atlas_label, ids)
        if (
            cli_main(
                [
                    "register",
                    "--moving",
                    str(subject),
                    "--moving-label",
                    str(label),
                    "--out",
                    str(work / "aligned"),
                    "--no-qc",
                    "--quiet",
                    *common,
                ]
            )
            != 0
        ):
            return 1
        aligned = json.loads((work / "aligned" / "summary.json").read_text())
        reproduction = itk_reproduction(moved_path, moved_label_path, atlas, work / "misaligned", not args.no_ants)
        transform_only = transform_dice(work / "misaligned" / "warp.nii.gz", truth, labels, atlas_labels, ids)

    brain = grid_points(atlas_volume.shape, atlas_volume.index_to_lps)[atlas_labels.array > 0]
    # The subject is not the atlas: the affine of the ALIGNED subject is not the identity. The moved scan's affine must
    # be that one followed by the known misalignment: fixed p -> aligned subject A_aligned(p) -> moved truth(...).
    found = np.asarray(misaligned["affine"]["matrix_fixed_to_moving_lps"])
    expected = truth @ np.asarray(aligned["affine"]["matrix_fixed_to_moving_lps"])
    affine_error = np.linalg.norm(apply_affine(found, brain) - apply_affine(expected, brain), axis=-1)
    difference = misaligned["dice"]["mean"] - aligned["dice"]["mean"]
    result = {
        "subject": args.subject,
        "atlas": str(atlas),
        "model_file": str(model_file),
        "threads": threads,
        "misalignment": {
            "rotation_deg": angles.tolist(),
            "translation_mm": translation.tolist(),
            "grid": list(moved.shape),
            "spacing_mm": list(args.spacing),
            "orientation": read_image(atlas).axcodes + " -> AIL",
            "intensities": "int16, 50..3050",
        },
        "mean_dice": {
            "aligned_bundle_path": bundle_dice,
            "aligned_command": aligned["dice"]["mean"],
            "misaligned_command": misaligned["dice"]["mean"],
            "misaligned_affine_only": misaligned["dice"]["mean_affine_only"],
            "misaligned_transform_original_labels": transform_only,
            "misaligned_minus_aligned_command": difference,
            "target_abs_difference": 0.02,
        },
        "affine_consistency_mm": {
            "mean": float(affine_error.mean()),
            "max": float(affine_error.max()),
            "what": "|A_moved(p) - truth(A_aligned(p))| over the atlas brain voxels",
        },
        "itk_reproduction": reproduction,
        "jacobian_nonpositive": misaligned["jacobian"]["num_nonpositive"],
        "timings_s": {
            **misaligned["timings_s"],
            "command_wall": round(wall, 2),
            "in_process": args.in_process,
            "startup (wall - total)": round(wall - misaligned["timings_s"]["total"], 2),
        },
        "versions": {"python": platform.python_version(), "torch": torch.__version__},
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    from monai_probreg.utils.files import write_text

    write_text(args.out_dir / "register_real_scan.json", json.dumps(result, indent=2) + "\n")
    rows = [
        ("mean Dice, aligned subject, bundle path (evaluate.yaml)", f"{bundle_dice:.4f}"),
        ("mean Dice, aligned subject, monai-probreg register", f"{aligned['dice']['mean']:.4f}"),
        (
            "mean Dice, moved scan, monai-probreg register",
            f"{misaligned['dice']['mean']:.4f} (affine only {misaligned['dice']['mean_affine_only']:.4f})",
        ),
        ("moved - aligned (target: within 0.02)", f"{difference:+.4f}"),
        (
            "mean Dice, subject's original labels through the moved scan's transform",
            f"{transform_only:.4f} ({transform_only - aligned['dice']['mean']:+.4f} vs aligned)",
        ),
        (
            "affine: moved scan vs misalignment o aligned scan's (mm, brain)",
            f"mean {affine_error.mean():.2f}, max {affine_error.max():.2f}",
        ),
        (
            "ITK reproduction of warped.nii.gz, max |diff|",
            f"{reproduction['max_abs_diff']:.3g} (range {reproduction['intensity_range']:.0f})",
        ),
        (
            "ITK reproduction of warped_label.nii.gz",
            f"{reproduction['label_mismatches']} of {reproduction['voxels']} voxels differ",
        ),
        ("|J| <= 0 voxels (moved scan)", str(misaligned["jacobian"]["num_nonpositive"])),
        ("command wall time (s)", f"{wall:.1f}"),
        *[(f"  stage {k} (s)", f"{v:.1f}") for k, v in misaligned["timings_s"].items()],
    ]
    if "ants_max_abs_diff" in reproduction:
        rows.insert(7, ("antsApplyTransforms reproduction, max |diff|", f"{reproduction['ants_max_abs_diff']:.3g}"))
    width = max(len(r[0]) for r in rows)
    print("\n".join(f"| {name:<{width}} | {value} |" for name, value in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
