"""How far to trust the calibrated posterior: held-out coverage against known deformations, label uncertainty.

This script measures; ``python -m monai_probreg.fitting`` fits the calibration the weights ship with, on the same
cases (:mod:`monai_probreg.fitting.calibration_probes`) and by the same fit.

1. Ground truth where it exists (:mod:`monai_probreg.fitting.population_probe`). For each subject S (default:
   ``val_ids`` of configs/train.yaml), ``--deformations`` random smooth velocity fields v are drawn, by one of two
   ``--probe`` models: ``population`` (default, the fit's: a statistical deformation model of the training subjects'
   velocities; optimistic, its fields lie in the span of what the model itself predicts) or ``noise`` (smoothed white
   noise of the RMS of the model's own displacement for S -> atlas: out of the training distribution, the mean
   registration recovers only a fraction of it, ``recovered_fraction`` in the JSON: the pessimistic bound). The
   reference R is the atlas by default (``--reference atlas``): the model is trained scan-to-atlas, so the atlas is
   the only fixed image it knows; ``--reference subject`` takes R = S (out of the training distribution). The answer (the
   posterior mean's displacement) and its first-order std per component (:mod:`monai_probreg.uncertainty.spread`)
   are compared with the truth exp(-v) inside the brain: coverage of the
   nominal 68% / 95% intervals, Spearman(std, |error|) per component and of the vectors (sqrt(sum_c std_c^2) against
   the length of the error vector), each with its ceiling: the Spearman errors drawn from N(0, std^2) themselves
   would reach (|error| of one Gaussian component varies so much at a given std that even a perfect std ranks it
   only partly), UCE (15 equal-count bins), reliability diagram; and the translation probe (the recovered fraction
   of a 3-voxel shift of the atlas per axis).
2. Label uncertainty on real pairs: S -> atlas; the atlas labels are propagated into S by the K sampled inverse
   warps exp(-z_k) (drawn as the bundle draws them: :mod:`monai_probreg.uncertainty.samples`); the per-voxel label entropy is scored (AUROC) as a detector of voxels where the atlas labels
   propagated by the mean, exp(-mean), disagree with S's manual labels (voxels where either is non-background).
3. Calibration held out: the coverage-matching fit of (std_scale, bias_fraction, interval_dof)
   (:meth:`~monai_probreg.fitting.calibration_probes.CalibrationProbes.fit`, ``--fit-iterations`` refits) is
   cross-fitted: the subjects are split in ``--folds`` folds; each fold is scored with the calibration fitted on the
   others, its std maps mapped at that calibration. Raw (scale 1) rows use the same subjects.
4. The subject probe (``--subject-probe N``, :mod:`monai_probreg.fitting.subject_probe`): N training subjects' scans
   are each the template of one synthetic subject made as ``monai-probreg demo`` makes its own, registered back by
   the command's path (affine stage, network, refinement) and scored in mm in the posterior's frame. Fitted together
   with the probe of part 1, each probe's coverage matched on its own; its templates are split into the same number
   of folds and scored held out the same way (the "subject probe" rows).

    python benchmarks/uncertainty_calibration.py --deformations 1 --threads 2   # table, JSON and two PNGs in results/
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO, bundle_parser
from uncertainty_figures import figure4, reliability_diagram

from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.data.dataset import index_dataset
from monai_probreg.fitting.calibration_probes import (
    FIT_ITERATIONS,
    FIT_TOLERANCE,
    RESIDUAL_WEIGHTS,
    SUBJECT_PROBE_TEMPLATES,
    ProbeSettings,
    calibration_probes,
)
from monai_probreg.fitting.population_probe import (
    SEED_STRIDE,
    SMOOTHING_VOXELS,
    TRUTH_STEPS,
    VOXELS_PER_CASE,
    pool_errors,
    posterior_for,
)
from monai_probreg.metrics.calibration import (
    auroc,
    interval_coverage,
    spearman,
    uncertainty_calibration_error,
)
from monai_probreg.uncertainty.calibration import (
    FIT_LEVELS,
    POSTERIOR_SAMPLES,
    Calibration,
    calibrate_log_var,
    calibration_for,
)
from monai_probreg.uncertainty.entropy import velocity_entropy
from monai_probreg.uncertainty.partial_volume import PartialVolumeLabels
from monai_probreg.uncertainty.samples import sample_log_var, sample_scales
from monai_probreg.uncertainty.spread import displacement_variance
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import write_text
from monai_probreg.weights.loading import load_weights

PROBE_SHIFT_VOXELS = 3.0  # translation of the diagnostic probe (recovered fraction per axis)
LABEL_SEED_OFFSET = 7  # the label entropy's samples are seeded by --seed + this (apart from the probes' draws)


def translation_probe(network, fixed: torch.Tensor, shift: float = PROBE_SHIFT_VOXELS) -> list[float]:
    """Fraction of a known ``shift``-voxel translation of ``fixed`` along each axis that the mean registration recovers
    (mean over the brain of the predicted displacement component, divided by the true -shift): 1 = fully."""
    brain = fixed[0, 0] > 0
    fractions = []
    for axis in range(3):
        displacement = torch.zeros((1, 3, *fixed.shape[2:]))
        displacement[:, axis] = shift
        moving = warp_image(fixed, displacement)  # moving(x) = fixed(x + shift e_axis): the truth is -shift e_axis
        with torch.inference_mode():
            predicted = network(moving, fixed).displacement
        fractions.append(float(predicted[0, axis][brain].mean()) / -shift)
    return fractions


def recovered_fraction(error: np.ndarray, truth: np.ndarray) -> float:
    """Least-squares slope of the predicted displacement (error + truth) on the true one: 1 = fully recovered."""
    return float(np.sum((error + truth) * truth) / np.sum(truth**2))


def displacement_metrics(std: np.ndarray, error: np.ndarray, interval_dof: float | None = None) -> dict[str, Any]:
    """Metrics of (3, N) std and error: per component, and of the vectors (std_c combined, error length). The
    intervals are Student-t with ``interval_dof`` degrees of freedom (None: Gaussian), as the calibration says."""
    perfect = std * np.random.default_rng(0).standard_normal(std.shape)  # errors a calibrated Gaussian would make
    vector_std = np.sqrt((std**2).sum(0))
    return {
        "coverage_68": interval_coverage(std, error, 0.68, interval_dof),
        "coverage_95": interval_coverage(std, error, 0.95, interval_dof),
        "coverage_by_level": {str(p): interval_coverage(std, error, p, interval_dof) for p in FIT_LEVELS},
        "interval_dof": interval_dof,
        "spearman_std_abs_error": spearman(std.ravel(), np.abs(error).ravel()),
        "spearman_ceiling": spearman(std.ravel(), np.abs(perfect).ravel()),
        "spearman_vector": spearman(vector_std, np.linalg.norm(error, axis=0)),
        "spearman_vector_ceiling": spearman(vector_std, np.linalg.norm(perfect, axis=0)),
        "uce_voxels": uncertainty_calibration_error(std.ravel(), error.ravel()),
        "rms_error_voxels": float(np.sqrt(np.mean(error**2))),
        "rms_std_voxels": float(np.sqrt(np.mean(std**2))),
    }


def pooled_metrics(stds: list[np.ndarray], errors: list[np.ndarray], dofs: list[float | None]) -> dict[str, Any]:
    """:func:`displacement_metrics` of the (3, N_i) parts pooled, each part's coverage taken with its own intervals
    (folds may fit different dofs) and weighted by its size; ``interval_dof``: the one dof, or the parts' list."""
    metrics = displacement_metrics(np.concatenate(stds, axis=1), np.concatenate(errors, axis=1))
    sizes = np.array([s.size for s in stds], np.float64)

    def coverage(level: float) -> float:
        per_part = [interval_coverage(s, e, level, d) for s, e, d in zip(stds, errors, dofs)]
        return float(np.dot(sizes, per_part) / sizes.sum())

    metrics["coverage_by_level"] = {str(p): coverage(p) for p in FIT_LEVELS}
    metrics["coverage_68"], metrics["coverage_95"] = coverage(0.68), metrics["coverage_by_level"]["0.95"]
    metrics["interval_dof"] = dofs[0] if len(set(dofs)) == 1 else list(dofs)
    return metrics


