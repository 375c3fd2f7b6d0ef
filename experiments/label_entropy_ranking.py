"""How much of the label-entropy AUROC is lost to how the labels are sampled, rather than to the posterior?

The product's label entropy (``monai_probreg.uncertainty.entropy.label_entropy``) propagates the atlas labels by
each of K posterior samples with nearest-neighbour interpolation and takes the entropy of the K labels per voxel. With
K = 16 a voxel whose label flips in 3% of the posterior's mass shows no entropy in most runs, so many wrongly labelled
voxels tie with the certain ones at 0. This study scores, on the bundle's validation subjects' real pairs (subject ->
atlas, refined as the bundle registers them, the shipped calibration), the AUROC of wrongly propagated voxels for:

- ``nearest, K``: the product's entropy, K = ``--samples`` (16) and four times as many;
- ``partial volume, K``: each sample's label read with the weights of linear interpolation over the 8 (4 in 2-d)
  voxels around the sampled point, so a sample contributes a fraction to each label around it: the label
  distribution per voxel is the mean over samples of those weights; its entropy, and one minus the probability of
  the label the mean registration gives;
- ``boundary distance``: the distance (voxels) of each voxel to the nearest voxel of another label in the mean
  registration's labels, negated (``uncertainty_ceiling.py``'s baseline: no posterior at all);
- ``boundary distance / displacement std``: that distance in units of the sampled displacement std (RMS over
  components): how far the posterior's spread reaches across the boundary, with no ties.

    PYTHONPATH=benchmarks python experiments/label_entropy_ranking.py --threads 2   # ~10 min

Prints a table and writes ``experiments/results/label_entropy_ranking.json``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import write_report
from monai.data import Dataset
from uncertainty_calibration import validation_arguments, validation_run
from uncertainty_ceiling import boundary_distance, scores

from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.blocks.warp import warp_labels
from monai_probreg.data.dataset import labelled_pairs
from monai_probreg.engines.registration import register_pair
from monai_probreg.fitting.population_probe import SEED_STRIDE
from monai_probreg.uncertainty.calibration import calibrate_log_var
from monai_probreg.uncertainty.entropy import label_entropy
from monai_probreg.uncertainty.residual import residual_variance
from monai_probreg.utils.tensors import plain_tensor

RESULTS = Path(__file__).resolve().parent / "results"
MANY_SAMPLES = 4  # the nearest-neighbour entropy is also scored with this many times --samples


def partial_volume(labels: torch.Tensor, displacement: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Where one displacement (1, D, *S) (voxels, pull-back: voxel x reads ``labels`` (*S) at x + displacement[x])
    lands among the label voxels: the linear-interpolation weights of the 2^D voxels around each sampled point and
    their labels, (2^D, N) each, N the voxels of S; a corner outside the grid reads label 0. The weights of a voxel sum
    to 1. Written by hand: grid_sample interpolates values, not the labels of its corners."""
    shape = tuple(labels.shape)
    dims = len(shape)
    if tuple(displacement.shape) != (1, dims, *shape):
        raise ValueError(f"expected a displacement (1, {dims}, *{shape}); got {tuple(displacement.shape)}")
    axes = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in shape], indexing="ij")
    point = (torch.stack(axes) + displacement[0].float()).reshape(dims, -1)
    base = point.floor()
    fraction, base = point - base, base.long()
    flat = labels.reshape(-1)
    strides = [int(np.prod(shape[k + 1 :])) for k in range(dims)]
    weights, values = [], []
    for corner in range(2**dims):
        index = torch.zeros(point.shape[1], dtype=torch.long)
        weight = torch.ones(point.shape[1])
        inside = torch.ones(point.shape[1], dtype=torch.bool)
        for k in range(dims):
            upper = (corner >> (dims - 1 - k)) & 1
            coord = base[k] + upper
            inside &= (coord >= 0) & (coord < shape[k])
            index += coord.clamp(0, shape[k] - 1) * strides[k]
            weight *= fraction[k] if upper else 1 - fraction[k]
        weights.append(weight)
        values.append(torch.where(inside, flat[index], torch.zeros_like(flat[index])))
    return torch.stack(weights), torch.stack(values)


