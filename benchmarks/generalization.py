"""Beyond LPBA40: the network alone, the network refined per pair and ANTs SyN, side by side in one run, on four kinds of data.

The model was trained on LPBA40's anatomy and intensities; users bring other scanners, sites and datasets. Methods
(every one through the code path a user runs; ``--model-files`` compares several weights in the same run):

- "network": the weights' posterior mean, no refinement (``--refine 0``);
- "refined": the posterior mean refined per pair (``--refine-iterations`` steps, 10 by default: ``--refine 10``; the
  bundle's other refinement settings, :mod:`monai_probreg.engines.refinement`);
- "ANTs SyN": ``ants.registration(fixed, moving, type_of_transform="SyN")``, antspyx defaults (``.[bench]``);
- ``--refined-variants NAME=FIELD:VALUE,...``: more refined rows, each the default's refinement with
  :class:`~monai_probreg.engines.refinement.RefinementSettings` fields replaced (e.g. ``image_grid_factor:2``).

Parts (``--parts``):

(a) ``demo``: ``monai-probreg demo``'s subjects (the MNI152 template moved by a known transform, seeds 0-2):
    median and 95th-percentile displacement error in the brain, the affine stage's median, 95% coverage
    (``benchmarks/demo_recovery.py``'s cases);
(b) ``native``: the raw S20 scan with its skull onto the MNI152 template, no ``--fixed`` (the whole command):
    normalised cross-correlation of the warped scan with the template inside the template's brain, folded voxels,
    the whole command's wall time (read, align, register, write) against ANTs SyN whole (read, register, resample,
    write);
(c) ``synthetic``: heads rendered T1-like (:func:`monai_probreg.cli.synth_space.render_head`) from two whole-head
    label maps no training run saw (SynthSeg's ``training_seg_11`` and ``_12`` by default), each deformed by a
    random smooth diffeomorphism per seed, cropped to the head, skull and scalp kept; each registered onto the other
    with its labels (``register --fixed``): Dice over FreeSurfer's aseg structures
    (:data:`~monai_probreg.data.label_synthesis.ASEG_LABELS`), folded voxels;
(d) ``lpba40``: ``benchmarks/accuracy_table.py`` on the validation subjects (-> S01 and the pairs between them).

    python benchmarks/generalization.py --threads 2 --label-maps SynthSeg/data/training_label_maps
    python benchmarks/generalization.py --parts demo native --model-files bundle/models/model.pt runs/x/model.pt
    python benchmarks/generalization.py --threads 1 --jobs 2 ...   # the parts in two processes, one table

A part whose data is missing (LPBA40, the native scans, the label maps) is skipped with a line that says so.
Prints one table and writes ``OUT_DIR/generalization.{json,png}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib.metadata
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import accuracy_table
import numpy as np
import torch
from common import parse_variant
from demo_recovery import ants_case, one_case

from monai_probreg.cli.synth_space import render_head
from monai_probreg.data.augmentation import RandDiffeomorphicd
from monai_probreg.data.label_synthesis import ASEG_LABELS, T1_LIKE
from monai_probreg.data.synthetic import SyntheticSettings
from monai_probreg.data.template import mni152_template_path
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.metrics.dice import label_dice
from monai_probreg.registration.demo import DEMO_SAMPLES
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_folder import label_dtype, write_volume
from monai_probreg.registration.scan import register_scan
from monai_probreg.spatial.volume_io import Volume, read_image, read_label
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import file_sha256, library_versions

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "results"
DEFAULT_NATIVE = REPO.parent / "shared" / "data" / "lpba40-native"
PARTS = ("demo", "native", "synthetic", "lpba40")
DEMO_SEEDS = (0, 1, 2)
NATIVE_SCAN = "S20"
SYNTH_MAPS = ("training_seg_11", "training_seg_12")  # never in a training run (train_synth.yaml uses 01-10)
SYNTH_SEEDS = (0, 1)
SYNTH_DEFORM_RMS_MM = 2.5  # the random deformation of each synthetic head: RMS velocity, mm (1 mm voxels)
SYNTH_DEFORM_SPACING_MM = 16.0  # its control-point spacing, mm (the demo's)
SYNTH_CROP_MARGIN = 8  # voxels kept around the head's bounding box (a scanner's field of view)
EXTRA_CEREBRAL_FROM = 500  # SynthSeg's maps: labels from 500 on are outside the brain (skull, scalp, eyes...)
ANTS_CALL = 'ants.registration(fixed, moving, type_of_transform="SyN")'


def dice(warped: np.ndarray, fixed: np.ndarray, labels: Sequence[int]) -> float:
    """Mean Dice over the ``labels`` present in both maps (:func:`monai_probreg.metrics.dice.label_dice`)."""
    present = set(np.unique(warped).tolist()) & set(np.unique(fixed).tolist())
    scored = [int(v) for v in labels if v in present]
    if not scored:
        return float("nan")
    per_label = label_dice(torch.from_numpy(warped.astype(np.int64)), torch.from_numpy(fixed.astype(np.int64)), scored)
    return float(np.mean(list(per_label.values())))


def brain_ncc(warped: np.ndarray, template: np.ndarray) -> float:
    """Pearson correlation of the two images over the template's brain (its voxels above its minimum)."""
    brain = template > template.min()
    a, b = warped[brain].astype(np.float64), template[brain].astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