def propagated_labels(network, velocities: torch.Tensor, atlas_label: torch.Tensor, size) -> list[torch.Tensor]:
    """The atlas labels (1, 1, *S) pulled into the moving image's grid by exp(-z) for each velocity z of
    ``velocities`` (K, 3, *V): K label maps (*S)."""
    return [
        warp_labels(atlas_label, inverse[None])[0, 0] for inverse in network.velocity_to_displacement(-velocities, size)
    ]


def label_case(
    network, pair, calibration: Calibration, num_samples, seed, refinement=None, posterior=None
) -> dict[str, Any]:
    """Atlas labels into the subject by K sampled inverse warps, read with partial volume as the bundle's
    ``label_entropy`` reads them; label entropy vs wrongly labelled voxels.
    ``refinement``: around the refined mean (:func:`posterior_for`); ``posterior``: the pair's
    :func:`posterior_for` with ``calibration.error_model`` when already made (None: registered here)."""
    moving, fixed = pair["moving"], pair["fixed"]
    size = tuple(moving.shape[2:])
    if posterior is None:
        posterior = posterior_for(network, moving, fixed, refinement, calibration.error_model)
    with torch.inference_mode():
        log_var = calibrate_log_var(
            posterior.log_var,
            calibration.std_scale,
            posterior.mean,
            calibration.bias_fraction,
            posterior.residual,
            calibration.residual_weight,
        )
        atlas_label = pair["fixed_label"].to(torch.int16)
        predicted = warp_labels(atlas_label, network.velocity_to_displacement(-posterior.mean, size))[0, 0]
        generator = torch.Generator().manual_seed(seed)
        # the bundle's label entropy (posterior_maps): its samples widened and Student-t (uncertainty.samples)
        reader = PartialVolumeLabels(atlas_label)
        sampled = sample_log_var(log_var, calibration.sample_gain)
        scales = sample_scales(num_samples, calibration.interval_dof)
        for start in range(0, num_samples, 4):
            chunk = scales[start : start + 4]
            z = sample_velocity(posterior.mean, sampled, len(chunk), generator, chunk)
            for inverse in network.velocity_to_displacement(-z.flatten(0, 1), size):
                reader.add(inverse[None])
        entropy = reader.entropy()
    truth = pair["moving_label"][0, 0].to(torch.int16)
    region = (predicted > 0) | (truth > 0)
    wrong = (predicted != truth)[region]
    return {
        "auroc": auroc(entropy[region].numpy(), wrong.numpy()),
        "wrong_fraction": float(wrong.float().mean()),
        "entropy": entropy,
        "predicted": predicted,
        "truth": truth,
        "log_var": log_var,
        "mean": posterior.mean,
    }


