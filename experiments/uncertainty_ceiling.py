"""How far can the registration posterior take the label-entropy AUROC? The calibrated posterior against oracles.

The label-entropy AUROC (``uncertainty_calibration.py``, issue #18's voxel target 0.80) asks the posterior to find
the voxels where the atlas labels propagated by the mean registration disagree with the subject's manual labels.
Its samples can only move labels across boundaries by displacements, so the best a posterior can do is bounded by
knowing the mean's *displacement* error exactly. This script measures that bound where it can be known:

1. **Real pairs** (each ``--subjects`` scan -> atlas, as in the calibration benchmark): the wrongly propagated
   fraction, the AUROC of the shipped calibrated posterior's label entropy, and of a baseline with no posterior at
   all, the distance to the nearest boundary of the propagated labels (closer = more suspect). No oracle: the true
   displacement of a real pair is unknown.
2. **Probe pairs**, where the truth is known: the atlas deformed by a draw of the ``population`` probe (the
   calibration benchmark's first deformation of each subject: same seeds), its labels deformed with it. Besides the
   calibrated posterior and the boundary distance, two oracles around the same network mean mu with the true
   subject -> atlas velocity v*:
   - ``oracle variance``: log_var = log((mu - v*)^2), rescaled so its mean variance is ``s`` times the calibrated
     posterior's (``ORACLE_SCALES``, the best is reported): a perfect per-voxel, per-component error magnitude;
   - ``oracle direction``: z_k = mu + t_k (v* - mu), t_k ~ N(0, 1): samples spread along the true error itself, so
     labels flip exactly where moving towards the truth flips them.
   If even the oracles stay near the calibrated posterior on the probe, a better displacement uncertainty cannot
   close the real pairs' gap: what the entropy misses there is not a displacement error the posterior could know.

    PYTHONPATH=benchmarks python experiments/uncertainty_ceiling.py --threads 2   # ~5 min

Prints a table and writes ``experiments/results/uncertainty_ceiling.json``.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from common import write_report
from monai.data import Dataset
from scipy.ndimage import distance_transform_edt
from uncertainty_calibration import propagated_labels, validation_arguments, validation_run

from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.data.dataset import labelled_pairs
from monai_probreg.fitting.population_probe import (
    SEED_STRIDE,
    TRUTH_STEPS,
    population_deformation,
    population_velocities,
    population_velocity,
)
from monai_probreg.metrics.calibration import auroc
from monai_probreg.uncertainty.calibration import calibrate_log_var
from monai_probreg.uncertainty.entropy import label_entropy
from monai_probreg.utils.tensors import plain_tensor

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
ORACLE_SCALES = (1 / 64, 1 / 16, 0.25, 1.0, 4.0)  # oracle variance levels, relative to the calibrated posterior's
# mean variance (label entropy is not scale-free: the best is kept)
ORACLE_EPS = 1e-4  # velocity-grid voxels^2 added to the squared error (log of an exact 0)


def scale_name(scale: float) -> str:
    """ "1/64" for 1/64, "4" for 4: the oracle levels as the JSON and the table name them."""
    return f"1/{round(1 / scale)}" if scale < 1 else f"{scale:g}"


def oracle_log_var(
    mean: torch.Tensor, true_velocity: torch.Tensor, reference_log_var: torch.Tensor, scale: float = 1.0
) -> torch.Tensor:
    """log((mean - true_velocity)^2 + ORACLE_EPS), shifted so that its mean variance is ``scale`` times
    ``reference_log_var``'s: the error magnitude known exactly, at the level of a given posterior."""
    if mean.shape != true_velocity.shape or mean.shape != reference_log_var.shape:
        raise ValueError(
            f"expected mean, true_velocity and reference_log_var of one shape; got {tuple(mean.shape)}, "
            f"{tuple(true_velocity.shape)} and {tuple(reference_log_var.shape)}"
        )
    if not scale > 0:
        raise ValueError(f"scale must be > 0; got {scale}")
    squared = (mean - true_velocity).pow(2) + ORACLE_EPS
    return squared.log() + math.log(scale * float(reference_log_var.exp().mean()) / float(squared.mean()))