def soft_label_maps(labels: torch.Tensor, displacements, answer: torch.Tensor) -> dict[str, torch.Tensor]:
    """From K sampled displacements (each (1, D, *S)) of the label map ``labels`` (*S): the per-voxel label
    distribution (the mean over samples of :func:`partial_volume`'s weights per label), its entropy (nats) and one
    minus its probability of ``answer`` (*S), the label the mean registration gives."""
    num_labels = int(labels.max()) + 1
    histogram = torch.zeros((num_labels, labels.numel()))
    count = 0
    for displacement in displacements:
        weights, values = partial_volume(labels, displacement)
        for w, v in zip(weights, values):
            histogram.scatter_add_(0, v.long()[None], w[None])
        count += 1
    p = (histogram / count).reshape(num_labels, *labels.shape)
    return {
        "entropy": -(p * p.clamp_min(1e-12).log()).sum(0),
        "disagreement": 1 - p.gather(0, answer.long()[None])[0],
    }


def subject_maps(network, pair, calibration, refinement, samples: int, seed: int) -> dict[str, float]:
    """The AUROCs of one real pair (subject -> atlas, registered and refined as the bundle does): the atlas labels
    pulled into the subject by the calibrated posterior's samples."""
    moving, fixed = pair["moving"], pair["fixed"]
    size = tuple(moving.shape[2:])
    output = register_pair(network, moving, fixed, refinement)
    mean = output.velocity_mean
    with torch.inference_mode():
        residual = residual_variance(output.warped, fixed, tuple(mean.shape[2:]))
        log_var = calibrate_log_var(
            output.velocity_log_var,
            calibration.std_scale,
            mean,
            calibration.bias_fraction,
            residual,
            calibration.residual_weight,
        )
        atlas_label = pair["fixed_label"].to(torch.int16)
        predicted = warp_labels(atlas_label, network.velocity_to_displacement(-mean, size))[0, 0]
        generator = torch.Generator().manual_seed(seed)
        velocities = sample_velocity(mean, log_var, MANY_SAMPLES * samples, generator=generator)[:, 0]
        displacements = [network.velocity_to_displacement(-z[None], size) for z in velocities]
        nearest = [warp_labels(atlas_label, d)[0, 0] for d in displacements]
        soft = soft_label_maps(atlas_label[0, 0], displacements[:samples], predicted)
        # the displacement std of the first samples (the product's std map), RMS over components
        first = torch.cat(displacements[:samples]).double()
        std = first.var(0, unbiased=False).mean(0).sqrt().float()
        distance = torch.from_numpy(boundary_distance(predicted)).float()
    truth = pair["moving_label"][0, 0].to(torch.int16)
    maps = {
        f"nearest, K = {samples}: entropy": label_entropy(torch.stack(nearest[:samples])),
        f"nearest, K = {MANY_SAMPLES * samples}: entropy": label_entropy(torch.stack(nearest)),
        f"partial volume, K = {samples}: entropy": soft["entropy"],
        f"partial volume, K = {samples}: 1 - p(the answer's label)": soft["disagreement"],
        f"boundary distance / displacement std, K = {samples} (negated)": -distance / std.clamp_min(1e-6),
    }
    return scores(predicted, truth, maps)


def main(argv=None) -> int:
    parser = validation_arguments(__doc__)
    parser.set_defaults(out_dir=RESULTS)
    args = parser.parse_args(argv)
    start = time.time()
    run = validation_run(args)
    if run is None:
        return 0
    network, subjects, calibration = run.network, run.subjects, run.calibration
    refinement = run.evaluate.get_parsed_content("refinement")
    per_subject = {}
    for n, item in enumerate(Dataset(labelled_pairs(run.index, subjects), transform=run.preprocessing)):
        pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
        per_subject[pair["id"]] = row = subject_maps(
            network, pair, calibration, refinement, args.samples, args.seed + SEED_STRIDE * n + 2
        )
        print(
            f"[{n + 1}/{len(subjects)}] {pair['id']}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()),
            flush=True,
        )
    summary = {k: float(np.nanmean([r[k] for r in per_subject.values()])) for k in row}
    lines = ["| label map (real pairs, the shipped calibration) | AUROC, wrongly propagated voxels |", "|---|---|"]
    lines += [f"| {k} | {v:.3f} |" for k, v in summary.items()]
    result = {
        "model_file": str(run.model_file),
        "calibration": calibration._asdict(),
        "refinement_steps": refinement.num_iterations,
        "subjects": list(per_subject),
        "settings": {"samples": args.samples, "seed": args.seed, "threads": args.threads},
        "summary": summary,
        "per_subject": per_subject,
        "wall_time_s": time.time() - start,
    }
    write_report(args.out_dir, "label_entropy_ranking", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
