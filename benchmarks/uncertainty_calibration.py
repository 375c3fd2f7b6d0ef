"""Does the posterior's uncertainty mean anything? Calibration against known deformations, label uncertainty.

1. Ground truth where it exists. For each subject S (default: ``val_ids`` of configs/train.yaml), ``--deformations``
   random smooth velocity fields v are drawn, by one of two ``--probe`` models:
   - ``population`` (default): a statistical deformation model of real anatomy. The model's mean velocities of the
     training subjects (never S) -> atlas give a mean and deviations; v = -(mean + sum_i w_i deviation_i) with
     w_i ~ N(0, 1/(n-1)), a draw from their empirical Gaussian. Realistic magnitude (about the RMS of real
     subject -> atlas fields) and realistic shape: the deformed atlas looks like a new subject. Optimistic: the
     fields lie in the span of what the model itself predicts.
   - ``noise``: white noise on the velocity grid, Gaussian-smoothed (``SMOOTHING_VOXELS``), scaled so the
     displacement RMS in the brain equals the RMS of the model's own displacement for S -> atlas. Same magnitude,
     random shape: out of the training distribution, the mean registration recovers only a fraction of it
     (``recovered_fraction`` in the JSON): the pessimistic bound.
   With our own integration (``TRUTH_STEPS`` squarings at full resolution): moving = R warped by
   exp(v), fixed = R; the true displacement of moving onto fixed is exp(-v). The reference R is the atlas by
   default (``--reference atlas``): the model is trained scan-to-atlas, so the atlas is the only fixed image it
   knows, and the test registers a deformed scan onto it as in use; ``--reference subject`` takes R = S (the
   subject as the fixed image: out of the training distribution, the model then recovers only a fraction of v). K posterior samples give a mean and a
   per-component std, compared with exp(-v) inside the brain (fixed > 0): coverage of the nominal 68% / 95%
   intervals, Spearman(std, |error|) per component and of the vectors (sqrt(sum_c std_c^2) against the length of
   the error vector), each with its ceiling: the Spearman errors drawn from N(0, std^2) themselves would reach
   (|error| of one Gaussian component varies so much at a given std that even a perfect std ranks it only
   partly), UCE (15 equal-count bins), reliability diagram.
2. Label uncertainty on real pairs: S -> atlas; the atlas labels are propagated into S by the K sampled inverse
   warps exp(-z_k); the per-voxel label entropy is scored (AUROC) as a detector of voxels where the atlas labels
   propagated by the mean, exp(-mean), disagree with S's manual labels (voxels where either is non-background).
3. Calibration: a scale of the velocity std and a bias fraction (:mod:`monai_probreg.uncertainty.calibration`: the velocity
   variance per component becomes std_scale^2 sigma^2 + (bias_fraction |mean|)^2), fitted together by coverage
   matching on the displacement errors of part 1 (re-sampled at the fitted pair and refitted, ``FIT_ITERATIONS``). Cross-fitted: the subjects are split in ``--folds`` folds; each fold is scored with the
   scale fitted on the others, with fresh samples drawn from the calibrated posterior. Raw (scale 1) rows use
   the same subjects. ``--write-calibration`` fits on all subjects and writes the sidecar next to the weights.
4. The subject probe (``--subject-probe N``, :mod:`calibration_subjects`): N training subjects' scans are each the
   template of one synthetic subject made as ``monai-probreg demo`` makes its own, registered back by the command's
   path (affine stage, network, refinement) and scored in mm in the posterior's frame. Fitted together with the probe
   of part 1, each probe's coverage matched on its own (``fit_calibration``'s ``groups``); its templates are split
   into the same number of folds and scored held out the same way (the "subject probe" rows).

    python benchmarks/uncertainty_calibration.py --write-calibration   # table, JSON and two PNGs in results/
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from calibration_subjects import SUBJECT_SEED, subject_case, subject_errors
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO, bundle_parser
from monai.data import Dataset
from monai.networks.layers import GaussianFilter
from uncertainty_figures import figure4, reliability_diagram

from monai_probreg.blocks.integration import ScalingAndSquaring, resize_displacement
from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.cli.model import load_model
from monai_probreg.data.dataset import index_dataset, labelled_pairs
from monai_probreg.engines.registration import register_pair
from monai_probreg.metrics.calibration import (
    auroc,
    interval_coverage,
    spearman,
    uncertainty_calibration_error,
)
from monai_probreg.networks.velocity_unet import VelocityPosterior
from monai_probreg.uncertainty.calibration import (
    FIT_LEVELS,
    Calibration,
    calibrate_log_var,
    fit_calibration,
    save_calibration,
)
from monai_probreg.uncertainty.entropy import (
    label_entropy,
    sampled_displacement_moments,
    velocity_entropy,
)
from monai_probreg.utils.files import write_text
from monai_probreg.utils.tensors import plain_tensor
from monai_probreg.weights.loading import load_weights

TRUTH_STEPS = 10  # squarings for the true fields (full resolution; the model uses 7 at half resolution)
SMOOTHING_VOXELS = 6.0  # Gaussian sigma of the random velocity, in velocity-grid voxels (12 mm at 1 mm, /2)
VOXELS_PER_CASE = 400_000  # brain voxels subsampled per case for the displacement metrics (x 3 components)
PROBE_SHIFT_VOXELS = 3.0  # translation of the diagnostic probe (recovered fraction per axis)
FIT_ITERATIONS = 3  # at most this many re-samplings at the fitted pair and refits (the std is not linear in it;
# the two scalars trade along a ridge of near-equal coverage, and 8 refits drift on to a
# smaller scale and a larger bias fraction: Spearman +0.02, label AUROC -0.004, README)
FIT_TOLERANCE = 0.02  # ... stopping once a refit asks for less than this: |scale - 1| and the bias fraction
SEED_STRIDE = 100  # subject n's deformation r is drawn with seed + SEED_STRIDE * n + r (r < SEED_STRIDE)
SUBJECT_PROBE_TEMPLATES = 6  # training subjects whose synthetic subjects make the subject probe (0: none)
POPULATION, SUBJECTS = 0, 1  # the fit's groups: each probe's coverage is matched on its own (fit_calibration)


def random_deformation(
    fixed: torch.Tensor, rms: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A random smooth diffeomorphism on ``fixed``'s grid: (forward displacement exp(v), inverse exp(-v)), both
    (1, 3, *S) voxels, with the forward displacement's RMS in the brain scaled to ``rms``."""
    size = fixed.shape[2:]
    noise = torch.randn((1, 3, *(s // 2 for s in size)), generator=generator)
    velocity = GaussianFilter(3, SMOOTHING_VOXELS)(noise)
    integrate = ScalingAndSquaring(num_steps=TRUTH_STEPS)
    brain = fixed[0, 0] > 0
    for _ in range(2):  # rescale twice: integration is only approximately linear in the velocity
        full = resize_displacement(velocity, size)
        current = integrate(full)[0][:, brain].pow(2).sum(0).mean().sqrt()
        velocity = velocity * (rms / float(current))
    full = resize_displacement(velocity, size)
    return integrate(full), integrate(-full)


def population_velocities(network, dataset) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean (3, *V), deviations (n, 3, *V)) of the model's mean velocities over ``dataset``'s pairs (the training
    subjects -> atlas): the statistical deformation model of the ``population`` probe."""
    velocities = []
    for item in dataset:
        pair = {k: plain_tensor(v)[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
        with torch.inference_mode():
            velocities.append(network.posterior(pair["moving"], pair["fixed"]).mean[0])
    if len(velocities) < 2:
        raise SystemExit(f"the population probe needs >= 2 training subjects; got {len(velocities)}")
    stacked = torch.stack(velocities)
    mean = stacked.mean(0)
    return mean, stacked - mean


def population_velocity(population: tuple[torch.Tensor, torch.Tensor], generator: torch.Generator) -> torch.Tensor:
    """A draw (1, 3, *V) of the population model, velocity-grid voxels: mean + sum_i w_i deviation_i with
    w_i ~ N(0, 1/(n - 1)), a subject -> atlas velocity (the truth the registration of the deformed atlas aims at)."""
    mean, deviations = population
    weights = torch.randn(len(deviations), generator=generator) / math.sqrt(len(deviations) - 1)
    return (mean + torch.einsum("n,n...->...", weights, deviations))[None]


def population_deformation(fixed: torch.Tensor, subject_to_atlas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The fields of a population draw ``subject_to_atlas`` (1, 3, *V) from :func:`population_velocity` on
    ``fixed``'s grid: (forward exp(v), inverse exp(-v)), both (1, 3, *S) voxels, with -v = ``subject_to_atlas``: the
    moving image, ``fixed`` warped by exp(v), takes the shape of a new subject, and the truth exp(-v) is a
    subject -> atlas field."""
    full = resize_displacement(-subject_to_atlas, fixed.shape[2:])  # velocity grid -> image voxels
    integrate = ScalingAndSquaring(num_steps=TRUTH_STEPS)
    return integrate(full), integrate(-full)


def sample_displacements(network, mean, log_var, size, num_samples, generator):
    """Mean and variance (1, 3, *size) of ``num_samples`` displacements drawn from N(mean, exp(log_var))."""
    with torch.inference_mode():
        return sampled_displacement_moments(
            mean, log_var, lambda z: network.velocity_to_displacement(z, size), num_samples, generator
        )


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


def _subsample(mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    index = mask.reshape(-1).nonzero()[:, 0]
    keep = torch.randperm(index.numel(), generator=generator)[:VOXELS_PER_CASE]
    return index[keep]


def posterior_for(network, moving, fixed, refinement=None) -> VelocityPosterior:
    """The posterior a user's registration samples: the network's, with its mean refined for the pair when
    ``refinement`` (evaluate.yaml's ``refinement``) is enabled; the variance stays the network's."""
    output = register_pair(network, moving, fixed, refinement)
    return VelocityPosterior(output.velocity_mean, output.velocity_log_var)


def displacement_case(network, fixed, rms, num_samples, seed, population=None, refinement=None) -> dict[str, Any]:
    """One synthetic case: the posterior (kept, to re-sample when calibrated), the truth on subsampled voxels.
    ``population`` (from :func:`population_velocities`) draws the field from it; None: smoothed noise of RMS ``rms``.
    ``refinement``: the mean is the refined one (:func:`posterior_for`)."""
    generator = torch.Generator().manual_seed(seed)
    if population is not None:
        forward, truth = population_deformation(fixed, population_velocity(population, generator))
    else:
        forward, truth = random_deformation(fixed, rms, generator)
    moving = warp_image(fixed, forward)
    posterior = posterior_for(network, moving, fixed, refinement)
    voxels = _subsample(fixed[0, 0] > 0, generator)
    with torch.inference_mode():
        registration = network.velocity_to_displacement(posterior.mean, tuple(fixed.shape[2:]))
        # the raw velocity std on the image grid, in its voxels: what sampling would give without any smoothing
        velocity_std = resize_displacement((0.5 * posterior.log_var).exp(), tuple(fixed.shape[2:]))
    return {
        "mean": posterior.mean,
        "log_var": posterior.log_var,
        "truth": truth[0].flatten(1)[:, voxels],
        "voxels": voxels,
        "size": tuple(fixed.shape[2:]),
        "seed": seed,
        "displacement_norm": registration[0].flatten(1)[:, voxels].norm(dim=0),
        "velocity_std": velocity_std[0].flatten(1)[:, voxels],
    }


def case_errors(network, case, calibration: Calibration, num_samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(std, error, |mean displacement|), each (3, N): per subsampled voxel and component, from ``num_samples``
    samples of the posterior calibrated by ``calibration``."""
    log_var = calibrate_log_var(case["log_var"], calibration.std_scale, case["mean"], calibration.bias_fraction)
    generator = torch.Generator().manual_seed(case["seed"] + 1)
    mean, variance = sample_displacements(network, case["mean"], log_var, case["size"], num_samples, generator)
    pick = case["voxels"]
    error = mean[0].flatten(1)[:, pick] - case["truth"]
    norm = case["displacement_norm"].expand_as(error)
    return variance[0].flatten(1)[:, pick].sqrt().numpy(), error.numpy(), norm.numpy()


def _pool(errors: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Concatenate the (3, N) arrays of several cases along N."""
    return tuple(np.concatenate([e[i] for e in errors], axis=1) for i in range(len(errors[0])))


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


def label_case(network, pair, calibration: Calibration, num_samples, seed, refinement=None) -> dict[str, Any]:
    """Atlas labels into the subject by K sampled inverse warps; label entropy vs wrongly labelled voxels.
    ``refinement``: around the refined mean (:func:`posterior_for`)."""
    moving, fixed = pair["moving"], pair["fixed"]
    size = tuple(moving.shape[2:])
    posterior = posterior_for(network, moving, fixed, refinement)
    with torch.inference_mode():
        log_var = calibrate_log_var(posterior.log_var, calibration.std_scale, posterior.mean, calibration.bias_fraction)
        atlas_label = pair["fixed_label"].to(torch.int16)
        predicted = warp_labels(atlas_label, network.velocity_to_displacement(-posterior.mean, size))[0, 0]
        generator = torch.Generator().manual_seed(seed)
        samples = []
        for start in range(0, num_samples, 4):
            z = sample_velocity(posterior.mean, log_var, min(4, num_samples - start), generator=generator)
            samples += propagated_labels(network, z.flatten(0, 1), atlas_label, size)
        entropy = label_entropy(torch.stack(samples))
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
    ap.add_argument("--samples", type=int, default=16, help="posterior samples K")
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
        help="templates of the subject probe, the first N training subjects (calibration_subjects.py; fitted "
        "together with --probe, each matched on its own; 0 = none)",
    )
    ap.add_argument("--folds", type=int, default=2, help="cross-fitting folds over the subjects")
    ap.add_argument(
        "--fit-iterations",
        type=int,
        default=FIT_ITERATIONS,
        help="refits at the fitted pair, at most (see FIT_ITERATIONS)",
    )
    ap.add_argument("--write-calibration", action="store_true", help="fit on all subjects, write the sidecar")
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
    torch.set_num_threads(args.threads)
    start_time = time.time()
    if not 1 <= args.deformations <= SEED_STRIDE:  # more would reuse the next subject's seeds
        raise SystemExit(f"--deformations must be in [1, {SEED_STRIDE}]; got {args.deformations}")
    evaluate, model_file, network, subjects = validation_model(args)
    refinement = evaluate.get_parsed_content("refinement")
    if args.refine is not None:
        if args.refine < 0:
            raise SystemExit(f"--refine must be >= 0 steps; got {args.refine}")
        refinement = dataclasses.replace(refinement, num_iterations=args.refine)
    print(
        f"calibrating the {'refined mean' if refinement.enabled else 'network mean'} "
        f"({refinement.num_iterations} refinement steps)",
        flush=True,
    )
    if args.fit_iterations < 1:
        raise SystemExit(f"--fit-iterations must be >= 1; got {args.fit_iterations}")
    if len(subjects) < args.folds or args.folds < 2:
        raise SystemExit(f"--folds must be >= 2 and <= the number of subjects ({len(subjects)}); got {args.folds}")
    index = index_dataset(args.dataset_dir)
    pairs = labelled_pairs(index, subjects)
    dataset = Dataset(pairs, transform=evaluate.get_parsed_content("preprocessing"))
    folds = {sid: i % args.folds for i, sid in enumerate(p["id"] for p in pairs)}
    population = None
    if args.probe == "population":  # training subjects only: the scored subjects never shape the probe
        train_ids = [i for i in index.ids if i not in subjects]
        population = population_velocities(
            network, Dataset(labelled_pairs(index, train_ids), transform=evaluate.get_parsed_content("preprocessing"))
        )
        print(
            f"population probe: mean and {len(population[1])} deviations of the model's velocities of "
            f"{', '.join(train_ids)} -> atlas",
            flush=True,
        )

    cases, items, probe = {}, {}, None
    for n, item in enumerate(dataset):
        pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
        sid, items[pair["id"]] = pair["id"], pair
        with torch.inference_mode():
            real = network(pair["moving"], pair["fixed"]).displacement  # eval mode: the mean registration
        brain = pair["moving"][0, 0] > 0
        rms = float(real[0][:, brain].pow(2).sum(0).mean().sqrt())
        reference = pair["fixed"] if args.reference == "atlas" else pair["moving"]
        if probe is None:  # the atlas (same for every subject): once
            probe = translation_probe(network, pair["fixed"])
            print(
                "translation probe: recovered fraction of a 3-voxel shift of the atlas per axis: "
                + ", ".join(f"{f:.2f}" for f in probe),
                flush=True,
            )
        cases[sid] = [
            displacement_case(
                network, reference, rms, args.samples, args.seed + SEED_STRIDE * n + r, population, refinement
            )
            for r in range(args.deformations)
        ]
        truth_rms = [float(c["truth"].pow(2).sum(0).mean().sqrt()) for c in cases[sid]]
        print(
            f"[{n + 1}/{len(pairs)}] {sid}: {args.deformations} {args.probe} deformations of the {args.reference}, "
            f"true RMS {', '.join(f'{r:.2f}' for r in truth_rms)} voxels (the model's own for {sid} -> atlas: "
            f"{rms:.2f})",
            flush=True,
        )

    raw_calibration = Calibration(1.0, 0.0)
    raw = {sid: [case_errors(network, c, raw_calibration, args.samples) for c in cs] for sid, cs in cases.items()}

    # the subject probe (calibration_subjects.py): synthetic subjects of training scans through the command's path
    if args.subject_probe < 0:
        raise SystemExit(f"--subject-probe must be >= 0 templates; got {args.subject_probe}")
    templates = [i for i in index.ids if i not in subjects][: args.subject_probe]
    command_model = load_model(args.bundle_root, model_file, calibrate=False, quality=False) if templates else None
    subject_cases = {
        tid: subject_case(tid, index.images[tid], SUBJECT_SEED + n, VOXELS_PER_CASE, command_model.divisor)
        for n, tid in enumerate(templates)
    }
    subject_folds = {tid: n % args.folds for n, tid in enumerate(subject_cases)}

    def subject_run(tid: str, calibration: Calibration) -> tuple[np.ndarray, ...]:
        return subject_errors(command_model, subject_cases[tid], calibration, args.samples, refinement)

    subject_raw = {}
    for n, tid in enumerate(subject_cases):
        subject_raw[tid] = subject_run(tid, raw_calibration)
        print(
            f"[subject probe {n + 1}/{len(subject_cases)}] {tid}: raw coverage 95% "
            f"{interval_coverage(*subject_raw[tid][:2], 0.95):.3f}, median error "
            f"{np.median(np.abs(subject_raw[tid][1])):.2f} mm per component",
            flush=True,
        )

    def errors_at(sids: list[str], tids: list[str], calibration: Calibration | None) -> tuple[np.ndarray, ...]:
        """(std, error, norm, group) pooled over the population cases of ``sids`` and the subject cases of
        ``tids``, sampled at ``calibration`` (None: the raw samples already drawn)."""
        parts = [
            (*e, np.full(e[0].shape, POPULATION))
            for s in sids
            for e in (
                raw[s]
                if calibration is None
                else [case_errors(network, c, calibration, args.samples) for c in cases[s]]
            )
        ]
        parts += [
            (*e, np.full(e[0].shape, SUBJECTS))
            for e in (subject_raw[t] if calibration is None else subject_run(t, calibration) for t in tids)
        ]
        return _pool(parts)

    def fit(sids: list[str], tids: list[str]) -> Calibration:
        """Coverage-matching (scale, bias fraction) on the population cases of ``sids`` and the subject-probe cases
        of ``tids``, each probe matched on its own: fitted on the raw samples, then re-sampled at the current pair
        and refitted. Independent velocity noise reaches the displacement damped by a factor kappa
        (interpolation and integration average neighbours; kappa = sampled raw displacement variance / raw velocity
        variance on the image grid), so a refit (c, a) of samples drawn at (s, b) means a variance of about
        c^2 kappa (s^2 sigma^2 + b^2 |mu|^2) + a^2 |u|^2 (u ~ mu once integrated): the new pair is
        (c s, sqrt(c^2 b^2 + a^2 / kappa))."""
        population_std = _pool([e for s in sids for e in raw[s]])[0]
        velocity_std = np.concatenate([c["velocity_std"].numpy() for s in sids for c in cases[s]], axis=1)
        kappa = float(np.mean(population_std**2) / np.mean(velocity_std**2))
        std, error, norm, groups = errors_at(sids, tids, None)
        first = fit_calibration(std, error, norm, groups=groups)
        current = Calibration(first.std_scale, first.bias_fraction / math.sqrt(kappa), first.interval_dof)
        for iteration in range(1, args.fit_iterations + 1):
            std, error, norm, groups = errors_at(sids, tids, current)
            refit = fit_calibration(std, error, norm, groups=groups)
            if (
                abs(refit.std_scale - 1) < FIT_TOLERANCE
                and refit.bias_fraction < FIT_TOLERANCE
                and refit.interval_dof == current.interval_dof
            ):
                break  # the samples at the current pair already cover as nominal as the fit can make them
            current = Calibration(  # the dof is the refit's: it reads the tails of the samples drawn at current
                refit.std_scale * current.std_scale,
                math.hypot(refit.std_scale * current.bias_fraction, refit.bias_fraction / math.sqrt(kappa)),
                refit.interval_dof,
            )
        print(
            f"  fit on {', '.join(sids + [t + ' (subject probe)' for t in tids])}: kappa {kappa:.3f}, "
            f"refit {iteration} ({refit.std_scale:.3f}, "
            f"{refit.bias_fraction:.3f}, dof {refit.interval_dof}) -> std_scale {current.std_scale:.3f}, bias_fraction "
            f"{current.bias_fraction:.3f}, interval dof {current.interval_dof}",
            flush=True,
        )
        return current

    scales = {
        f: fit([s for s in raw if folds[s] != f], [t for t in subject_cases if subject_folds[t] != f])
        for f in range(args.folds)
    }
    print(
        "held-out calibrations per fold (std_scale, bias_fraction, interval dof): "
        + ", ".join(f"({v.std_scale:.3f}, {v.bias_fraction:.2f}, {v.interval_dof})" for v in scales.values()),
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
            errors = raw[sid] if name == "raw" else [case_errors(network, c, cal, args.samples) for c in cases[sid]]
            std, error, _ = _pool(errors)
            labels = label_case(network, items[sid], cal, args.samples, args.seed + 7, refinement)
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
                figure_case = (sid, items[sid], labels)
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
        held_out = {t: subject_run(t, scales[subject_folds[t]]) for t in subject_cases}
        for name, errors in (("raw", subject_raw), ("calibrated", held_out)):
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
    variance = sample_displacements(
        network, labels["mean"], labels["log_var"], size, args.samples, torch.Generator().manual_seed(args.seed)
    )[1]
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
    if args.write_calibration:
        fitted = fit(list(raw), list(subject_cases))
        record = save_calibration(
            model_file,
            fitted.std_scale,
            list(raw) + [f"{t} (subject probe, seed {c.seed})" for t, c in subject_cases.items()],
            args.samples,
            bias_fraction=fitted.bias_fraction,
            refinement=refinement.as_dict() if refinement.enabled else None,
            interval_dof=fitted.interval_dof,
        )
        result["written_calibration"] = {
            "path": str(model_file),
            "std_scale": record.std_scale,
            "bias_fraction": record.bias_fraction,
            "interval_dof": record.interval_dof,
        }
        print(
            f"wrote the calibration of {model_file.name}: std_scale {fitted.std_scale:.3f}, bias_fraction "
            f"{fitted.bias_fraction:.2f}, interval dof {fitted.interval_dof} (all {len(raw)} subjects, {len(subject_cases)} subject-probe templates)"
        )
    result["wall_time_s"] = time.time() - start_time  # the whole run, the written calibration's fit included
    json_path = write_text(args.out_dir / "uncertainty_calibration.json", json.dumps(result, indent=2) + "\n")
    print(
        f"\n{markdown}\n\nwrote "
        f"{json_path}, uncertainty_reliability.png, uncertainty_figure4.png ({result['wall_time_s']:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