def directional_samples(
    mean: torch.Tensor, true_velocity: torch.Tensor, num_samples: int, generator: torch.Generator
) -> torch.Tensor:
    """(K, D, *V) velocities mean + t_k (true_velocity - mean), t_k ~ N(0, 1), for one pair's (1, D, *V) mean and
    truth: a posterior spread along the true error."""
    if mean.shape != true_velocity.shape or mean.shape[0] != 1:
        raise ValueError(
            f"expected mean and true_velocity of one shape (1, D, *V); got {tuple(mean.shape)} and "
            f"{tuple(true_velocity.shape)}"
        )
    t = torch.randn(num_samples, generator=generator).view(-1, *[1] * (mean.ndim - 1))
    return mean + t * (true_velocity - mean)


def boundary_distance(labels: torch.Tensor) -> np.ndarray:
    """Euclidean distance (voxels) of every voxel of a label map (*S) to the nearest voxel whose face neighbour
    carries another label."""
    lab = labels.numpy()
    boundary = np.zeros(lab.shape, dtype=bool)
    for axis in range(lab.ndim):
        differs = np.diff(lab, axis=axis) != 0
        lower = [slice(None)] * lab.ndim
        upper = [slice(None)] * lab.ndim
        lower[axis], upper[axis] = slice(0, -1), slice(1, None)
        boundary[tuple(lower)] |= differs
        boundary[tuple(upper)] |= differs
    return distance_transform_edt(~boundary)


def scores(predicted: torch.Tensor, truth: torch.Tensor, entropies: dict[str, torch.Tensor]) -> dict[str, float]:
    """AUROC of each entropy map and of the boundary distance (negated) for the wrongly propagated voxels, over the
    voxels where either map is non-background (the calibration benchmark's region); NaN where every voxel of the
    region is wrong or none is."""
    region = ((predicted > 0) | (truth > 0)).numpy()
    wrong = (predicted != truth).numpy()[region]
    if wrong.all() or not wrong.any():  # one class only (e.g. a probe that moved nothing): no ranking to score
        return {
            "wrong_fraction": float(wrong.mean()),
            "boundary_distance": math.nan,
            **{name: math.nan for name in entropies},
        }
    result = {
        "wrong_fraction": float(wrong.mean()),
        "boundary_distance": auroc(-boundary_distance(predicted)[region], wrong),
    }
    result.update({name: auroc(e.numpy()[region], wrong) for name, e in entropies.items()})
    return result


def entropy_of(network, velocities: torch.Tensor, atlas_label: torch.Tensor, size) -> torch.Tensor:
    with torch.inference_mode():
        return label_entropy(torch.stack(propagated_labels(network, velocities, atlas_label, size)))