# ---------------------------------------------------------------------------------------------------- ANTs SyN
def ants_whole(fixed_path: Path, moving_path: Path, moving_label: Path | None, out_dir: Path) -> dict:
    """ANTs SyN as a user runs it: read both files, register, resample the scan (and labels), write; timed whole."""
    import ants

    start = time.perf_counter()
    fixed, moving = ants.image_read(str(fixed_path)), ants.image_read(str(moving_path))
    result = ants.registration(fixed, moving, type_of_transform="SyN", outprefix=f"{out_dir}/tx_")
    warped = ants.apply_transforms(fixed, moving, result["fwdtransforms"])
    ants.image_write(warped, str(out_dir / "warped.nii.gz"))
    record = {}
    if moving_label is not None:
        labels = ants.apply_transforms(
            fixed, ants.image_read(str(moving_label)), result["fwdtransforms"], interpolator="genericLabel"
        )
        ants.image_write(labels, str(out_dir / "warped_label.nii.gz"))
    record["seconds"] = round(time.perf_counter() - start, 2)
    jacobian = ants.create_jacobian_determinant_image(fixed, result["fwdtransforms"][0]).numpy()
    record["num_folding"] = int((jacobian <= 0).sum())  # the SyN field's; the affine stage folds nothing
    return record


class AntsCache:
    """ANTs SyN's records by case, kept in a JSON file across runs (``--ants-cache``): its inputs do not depend on our
    weights, so comparing new weights need not rerun 20-60 minutes of SyN. A key names the case, the sha256 of its
    input files and every setting that makes it; a reused record says ``"cached": true`` and when it was computed."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.records: dict[str, dict] = json.loads(path.read_text()) if path is not None and path.is_file() else {}

    def get(self, key: str, compute: Callable[[], dict]) -> dict:
        if key in self.records:
            return {**self.records[key], "cached": True}
        record = {
            **compute(),
            "computed_at": time.strftime("%Y-%m-%d %H:%M:%S"),
            "antspyx": _antspyx_version(),
        }
        self.records[key] = record
        if self.path is not None:  # merged with the file as it is now: --jobs runs several writers
            on_disk = json.loads(self.path.read_text()) if self.path.is_file() else {}
            self.records = {**on_disk, **self.records}
            write_text(self.path, json.dumps(self.records, indent=1) + "\n")
        return record


def _antspyx_version() -> str | None:
    try:
        return importlib.metadata.version("antspyx")
    except importlib.metadata.PackageNotFoundError:
        return None


def _sha(*paths: Path) -> str:
    return ",".join(file_sha256(p)[:16] for p in paths)


def _voxel_sha(*paths: Path) -> str:
    """Of the images' voxels, shape, dtype and voxel-to-world matrix (not their files: a gzip header may differ
    between identical writes): a rendering or geometry that changes changes the key of the ANTs records made from it."""

    def digest(path: Path) -> str:
        volume = read_image(path)
        h = hashlib.sha256(np.ascontiguousarray(volume.array).tobytes())
        h.update(f"{volume.array.shape}{volume.array.dtype}".encode())
        h.update(np.ascontiguousarray(volume.index_to_lps, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]

    return ",".join(digest(p) for p in paths)


# ---------------------------------------------------------------------------------------------------- parts
def part_demo(models: dict, options: dict, fixed, ants: AntsCache | None) -> dict:
    rows = {}
    for name, model in models.items():
        for method, refine in options.items():
            cases = {}
            for seed in DEMO_SEEDS:
                opts = command_options(model, refine, seed, samples=True)
                cases[seed] = one_case(model, fixed, seed, SyntheticSettings(), opts)
            rows[f"{method} ({name})"] = _demo_row(cases)
            print(f"[demo] {method} ({name}): {rows[f'{method} ({name})']}", flush=True)
    if ants is not None:
        settings = SyntheticSettings()
        key = f"demo:{_sha(Path(fixed.image.path))}:{json.dumps(settings.as_dict(), sort_keys=True)}:seed"
        rows["ANTs SyN"] = _demo_row(
            {seed: ants.get(f"{key}{seed}", lambda seed=seed: ants_case(fixed, seed, settings)) for seed in DEMO_SEEDS}
        )
        print(f"[demo] ANTs SyN: {rows['ANTs SyN']}", flush=True)
    return rows


def _demo_row(cases: dict) -> dict:
    mean = lambda key, part: float(np.mean([c[key][part] for c in cases.values()]))  # noqa: E731
    first = next(iter(cases.values()))
    return {
        "after_median_mm": mean("after", "median_mm"),
        "after_p95_mm": mean("after", "p95_mm"),
        "affine_median_mm": None if first.get("affine_only") is None else mean("affine_only", "median_mm"),
        "coverage": (
            None if first.get("coverage") is None else float(np.mean([c["coverage"] for c in cases.values()]))
        ),
        "after_below_affine_every_seed": (
            None
            if first.get("affine_only") is None
            else all(c["after"]["median_mm"] < c["affine_only"]["median_mm"] for c in cases.values())
        ),
        "per_seed_after_median_mm": [c["after"]["median_mm"] for c in cases.values()],
    }


def part_native(models: dict, options: dict, native_dir: Path, ants: AntsCache | None) -> dict:
    scan = native_dir / f"{NATIVE_SCAN}.nii.gz"
    if not scan.is_file():
        return {"skipped": f"no {scan}"}
    template_path = mni152_template_path()
    template = read_image(template_path).array
    fixed = prepare_fixed(template_path)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="generalization_native_") as tmp:
        for name, model in models.items():
            for method, refine in options.items():
                out = Path(tmp) / f"{name}_{method}"
                start = time.perf_counter()
                summary = register_scan(model, fixed, scan, out, None, command_options(model, refine, 0))
                seconds = time.perf_counter() - start
                warped = read_image(out / "warped.nii.gz").array
                rows[f"{method} ({name})"] = {
                    "ncc": brain_ncc(warped, template),
                    "seconds": round(seconds, 2),
                    "num_folding": summary["jacobian"]["num_nonpositive"],
                }
                print(f"[native] {method} ({name}): {rows[f'{method} ({name})']}", flush=True)
        if ants is not None:

            def compute() -> dict:
                out = Path(tmp) / "ants"
                out.mkdir()
                record = ants_whole(template_path, scan, None, out)
                return {"ncc": brain_ncc(read_image(out / "warped.nii.gz").array, template), **record}

            rows["ANTs SyN"] = ants.get(f"native:{_sha(template_path, scan)}", compute)
            print(f"[native] ANTs SyN: {rows['ANTs SyN']}", flush=True)
    return rows


def synthetic_head(
    label_map: Path, seed: int, out_dir: Path, brain: Mapping[int, float] = T1_LIKE, brain_only: bool = False
) -> tuple[Path, Path]:
    """A label map cropped to its head, deformed by a random diffeomorphism (``seed``), rendered with the brain's
    intensities of ``brain`` (T1-like by default); written as ``<stem>_<seed>_image.nii.gz`` and ``_label.nii.gz`` in
    ``out_dir``. Returns their paths. ``brain_only``: the extra-cerebral labels (500 and above) set to background
    first, a skull-stripped brain cropped to itself."""
    labels = read_label(label_map)
    if brain_only:
        labels = labels.with_array(np.where(labels.array < EXTRA_CEREBRAL_FROM, labels.array, 0))
    nonzero = np.argwhere(labels.array > 0)
    lo = np.maximum(nonzero.min(0) - SYNTH_CROP_MARGIN, 0)
    hi = np.minimum(nonzero.max(0) + SYNTH_CROP_MARGIN + 1, labels.shape)
    cropped = labels.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    index_to_lps = labels.index_to_lps.copy()
    index_to_lps[:3, 3] = labels.index_to_lps[:3, :3] @ lo + labels.index_to_lps[:3, 3]
    spacing = float(np.mean(labels.spacing))
    deform = RandDiffeomorphicd(
        keys=[],
        label_keys=["label"],
        magnitude=SYNTH_DEFORM_RMS_MM / spacing,
        control_spacing=SYNTH_DEFORM_SPACING_MM / spacing,
    )
    deform.set_random_state(seed=seed)
    warped = deform({"label": torch.from_numpy(cropped.astype(np.int32))[None]})["label"][0].numpy()
    volume = Volume(warped.astype(np.int32), index_to_lps)
    stem = f"{label_map.name.split('.')[0]}_{seed}"
    image_path, label_path = out_dir / f"{stem}_image.nii.gz", out_dir / f"{stem}_label.nii.gz"
    write_volume(image_path, render_head(volume, seed, brain))
    write_volume(label_path, volume, label_dtype(volume.array))
    return image_path, label_path


def part_synthetic(models: dict, options: dict, label_maps: Path | None, ants: AntsCache | None) -> dict:
    paths = [label_maps / f"{m}.nii.gz" for m in SYNTH_MAPS] if label_maps else []
    if not paths or not all(p.is_file() for p in paths):
        return {"skipped": f"no {SYNTH_MAPS} in {label_maps} (git clone https://github.com/BBillot/SynthSeg)"}
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="generalization_synth_") as tmp:
        for seed in SYNTH_SEEDS:
            heads = [synthetic_head(p, seed, Path(tmp)) for p in paths]
            for (moving, moving_label), (fixed_image, fixed_label) in ((heads[0], heads[1]), (heads[1], heads[0])):
                pair = f"{moving.name.split('_image')[0]}_to_{fixed_image.name.split('_image')[0]}"
                target = read_label(fixed_label).array
                fixed = prepare_fixed(fixed_image, fixed_label)
                for name, model in models.items():
                    for method, refine in options.items():
                        out = Path(tmp) / f"{pair}_{name}_{method}"
                        summary = register_scan(
                            model, fixed, moving, out, moving_label, command_options(model, refine, seed)
                        )
                        score = dice(read_label(out / "warped_label.nii.gz").array, target, ASEG_LABELS)
                        _add(rows, f"{method} ({name})", pair, score, summary["jacobian"]["num_nonpositive"])
                if ants is not None:

                    def compute(
                        pair=pair, moving=moving, moving_label=moving_label, fixed_image=fixed_image, target=target
                    ) -> dict:
                        out = Path(tmp) / f"{pair}_ants"
                        out.mkdir()
                        record = ants_whole(fixed_image, moving, moving_label, out)
                        return {
                            **record,
                            "dice": dice(read_label(out / "warped_label.nii.gz").array, target, ASEG_LABELS),
                        }

                    key = f"synthetic:{_voxel_sha(moving, fixed_image)}:{pair}"
                    record = ants.get(key, compute)
                    _add(rows, "ANTs SyN", pair, record["dice"], record["num_folding"])
                print(
                    f"[synthetic] {pair}: " + ", ".join(f"{k} {v['per_pair'][pair]:.3f}" for k, v in rows.items()),
                    flush=True,
                )
    for row in rows.values():
        row["dice"] = float(np.mean(list(row["per_pair"].values())))
    return rows


def _add(rows: dict, key: str, pair: str, score: float, folds: int) -> None:
    row = rows.setdefault(key, {"per_pair": {}, "num_folding": 0})
    row["per_pair"][pair] = score
    row["num_folding"] += int(folds)


def part_lpba40(
    model_files: list[Path | None],
    steps: int,
    dataset_dir: Path | None,
    threads: int,
    ants: AntsCache | None,
    variants: dict[str, dict] | None = None,
) -> dict:
    """``accuracy_table.py``'s validation -> S01 and pairs, per weights: network and default rows, and one refined row
    per variant (its fields as ``refine_*`` overrides of evaluate.yaml); ANTs SyN once."""
    dataset = (dataset_dir or accuracy_table.DEFAULT_DATASET).resolve()
    if not dataset.is_dir():
        return {"skipped": f"LPBA40 not found at {dataset}"}
    ants_key = f"lpba40:{dataset}:{accuracy_table.DEFAULT_REFINE_ITERATIONS}"
    run_ants = ants is not None and ants_key not in ants.records
    rows = {}
    with tempfile.TemporaryDirectory(prefix="generalization_lpba40_") as tmp:

        def table(model_file: Path | None, methods: list[str], overrides: dict | None = None) -> dict:
            argv = ["--threads", str(threads), "--out-dir", tmp, "--refine-iterations", str(steps)]
            argv += ["--dataset-dir", str(dataset), "--methods", *methods]
            argv += ["--model-file", str(model_file)] if model_file else []
            argv += [f"--override=refine_{key}={value}" for key, value in (overrides or {}).items()]
            accuracy_table.main(argv)
            return json.loads((Path(tmp) / "accuracy_table.json").read_text())["methods"]

        for n, model_file in enumerate(model_files):
            name = _name(model_file)
            result = table(model_file, ["ours", "refined"] + (["ants"] if run_ants and n == 0 else []))
            for method, label in (
                ("ours", f"network ({name})"),
                ("refined", f"refined ({name})"),
                ("ants", "ANTs SyN"),
            ):
                row = result.get(method)
                if row and row.get("aggregate"):
                    rows[label] = _lpba40_row(row)
            for variant, fields in (variants or {}).items():
                rows[f"{variant} ({name})"] = _lpba40_row(table(model_file, ["refined"], fields)["refined"])
    if ants is not None:
        computed = rows.pop("ANTs SyN", None)
        rows["ANTs SyN"] = ants.get(ants_key, lambda: computed)
    return rows


def _lpba40_row(row: dict) -> dict:
    """accuracy_table.py's row: mean Dice (and its std over pairs), folds and seconds per pair (all pairs)."""
    atlas, pairs = row["aggregate"]["atlas"]["mean_dice"], row["aggregate"]["pairs"]["mean_dice"]
    return {
        "to_atlas": atlas["mean"],
        "pairs": pairs["mean"],
        "num_folding_per_pair": row["aggregate_all"]["num_folding"]["mean"],
        "to_atlas_std": atlas.get("std"),
        "pairs_std": pairs.get("std"),
        "seconds_per_pair": row["aggregate_all"].get("runtime_s", {}).get("mean"),
    }