def validation_arguments(description: str) -> argparse.ArgumentParser:
    """The arguments every validation-subject benchmark here shares: dataset, bundle, weights, subjects, samples,
    threads, seed, output folder."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument("--subjects", nargs="+", default=None, help="default: val_ids of configs/train.yaml")
    ap.add_argument("--samples", type=int, default=POSTERIOR_SAMPLES, help="posterior samples K")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    return ap


def validation_model(args: argparse.Namespace):
    """(evaluate.yaml's parser, weights file, network with its weights, subjects) for ``args`` of
    :func:`validation_arguments`."""
    bundle_root = args.bundle_root.resolve()
    evaluate = bundle_parser(bundle_root, ["evaluate.yaml"], {"dataset_dir": str(args.dataset_dir.resolve())})
    model_file = args.model_file or Path(evaluate.get_parsed_content("model_file"))
    network = load_weights(evaluate.get_parsed_content("network_def", lazy=False), model_file, "cpu")
    subjects = args.subjects or list(bundle_parser(bundle_root, ["train.yaml"]).get_parsed_content("val_ids"))
    return evaluate, model_file, network, subjects


class ValidationRun(NamedTuple):
    """What a study on the validation subjects starts from (:func:`validation_run`)."""

    evaluate: Any  # evaluate.yaml's parser
    model_file: Path
    network: Any
    subjects: list[str]
    calibration: Calibration  # the weights' sidecar's (raw, with a warning, without one)
    index: Any  # the dataset's DatasetIndex
    preprocessing: Any  # evaluate.yaml's


def validation_run(args: argparse.Namespace) -> ValidationRun | None:
    """The start of a study over ``args`` of :func:`validation_arguments`: None after printing the skip line when the
    dataset is absent; ``--samples`` below 2 refused (a spread needs two); the threads set; the model, subjects,
    calibration, dataset index and preprocessing."""
    if not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return None
    if args.samples < 2:
        raise SystemExit(f"--samples must be >= 2; got {args.samples}")
    torch.set_num_threads(args.threads)
    evaluate, model_file, network, subjects = validation_model(args)
    return ValidationRun(
        evaluate,
        model_file,
        network,
        subjects,
        calibration_for(model_file),
        index_dataset(args.dataset_dir),
        evaluate.get_parsed_content("preprocessing"),
    )


def main(argv=None) -> int:
    ap = validation_arguments(__doc__)
    ap.add_argument("--deformations", type=int, default=2, help="random deformations per subject")
    ap.add_argument(
        "--probe",
        choices=["population", "noise"],
        default="population",
        help="how the known deformations are drawn (see the module docstring)",
    )
    ap.add_argument(
        "--reference",
        choices=["atlas", "subject"],
        default="atlas",
        help="the image that is deformed and registered back (see the module docstring)",
    )
    ap.add_argument(
        "--subject-probe",
        type=int,
        default=SUBJECT_PROBE_TEMPLATES,
        metavar="N",
        help="templates of the subject probe, the first N training subjects (monai_probreg.fitting.subject_probe; fitted "
        "together with --probe, each matched on its own; 0 = none)",
    )
    ap.add_argument("--folds", type=int, default=2, help="cross-fitting folds over the subjects")
    ap.add_argument(
        "--fit-iterations",
        type=int,
        default=FIT_ITERATIONS,
        help="refits at the fitted pair, at most (see FIT_ITERATIONS)",
    )
    ap.add_argument(
        "--residual-weights",
        type=float,
        nargs="+",
        default=list(RESIDUAL_WEIGHTS),
        help="the residual term's weights each fold's fit chooses among (default: the fit's; 0 alone: the "
        "network's spread without it, the calibration before the residual term)",
    )
    ap.add_argument(
        "--no-error-model",
        action="store_true",
        help="the calibration's term reads the pair's residual, not the weights' error model (the form before bundle "
        "0.33.0; the error model is fitted on other training scans than every case here, so it is used as shipped)",
    )
    ap.add_argument(
        "--refine",
        type=int,
        default=None,
        metavar="N",
        help="refinement steps of the mean that is calibrated (default: evaluate.yaml's refine_iterations,"
        " the bundle's default path; 0 = the network's mean)",
    )
    args = ap.parse_args(argv)
    if not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the fitting's progress lines
    torch.set_num_threads(args.threads)
    start_time = time.time()
    if not 1 <= args.deformations <= SEED_STRIDE:  # more would reuse the next subject's seeds
        raise SystemExit(f"--deformations must be in [1, {SEED_STRIDE}]; got {args.deformations}")
    evaluate, model_file, network, subjects = validation_model(args)
    refinement = evaluate.get_parsed_content("refinement")
    if args.refine is not None:
        if args.refine < 0:
            raise SystemExit(f"--refine must be >= 0 steps; got {args.refine}")
        refinement = refinement.with_fields(num_iterations=args.refine)
    print(
        f"calibrating the {'refined mean' if refinement.enabled else 'network mean'} "
        f"({refinement.num_iterations} refinement steps)",
        flush=True,
    )
    if args.fit_iterations < 1:
        raise SystemExit(f"--fit-iterations must be >= 1; got {args.fit_iterations}")
    if len(subjects) < args.folds or args.folds < 2:
        raise SystemExit(f"--folds must be >= 2 and <= the number of subjects ({len(subjects)}); got {args.folds}")
    if args.subject_probe < 0:
        raise SystemExit(f"--subject-probe must be >= 0 templates; got {args.subject_probe}")
    try:
        probes = calibration_probes(
            network,
            evaluate.get_parsed_content("preprocessing"),
            index_dataset(args.dataset_dir),
            subjects,
            args.bundle_root,
            model_file,
            refinement,
            ProbeSettings(args.deformations, args.samples, args.seed, args.subject_probe, args.probe, args.reference),
            None if args.no_error_model else calibration_for(model_file).error_model,
        )
    except InputError as err:
        raise SystemExit(str(err)) from None
    if any(w < 0 for w in args.residual_weights):
        raise SystemExit(f"--residual-weights must be >= 0; got {args.residual_weights}")
    probes.residual_weights = tuple(args.residual_weights)
    folds = {sid: i % args.folds for i, sid in enumerate(probes.cases)}
    subject_folds = {tid: n % args.folds for n, tid in enumerate(probes.subject_cases)}
    probe = translation_probe(network, next(iter(probes.items.values()))["fixed"])  # the atlas, the same for all
    print(
        "translation probe: recovered fraction of a 3-voxel shift of the atlas per axis: "
        + ", ".join(f"{f:.2f}" for f in probe),
        flush=True,
    )
    cases, subject_cases = probes.cases, probes.subject_cases

    scales = {
        f: probes.fit(
            [s for s in cases if folds[s] != f],
            [t for t in subject_cases if subject_folds[t] != f],
            args.fit_iterations,
        )
        for f in range(args.folds)
    }
    print(
        "held-out calibrations per fold (std_scale, bias_fraction, interval dof, residual weight): "
        + ", ".join(
            f"({v.std_scale:.3f}, {v.bias_fraction:.2f}, {v.interval_dof}, {v.residual_weight:g})"
            for v in scales.values()
        ),
        flush=True,
    )
    # the intervals of each row: raw = Gaussian; calibrated = each subject's fold's dof (one dof when the folds agree)
    row_dofs = {"raw": [], "calibrated": []}
    rows: dict[str, Any] = {
        "raw": {"std": [], "error": [], "auroc": []},
        "calibrated": {"std": [], "error": [], "auroc": []},
    }
    per_subject, figure_case = {}, None
    truth = {sid: np.concatenate([c["truth"].numpy() for c in cs], axis=1) for sid, cs in cases.items()}
    for sid in cases:
        calibration = scales[folds[sid]]
        record = {"fold": folds[sid], **calibration._asdict()}
        for name, cal in (("raw", Calibration(1.0, 0.0)), ("calibrated", calibration)):
            errors = probes.raw[sid] if name == "raw" else probes.population_errors(sid, cal)
            std, error, _ = pool_errors(errors)
            labels = label_case(
                network, probes.items[sid], cal, args.samples, args.seed + LABEL_SEED_OFFSET, refinement
            )
            row_dofs[name].append(cal.interval_dof)
            rows[name]["std"].append(std)
            rows[name]["error"].append(error)
            rows[name]["auroc"].append(labels["auroc"])
            record[name] = {
                **displacement_metrics(std, error, cal.interval_dof),
                "label_entropy_auroc": labels["auroc"],
                "wrong_label_fraction": labels["wrong_fraction"],
                "recovered_fraction": recovered_fraction(error, truth[sid]),
            }
            if name == "calibrated" and figure_case is None:
                figure_case = (sid, probes.items[sid], labels)
        per_subject[sid] = record
        print(
            f"{sid} (fold {folds[sid]}, scale {calibration.std_scale:.2f}, bias fraction "
            f"{calibration.bias_fraction:.2f}): "
            + "; ".join(
                f"{n} cov68 {record[n]['coverage_68']:.3f} cov95 {record[n]['coverage_95']:.3f} "
                f"rho {record[n]['spearman_std_abs_error']:.3f} AUROC {record[n]['label_entropy_auroc']:.3f}"
                for n in ("raw", "calibrated")
            ),
            flush=True,
        )

    summary = {}
    for name, row in rows.items():
        std, error = np.concatenate(row["std"], axis=1), np.concatenate(row["error"], axis=1)
        summary[name] = {
            **pooled_metrics(row["std"], row["error"], row_dofs[name]),
            "label_entropy_auroc": float(np.mean(row["auroc"])),
            "recovered_fraction": recovered_fraction(error, np.concatenate(list(truth.values()), axis=1)),
        }
    subject_summary = {}
    if subject_cases:  # each template scored at the calibration fitted without it (its fold's)
        held_out = {t: probes.subject_errors(t, scales[subject_folds[t]]) for t in subject_cases}
        for name, errors in (("raw", probes.subject_raw), ("calibrated", held_out)):
            dofs = {t: None if name == "raw" else scales[subject_folds[t]].interval_dof for t in errors}
            subject_summary[name] = pooled_metrics(
                [e[0] for e in errors.values()], [e[1] for e in errors.values()], list(dofs.values())
            )
            subject_summary[name]["per_template"] = {
                t: interval_coverage(e[0], e[1], 0.95, dofs[t]) for t, e in errors.items()
            }
    table = [
        "| posterior | coverage 68% | coverage 95% | Spearman per component (ceiling) | Spearman of vectors "
        "(ceiling) | UCE (voxels; subject probe: mm) | RMS error / RMS std (voxels; subject probe: mm) | "
        "label-entropy AUROC |",
        "|---|---|---|---|---|---|---|---|",
    ]
    # (recovered_fraction, in the JSON: how much of the true displacement the mean registration recovers)
    named = {**summary, **{f"{n} (subject probe, mm)": m for n, m in subject_summary.items()}}
    for name, m in named.items():
        table.append(
            f"| {name} | {m['coverage_68']:.3f} | {m['coverage_95']:.3f} | {m['spearman_std_abs_error']:.3f} "
            f"({m['spearman_ceiling']:.2f}) | {m['spearman_vector']:.3f} ({m['spearman_vector_ceiling']:.2f}) | "
            f"{m['uce_voxels']:.3f} | {m['rms_error_voxels']:.2f} / {m['rms_std_voxels']:.2f} | "
            + (f"{m['label_entropy_auroc']:.3f} |" if "label_entropy_auroc" in m else "- |")
        )
    markdown = "\n".join(table)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    curve_names = {"raw": "raw posterior", "calibrated": "calibrated (fitted on the other fold)"}
    reliability_diagram(
        {
            curve_names[n]: (np.concatenate(r["std"], axis=1).ravel(), np.concatenate(r["error"], axis=1).ravel())
            for n, r in rows.items()
        },
        args.out_dir / "uncertainty_reliability.png",
    )
    sid, pair, labels = figure_case
    size = tuple(pair["fixed"].shape[2:])
    variance = displacement_variance(labels["log_var"], size)
    figure4(
        pair,
        labels,
        velocity_entropy(labels["log_var"], size)[0, 0],
        variance[0].sum(0).sqrt(),
        args.out_dir / "uncertainty_figure4.png",
        sid,
    )
    result = {
        "model_file": str(model_file),
        "subjects": list(cases),
        "folds": folds,
        "fold_calibrations": {f: c._asdict() for f, c in scales.items()},
        "settings": {
            "refinement": refinement.as_dict(),
            "probe": args.probe,
            "subject_probe": {
                "templates": list(subject_cases),
                "seeds": [c.seed for c in subject_cases.values()],
                "folds": subject_folds,
                "units": "mm on each template's grid",
            },
            "deformations": args.deformations,
            "reference": args.reference,
            "samples": args.samples,
            "truth_steps": TRUTH_STEPS,
            "smoothing_voxels": SMOOTHING_VOXELS,
            "voxels_per_case": VOXELS_PER_CASE,
            "threads": args.threads,
            "seed": args.seed,
            "fit_iterations": args.fit_iterations,
            "fit_tolerance": FIT_TOLERANCE,
            "uce_bins": "15 equal-count bins of predicted std",
            "label_region": "voxels where the propagated or the manual label is non-background",
        },
        "summary": summary,
        "subject_probe_summary": subject_summary,
        "per_subject": per_subject,
        "translation_probe_recovered": probe,
        "markdown": markdown,
    }
    result["wall_time_s"] = time.time() - start_time  # the whole run
    json_path = write_text(args.out_dir / "uncertainty_calibration.json", json.dumps(result, indent=2) + "\n")
    print(
        f"\n{markdown}\n\nwrote "
        f"{json_path}, uncertainty_reliability.png, uncertainty_figure4.png ({result['wall_time_s']:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
