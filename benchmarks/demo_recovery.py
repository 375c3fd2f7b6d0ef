"""How well the shipped model recovers a known transform: ``monai-probreg demo`` over several seeds, side by side.

For each weights file (``--model-files``, default the bundle's shipped default) and each seed, the demo's synthetic
subject (:mod:`monai_probreg.data.synthetic`: the MNI152 template nilearn ships, turned, shifted and deformed by a
known transform, with a bias field and noise) is registered back through the code path of ``monai-probreg register``
(:func:`monai_probreg.registration.demo.run_demo`) and scored inside the brain
(:mod:`monai_probreg.metrics.recovery`): the displacement error in mm before, after the affine stage alone and after the whole registration (median, 95th
percentile) and the coverage of the calibrated 95% interval. One more case, "identity", registers the template to an
exact copy of itself (nothing drawn): the right answer is no displacement at all, so its "after" error is what the
model invents where there is nothing to register.

``--ants``: one more row, ANTs SyN (antspyx defaults, ``type_of_transform="SyN"``: its own affine stage, then SyN; the
``.[bench]`` extra) on the same subjects, as an anchor of what a classical optimiser recovers here. Its composed
forward field (``ants.apply_transforms(..., compose=...)``, ITK's convention: a fixed LPS point ``p`` maps to the
moving point ``p + u(p)``, which is ``warp.nii.gz``'s) is scored like ours; it has no posterior (no coverage) and no
separate affine error.

Issue "The first five minutes" asks for a median error <= 1 mm after registration (synthetic displacement of median
>= 3 mm) and a coverage in [0.90, 0.98]. The template ships with nilearn, so this runs on any install:

    python benchmarks/demo_recovery.py --threads 2
    python benchmarks/demo_recovery.py --model-files bundle/models/model.pt CANDIDATE.pt --refine 0 10
    python benchmarks/demo_recovery.py --refine 0 10 --seeds 0 1 2 --ants   # + ANTs SyN on the same subjects

Prints a table and writes ``OUT_DIR/demo_recovery.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_OUT

from monai_probreg.data.synthetic import SyntheticSettings, brain_mask, synthesize_subject
from monai_probreg.data.template import mni152_template_path
from monai_probreg.metrics.recovery import displacement_recovery
from monai_probreg.registration.demo import DEMO_SAMPLES, run_demo
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_folder import write_volume
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import library_versions

DEFAULT_SEEDS = (0, 1, 2, 3, 4)
IDENTITY = SyntheticSettings(max_rotation_deg=0, max_shift_mm=0, deform_rms_mm=0, bias_coeff=0, noise_fraction=0)


def one_case(model, fixed, seed: int, settings: SyntheticSettings, options: RegistrationOptions) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        summary = run_demo(model, fixed, Path(tmp) / "out", seed, settings, options)
        seconds = time.perf_counter() - start  # synthesis + registration + writing
    return {**summary["demo"], "seconds": round(seconds, 2), "num_folding": summary["jacobian"]["num_nonpositive"]}


def ants_case(fixed, seed: int, settings: SyntheticSettings) -> dict:
    """The demo's subject of ``seed`` registered onto the template by ANTs SyN, scored as ours (module docstring)."""
    import ants

    template = fixed.image
    subject = synthesize_subject(template, settings, seed)
    with tempfile.TemporaryDirectory(prefix="demo_ants_") as tmp:
        write_volume(Path(tmp) / "subject.nii.gz", subject.image)
        fixed_img, moving_img = ants.image_read(template.path), ants.image_read(str(Path(tmp) / "subject.nii.gz"))
        start = time.perf_counter()
        result = ants.registration(fixed_img, moving_img, type_of_transform="SyN", outprefix=f"{tmp}/tx_")
        seconds = time.perf_counter() - start
        field = ants.image_read(
            ants.apply_transforms(fixed_img, moving_img, result["fwdtransforms"], compose=f"{tmp}/composed_")
        )  # double vectors: ITK's Python can't
    # ANTs' arrays are in ITK index order (i, j, k), like our Volumes; the vectors are LPS mm (ITK's physical space)
    warp = np.ascontiguousarray(field.numpy(), dtype=np.float64)
    index_to_lps = np.eye(4)
    index_to_lps[:3, :3] = np.asarray(field.direction) * np.asarray(field.spacing)
    index_to_lps[:3, 3] = field.origin
    if warp.shape != (*template.shape, 3) or not np.allclose(index_to_lps, template.index_to_lps, atol=1e-4):
        raise RuntimeError(f"ANTs' composed field is not on the template grid: {warp.shape} vs {template.shape}")
    recovery = displacement_recovery(subject.true_warp, warp, brain_mask(template))
    return {**recovery.as_dict(), "seconds": round(seconds, 2)}