# ---------------------------------------------------------------------------------------------------- running
def command_options(model, refine: dict, seed: int, samples: bool = False) -> RegistrationOptions:
    """The command's options with the bundle's refinement settings, ``refine``'s fields replaced, and ``seed``;
    ``samples``: the demo's posterior samples (its coverage), else none and no maps (what is scored needs none)."""
    base = (
        RegistrationOptions(samples=DEMO_SAMPLES, seed=seed)
        if samples
        else RegistrationOptions(qc=False, inverse=False, maps=False, seed=seed)
    )
    return dataclasses.replace(
        base,
        affine=dataclasses.replace(base.affine, seed=seed),
        refinement=model.refinement.with_fields(**refine),
    )


def _name(model_file: Path | None) -> str:
    return "shipped" if model_file is None else Path(model_file).stem


def markdown(result: dict) -> str:
    lines = [
        "| method | demo: median / p95 mm (affine) | demo 95% coverage | S20 -> MNI152: NCC, folds, s | "
        "unseen label maps: Dice | LPBA40 -> S01 / pairs |",
        "|---|---|---|---|---|---|",
    ]
    parts = result["parts"]
    names = list(dict.fromkeys(k for p in parts.values() if "skipped" not in p for k in p))
    for name in names:
        d, n, s, l4 = (parts.get(p, {}).get(name) for p in PARTS)
        cell = lambda v, f: "–" if v is None else f.format(v)  # noqa: E731
        lines.append(
            f"| {name} | "
            + (
                "–"
                if d is None
                else f"{d['after_median_mm']:.2f} / {d['after_p95_mm']:.2f} ({cell(d['affine_median_mm'], '{:.2f}')})"
            )
            + f" | {cell(d and d['coverage'], '{:.3f}')} | "
            + ("–" if n is None else f"{n['ncc']:.3f}, {n['num_folding']}, {n['seconds']:.1f}")
            + " | "
            + ("–" if s is None else f"{s['dice']:.3f}")
            + " | "
            + ("–" if l4 is None else f"{l4['to_atlas']:.3f} / {l4['pairs']:.3f}")
            + " |"
        )
    return "\n".join(lines)