def subject_rows(network, pair, calibration, population, num_samples: int, seed: int) -> dict[str, Any]:
    """The real pair's and the probe pair's scores for one subject."""
    size = tuple(pair["moving"].shape[2:])
    atlas_label = pair["fixed_label"].to(torch.int16)
    generator = torch.Generator().manual_seed(seed)
    with torch.inference_mode():
        posterior = network.posterior(pair["moving"], pair["fixed"])
        log_var = calibrate_log_var(posterior.log_var, calibration.std_scale, posterior.mean, calibration.bias_fraction)
        predicted = warp_labels(atlas_label, network.velocity_to_displacement(-posterior.mean, size))[0, 0]
    z = sample_velocity(posterior.mean, log_var, num_samples, generator=generator).flatten(0, 1)
    real = scores(
        predicted, pair["moving_label"][0, 0].to(torch.int16), {"calibrated": entropy_of(network, z, atlas_label, size)}
    )

    true_velocity = population_velocity(population, torch.Generator().manual_seed(seed))
    with torch.inference_mode():
        forward, _ = population_deformation(pair["fixed"], true_velocity)  # moving = atlas o exp(-v*)
        moving = warp_image(pair["fixed"], forward)
        truth = warp_labels(atlas_label, forward)[0, 0]
        posterior = network.posterior(moving, pair["fixed"])
        log_var = calibrate_log_var(posterior.log_var, calibration.std_scale, posterior.mean, calibration.bias_fraction)
        predicted = warp_labels(atlas_label, network.velocity_to_displacement(-posterior.mean, size))[0, 0]
    mean = posterior.mean
    entropies = {
        "calibrated": entropy_of(
            network, sample_velocity(mean, log_var, num_samples, generator=generator).flatten(0, 1), atlas_label, size
        )
    }
    for s in ORACLE_SCALES:
        oracle = oracle_log_var(mean, true_velocity, log_var, s)
        entropies[f"oracle variance x{scale_name(s)}"] = entropy_of(
            network, sample_velocity(mean, oracle, num_samples, generator=generator).flatten(0, 1), atlas_label, size
        )
    along_error = directional_samples(mean, true_velocity, num_samples, generator)
    entropies["oracle direction"] = entropy_of(network, along_error, atlas_label, size)
    probe = scores(predicted, truth, entropies)
    # an upper bound: the best level, per subject
    levels = [probe[f"oracle variance x{scale_name(s)}"] for s in ORACLE_SCALES]
    probe["oracle variance (best scale)"] = math.nan if np.isnan(levels).all() else float(np.nanmax(levels))
    return {"real": real, "probe": probe}


def main(argv=None) -> int:
    parser = validation_arguments(__doc__)
    parser.set_defaults(out_dir=RESULTS)
    args = parser.parse_args(argv)
    start = time.time()
    run = validation_run(args)
    if run is None:
        return 0
    network, subjects, calibration, index = run.network, run.subjects, run.calibration, run.index
    model_file, preprocessing = run.model_file, run.preprocessing
    train_ids = [i for i in index.ids if i not in subjects]
    population = population_velocities(network, Dataset(labelled_pairs(index, train_ids), transform=preprocessing))
    per_subject = {}
    for n, item in enumerate(Dataset(labelled_pairs(index, subjects), transform=preprocessing)):
        pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
        per_subject[pair["id"]] = rows = subject_rows(
            network, pair, calibration, population, args.samples, args.seed + SEED_STRIDE * n
        )
        print(
            f"[{n + 1}/{len(subjects)}] {pair['id']}: "
            + "; ".join(f"{kind} " + ", ".join(f"{k} {v:.3f}" for k, v in r.items()) for kind, r in rows.items()),
            flush=True,
        )
    summary = {
        kind: {k: float(np.nanmean([r[kind][k] for r in per_subject.values()])) for k in rows[kind]}
        for kind in ("real", "probe")
    }
    columns = ["wrong_fraction", "boundary_distance", "calibrated", "oracle variance (best scale)", "oracle direction"]
    names = {"real": "real (scan -> atlas)", "probe": "probe (atlas deformed by the population model)"}
    table = [
        (
            "| pairs | wrongly propagated | AUROC: boundary distance alone | calibrated posterior | oracle variance "
            "(best of scales) | oracle direction |"
        ),
        "|---|---|---|---|---|---|",
    ]
    for kind, m in summary.items():
        table.append(f"| {names[kind]} | " + " | ".join(f"{m[c]:.3f}" if c in m else "–" for c in columns) + " |")
    result = {
        "model_file": str(model_file),
        "calibration": calibration._asdict(),
        "subjects": list(per_subject),
        "train_subjects_for_the_probe": train_ids,
        "settings": {
            "samples": args.samples,
            "seed": args.seed,
            "oracle_scales": list(ORACLE_SCALES),
            "threads": args.threads,
            "truth_steps": TRUTH_STEPS,
        },
        "summary": summary,
        "per_subject": per_subject,
        "wall_time_s": time.time() - start,
    }
    write_report(args.out_dir, "uncertainty_ceiling", result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