def _row_means(cases: dict[str, dict]) -> dict:
    drawn = [c for name, c in cases.items() if name != "identity"]

    def mean(key, part):
        return None if drawn[0][key] is None else float(np.mean([c[key][part] for c in drawn]))

    return {
        "before_median_mm": mean("before", "median_mm"),
        "affine_median_mm": mean("affine_only", "median_mm"),
        "after_median_mm": mean("after", "median_mm"),
        "after_p95_mm": mean("after", "p95_mm"),
        "coverage": None if drawn[0]["coverage"] is None else float(np.mean([c["coverage"] for c in drawn])),
        "identity_after_median_mm": cases["identity"]["after"]["median_mm"],
        "identity_coverage": cases["identity"]["coverage"],
        "seconds": float(np.mean([c["seconds"] for c in drawn])),
    }


def _cell(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model-files", nargs="*", default=[None], help="weights to compare (default: the bundle's)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS), help="demo seeds")
    ap.add_argument("--refine", type=int, nargs="+", default=[0], help="test-time refinement steps to compare")
    ap.add_argument("--samples", type=int, default=DEMO_SAMPLES, help="posterior samples (default: the demo's)")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="where demo_recovery.json goes")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default: %(default)s)")
    ap.add_argument("--ants", action="store_true", help="also ANTs SyN on the same subjects (antspyx, '.[bench]')")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)  # ANTs' too; ITK reads it at its first use
    fixed = prepare_fixed(mni152_template_path())
    rows = {}
    names = [None if f is None else Path(f).name for f in args.model_files]
    for model_file in args.model_files:
        model = load_model(model_file=model_file)
        # weights named alike (the same weights beside other sidecars) are told apart by their folder
        shown = model.model_file.name if names.count(model.model_file.name) < 2 else str(model_file)
        for steps in args.refine:
            options = RegistrationOptions(
                samples=args.samples, refinement=model.refinement.with_fields(num_iterations=steps)
            )
            name = shown + (f" + refine {steps}" if steps else "")
            cases = {"identity": one_case(model, fixed, 0, IDENTITY, options)}
            for seed in args.seeds:
                seeded = dataclasses.replace(options, seed=seed, affine=dataclasses.replace(options.affine, seed=seed))
                cases[f"seed {seed}"] = one_case(model, fixed, seed, SyntheticSettings(), seeded)  # as the command
                c = cases[f"seed {seed}"]
                print(
                    f"{name}, seed {seed}: before {c['before']['median_mm']:.2f}, affine "
                    f"{c['affine_only']['median_mm']:.2f}, after {c['after']['median_mm']:.2f} mm median; "
                    f"coverage {c['coverage']:.3f}; {c['seconds']:.1f} s",
                    flush=True,
                )
            rows[name] = {
                "model_file": str(model.model_file),
                "refine": steps,
                "means": _row_means(cases),
                "cases": cases,
            }
    if args.ants:
        cases = {"identity": ants_case(fixed, 0, IDENTITY)}
        for seed in args.seeds:
            cases[f"seed {seed}"] = c = ants_case(fixed, seed, SyntheticSettings())
            print(
                f"ANTs SyN, seed {seed}: before {c['before']['median_mm']:.2f}, after {c['after']['median_mm']:.2f} "
                f"mm median; {c['seconds']:.1f} s",
                flush=True,
            )
        rows["ANTs SyN"] = {
            "call": 'ants.registration(fixed, moving, type_of_transform="SyN")',
            "refine": 0,
            "means": _row_means(cases),
            "cases": cases,
        }
    lines = [
        "| weights | before | affine only | after (median / p95) | 95% coverage | identity: after | s |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, row in rows.items():
        m = row["means"]
        lines.append(
            f"| {name} | {m['before_median_mm']:.2f} | {_cell(m['affine_median_mm'])} | "
            f"{m['after_median_mm']:.2f} / {m['after_p95_mm']:.2f} | {_cell(m['coverage'], 3)} | "
            f"{m['identity_after_median_mm']:.2f} | {m['seconds']:.1f} |"
        )
    table = "\n".join(lines)
    result = {
        "seeds": args.seeds,
        "samples": args.samples,
        "threads": args.threads,
        "rows": rows,
        "settings": SyntheticSettings().as_dict(),
        "template": str(mni152_template_path()),
        "errors": "mean over the seeds of each subject's median (and 95th percentile) error in the brain, mm",
        "markdown": table,
        "versions": library_versions(),
    }
    path = write_text(args.out_dir / "demo_recovery.json", json.dumps(result, indent=2) + "\n")
    print(f"\n{table}\n\nwrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
