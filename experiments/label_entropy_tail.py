"""Where does the label-entropy AUROC stop at 16 samples? The voxels that every sample reads wholly.

The bundle's label entropy (``posterior_maps`` with the moving labels: each of K calibrated posterior samples reads
the atlas labels with partial volume, :class:`~monai_probreg.uncertainty.partial_volume.PartialVolumeLabels`) is 0
wherever every sample read one label wholly. Those voxels tie at 0 in the AUROC of wrongly propagated voxels
(``benchmarks/uncertainty_calibration.py``, issue "An uncertainty that belongs to the answer": target 0.76), however
many of them are wrong. This study scores, on the bundle's validation subjects' real pairs (subject -> atlas, refined
as the bundle registers them, the shipped calibration, the benchmark's own ``label_case``), for the samples the
bundle draws (Student-t with the calibration's ``interval_dof``, :mod:`monai_probreg.uncertainty.samples`) and for
the Gaussian samples of older bundles (the same calibration, ``interval_dof`` None for the samples alone), side by
side:

- ``label entropy, K``: the bundle's map (the benchmark's label AUROC for that subject);
- ``zero_fraction`` / ``wrong_among_zero``: the share of the scored region whose entropy is 0 (below
  ``ZERO_ENTROPY``), and the share of those voxels that are wrongly propagated (``wrong_fraction``: of all);
- ``ties broken by the posterior's tail``: the same map, its zero voxels ordered below every non-zero one by the
  distance to the nearest boundary of the propagated labels in units of the posterior's first-order displacement
  std there (:mod:`monai_probreg.uncertainty.spread`, RMS over components, carried to the subject's voxel by the
  inverse mean): the order of the posterior's own probability of a label flip, Phi(-d / sigma), which 16 samples
  cannot resolve;
- ``ties broken by the boundary distance``: the same, ordered by the distance alone (no posterior);
- ``boundary_distance``: the distance alone, negated (``uncertainty_ceiling.py``'s baseline).

Only the ranking of the tied voxels changes; the map's values elsewhere are the bundle's.

    PYTHONPATH=benchmarks python experiments/label_entropy_tail.py --threads 2   # ~2 min

Prints a table and writes ``experiments/results/label_entropy_tail.json``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import write_report
from monai.data import Dataset
from uncertainty_calibration import LABEL_SEED_OFFSET, label_case, validation_arguments, validation_run
from uncertainty_ceiling import boundary_distance, scores

from monai_probreg.blocks.warp import warp_image
from monai_probreg.data.dataset import labelled_pairs
from monai_probreg.fitting.population_probe import posterior_for
from monai_probreg.uncertainty.spread import displacement_variance
from monai_probreg.utils.tensors import plain_tensor

RESULTS = Path(__file__).resolve().parent / "results"
ZERO_ENTROPY = 1e-6  # nats: an entropy below this is a voxel every sample read (to float rounding) wholly
SAMPLES = {  # the samples' form: the calibration each is drawn with, from the shipped one
    "Student-t samples (shipped)": lambda calibration: calibration,
    "Gaussian samples (older bundles)": lambda calibration: calibration._replace(interval_dof=None),
}


def tie_broken(entropy: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
    """``entropy`` (*S) where it is at least ``ZERO_ENTROPY``; below it, a score under every such value (<= 0) that
    falls as ``key`` (*S, >= 0) grows: the tied voxels ranked by ``key``, the others as they were."""
    if entropy.shape != key.shape:
        raise ValueError(f"expected a key of the entropy's shape {tuple(entropy.shape)}; got {tuple(key.shape)}")
    if bool((key < 0).any()):
        raise ValueError("expected a key >= 0 (a distance)")
    tied = -key / (1 + key)  # in (-1, 0], decreasing in key
    return torch.where(entropy < ZERO_ENTROPY, tied, entropy)


def tail_std(network, mean: torch.Tensor, log_var: torch.Tensor, size) -> torch.Tensor:
    """(*S) the calibrated posterior's first-order displacement std (voxels, RMS over components) on the fixed image's
    grid, read at each voxel of the moving image's grid where the inverse mean exp(-mean) takes it (where the
    samples' labels are read)."""
    with torch.inference_mode():
        std = displacement_variance(log_var, size).mean(1, keepdim=True).sqrt()
        inverse = network.velocity_to_displacement(-mean, size)
        return warp_image(std, inverse)[0, 0]


def subject_row(network, pair, calibration, posterior, samples: int, seed: int) -> dict[str, float]:
    """The AUROCs and tie counts of one real pair (module docstring), its ``posterior`` (``posterior_for``) given."""
    case = label_case(network, pair, calibration, samples, seed, posterior=posterior)
    entropy, predicted, truth = case["entropy"], case["predicted"], case["truth"]
    size = tuple(pair["moving"].shape[2:])
    distance = torch.from_numpy(boundary_distance(predicted)).float()
    sigma = tail_std(network, case["mean"], case["log_var"], size).clamp_min(1e-6)
    region = ((predicted > 0) | (truth > 0)).numpy()
    wrong = (predicted != truth).numpy()[region]
    zero = (entropy < ZERO_ENTROPY).numpy()[region]
    row = scores(
        predicted,
        truth,
        {
            f"label entropy, K = {samples}": entropy,
            "ties broken by the posterior's tail (distance / std)": tie_broken(entropy, distance / sigma),
            "ties broken by the boundary distance (no posterior)": tie_broken(entropy, distance),
        },
    )
    row["zero_fraction"] = float(zero.mean())
    row["wrong_among_zero"] = float(wrong[zero].mean()) if zero.any() else float("nan")
    return row


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
    per_subject: dict[str, dict[str, dict[str, float]]] = {}
    seed = args.seed + LABEL_SEED_OFFSET  # the calibration benchmark's samples
    for n, item in enumerate(Dataset(labelled_pairs(run.index, subjects), transform=run.preprocessing)):
        pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
        # one registration per pair: the forms differ in the samples alone
        posterior = posterior_for(network, pair["moving"], pair["fixed"], refinement, calibration.error_model)
        per_subject[pair["id"]] = rows = {
            form: subject_row(network, pair, drawn(calibration), posterior, args.samples, seed)
            for form, drawn in SAMPLES.items()
        }
        for form, row in rows.items():
            print(
                f"[{n + 1}/{len(subjects)}] {pair['id']}, {form}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items())
            )
    summary = {
        form: {k: float(np.nanmean([r[form][k] for r in per_subject.values()])) for k in per_subject[pair["id"]][form]}
        for form in SAMPLES
    }
    lines = [
        "| real pairs, the shipped calibration (mean over subjects) | " + " | ".join(SAMPLES) + " |",
        "|---|" + "---|" * len(SAMPLES),
    ]
    lines += [
        f"| {k} | " + " | ".join(f"{summary[f][k]:.3f}" for f in SAMPLES) + " |" for k in summary[next(iter(SAMPLES))]
    ]
    result = {
        "model_file": str(run.model_file),
        "calibration": calibration._asdict(),
        "refinement_steps": refinement.num_iterations,
        "subjects": list(per_subject),
        "settings": {"samples": args.samples, "seed": args.seed, "threads": args.threads, "zero_entropy": ZERO_ENTROPY},
        "summary": summary,
        "per_subject": per_subject,
        "wall_time_s": time.time() - start,
    }
    write_report(args.out_dir, "label_entropy_tail", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