def figure(result: dict, path: Path) -> Path:
    """One panel per part: each method's headline number (lower is better for the demo's error)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("demo", "after_median_mm", "demo: median error, mm (lower is better)"),
        ("native", "ncc", "S20 -> MNI152: NCC in the brain"),
        ("synthetic", "dice", "unseen label maps: mean Dice"),
        ("lpba40", "pairs", "LPBA40: pairs between unseen subjects, Dice"),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6))
    for ax, (part, key, title) in zip(axes, panels):
        rows = {k: v for k, v in result["parts"].get(part, {}).items() if isinstance(v, dict) and key in v}
        ax.barh(list(rows), [v[key] for v in rows.values()], color="tab:blue")
        for y, v in enumerate(rows.values()):
            ax.text(v[key], y, f" {v[key]:.3f}", va="center", fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=8)
        if not rows:
            ax.text(0.5, 0.5, "skipped", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# rough relative run times of the parts (1 thread, two rows, ANTs records cached: 36 LPBA40 pairs against 3 demo
# subjects, 4 synthetic pairs and 1 native scan through the whole command), to balance --jobs
PART_COST = {"lpba40": 10, "demo": 4, "synthetic": 4, "native": 1}


def part_groups(parts: Sequence[str], jobs: int) -> list[list[str]]:
    """``parts`` in at most ``jobs`` groups of similar total :data:`PART_COST` (greedy, costliest part first), each
    group in :data:`PARTS`' order."""
    groups: list[list[str]] = [[] for _ in range(max(1, min(jobs, len(parts))))]
    for part in sorted(parts, key=lambda p: -PART_COST[p]):
        min(groups, key=lambda g: sum(PART_COST[p] for p in g)).append(part)
    return [sorted(g, key=PARTS.index) for g in groups]


def run_jobs(argv: Sequence[str], groups: list[list[str]]) -> dict:
    """This script once per group of parts, side by side (``argv`` with ``--jobs 1 --parts GROUP`` and a temporary
    ``--out-dir``: the last occurrence of an option wins); their results with the parts merged, ``seconds`` the
    longest process's and ``jobs`` each group's seconds."""
    with tempfile.TemporaryDirectory(prefix="generalization_jobs_") as tmp:
        runs = []
        try:
            for n, group in enumerate(groups):
                out = Path(tmp) / str(n)
                child = [sys.executable, str(Path(__file__).resolve()), *argv, "--jobs", "1", "--parts", *group]
                runs.append((group, out, subprocess.Popen([*child, "--out-dir", str(out)])))
            codes = [process.wait() for _, _, process in runs]  # all of them, before the folder goes
        finally:  # interrupted (or a later start failed): no process outlives this one
            for _, _, process in runs:
                if process.poll() is None:
                    process.terminate()
                    process.wait()
        failed = [f"{' '.join(group)} (exit {code})" for (group, _, _), code in zip(runs, codes) if code != 0]
        if failed:
            raise SystemExit(f"--jobs: the process of parts {'; '.join(failed)} failed")
        results = [json.loads((out / "generalization.json").read_text()) for _, out, _ in runs]
    merged = {**results[0], "parts": {}}
    for result in results:
        merged["parts"].update(result["parts"])
    merged["parts"] = {p: merged["parts"][p] for p in PARTS if p in merged["parts"]}
    merged["seconds"] = max(r["seconds"] for r in results)
    merged["jobs"] = {" ".join(g): r["seconds"] for (g, _, _), r in zip(runs, results)}
    return merged


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    ap.add_argument("--model-files", nargs="+", type=Path, default=None, help="weights (default: the bundle's)")
    ap.add_argument(
        "--refine-iterations",
        type=int,
        default=accuracy_table.DEFAULT_REFINE_ITERATIONS,
        help="refinement steps of the refined rows (default: %(default)s)",
    )
    ap.add_argument(
        "--refined-variants",
        nargs="+",
        default=[],
        metavar="NAME=FIELD:VALUE,...",
        help="more refined rows, each the default's settings with RefinementSettings fields replaced, e.g. "
        "'refined, 1 mm loss=image_grid_factor:2'",
    )
    ap.add_argument("--label-maps", type=Path, default=None, help="folder with SynthSeg's training_seg_*.nii.gz")
    ap.add_argument("--native-dir", type=Path, default=DEFAULT_NATIVE)
    ap.add_argument("--dataset-dir", type=Path, default=None, help="LPBA40 (default: accuracy_table.py's)")
    ap.add_argument("--no-ants", dest="ants", action="store_false", help="leave ANTs SyN out")
    ap.add_argument(
        "--ants-cache",
        type=Path,
        default=None,
        help="JSON file of ANTs SyN's records to reuse and extend (AntsCache; default: none, all run)",
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="run the parts in this many processes side by side, each with --threads, merged into one table "
        "(2 with --threads 1 on a 2-core machine: each part's methods still share one process)",
    )
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if args.jobs < 1:
        raise SystemExit(f"--jobs must be >= 1; got {args.jobs}")
    options = {"network": {"num_iterations": 0}, "refined": {"num_iterations": args.refine_iterations}}
    variants = dict(parse_variant(v) for v in args.refined_variants)
    for variant, fields in variants.items():
        if variant in options:
            raise SystemExit(f"--refined-variants: {variant!r} is taken; name it otherwise")
        try:
            RefinementSettings(**fields)
        except (TypeError, ValueError) as err:
            raise SystemExit(f"--refined-variants {variant!r}: {err}") from None
        options[variant] = {"num_iterations": args.refine_iterations, **fields}
    groups = part_groups(args.parts, args.jobs)
    if len(groups) > 1:
        result = run_jobs(argv, groups)
        return _write(result, args.out_dir)
    torch.set_num_threads(args.threads)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)  # ANTs' too; read at ITK's first use
    if args.ants:
        try:
            import ants  # noqa: F401
        except ImportError as err:
            print(f"ANTs SyN skipped: antspyx not importable ({err}); pip install -e '.[bench]'", flush=True)
            args.ants = False
    ants = AntsCache(args.ants_cache) if args.ants else None
    model_files = args.model_files or [None]
    models = {_name(f): load_model(model_file=f) for f in model_files}
    start = time.perf_counter()
    parts: dict[str, dict] = {}
    if "demo" in args.parts:
        parts["demo"] = part_demo(models, options, prepare_fixed(mni152_template_path()), ants)
    if "native" in args.parts:
        parts["native"] = part_native(models, options, args.native_dir, ants)
    if "synthetic" in args.parts:
        parts["synthetic"] = part_synthetic(models, options, args.label_maps, ants)
    if "lpba40" in args.parts:
        parts["lpba40"] = part_lpba40(
            model_files, args.refine_iterations, args.dataset_dir, args.threads, ants, variants
        )
    result = {
        "parts": parts,
        "threads": args.threads,
        "refine_iterations": args.refine_iterations,
        "refined_variants": variants,
        "model_files": {k: str(m.model_file) for k, m in models.items()},
        "ants": ANTS_CALL if args.ants else None,
        "synthetic": {
            "label_maps": list(SYNTH_MAPS),
            "seeds": list(SYNTH_SEEDS),
            "deform_rms_mm": SYNTH_DEFORM_RMS_MM,
            "deform_spacing_mm": SYNTH_DEFORM_SPACING_MM,
            "labels": list(ASEG_LABELS),
        },
        "seconds": round(time.perf_counter() - start, 1),
        "versions": library_versions(),
    }
    return _write(result, args.out_dir)


def _write(result: dict, out_dir: Path) -> int:
    result["markdown"] = markdown(result)
    path = write_text(out_dir / "generalization.json", json.dumps(result, indent=2) + "\n")
    png = figure(result, out_dir / "generalization.png")
    print(f"\n{result['markdown']}\n\nwrote {path} and {png}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
