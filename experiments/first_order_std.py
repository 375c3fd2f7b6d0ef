"""Which displacement std ranks the answer's errors: K samples' std, or the posterior's spread to first order?

Up to bundle 0.33.0 the ``displacement_std`` map was the std of K = 16 displacements sampled from the calibrated
posterior. The posterior is a diagonal Gaussian on the velocity grid, so its samples are independent from one velocity
voxel to the next: resized onto the image grid by linear interpolation they have the variance sum_k w_k^2 sigma_k^2,
lower between the velocity grid's voxels than on them (1/8 at a cell's centre in 3-d: a pattern of the grid, not of
the pair); the integration averages them further; and 16 samples estimate a std to about 18%. Since bundle 0.34.0 the
map is first order (:mod:`monai_probreg.uncertainty.spread`: the calibrated velocity std resized like the velocity).
This study scores, side by side at the shipped calibration, on the calibration's own cases (the subject probe's 6
templates through the command's path, the population probe's 6 validation subjects), Spearman(std, |error|) per
component of:

- ``first order`` (shipped since bundle 0.34.0): :func:`~monai_probreg.uncertainty.spread.displacement_variance`;
- ``16 samples`` / ``128 samples``: the std of that many displacements sampled from the posterior, widened by the
  calibration's ``sample_gain`` (as the label entropy's samples are; the map up to bundle 0.33.0 with 16);
- ``independent noise, first order``: the variance of linearly interpolated independent velocity noise,
  sum_k w_k^2 sigma_k^2 (what the samples converge to before the integration's own averaging).

Spearman is unchanged by one scale, so the gain matters only for the samples' integration, which is not linear.

    PYTHONPATH=benchmarks python experiments/first_order_std.py --threads 2   # ~6 min

Prints a table and writes ``experiments/results/first_order_std.json``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import torch
from residual_forms import mean_spearman
from study_setup import finish_study, population_probe_cases, study_parser, study_start, subject_probe_cases

import monai_probreg.registration.network as registration_network
from monai_probreg.blocks.box_resize import interpolation_matrix, resize_displacement_box
from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.fitting.population_probe import case_errors, sampled_case_errors
from monai_probreg.fitting.subject_probe import subject_errors
from monai_probreg.registration.model import load_model
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES, calibrate_log_var
from monai_probreg.uncertainty.posterior_maps import PosteriorMaps
from monai_probreg.uncertainty.samples import sample_log_var

RESULTS = Path(__file__).resolve().parent / "results"
MANY_SAMPLES = 128
VARIANTS = ("first order", f"{POSTERIOR_SAMPLES} samples", f"{MANY_SAMPLES} samples", "independent noise, first order")


def independent_noise_variance(variance: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """(B, D, *size) the variance of independent noise of ``variance`` (B, D, *V) on the velocity grid resized onto
    ``size`` by linear interpolation (each axis' weights squared), in voxels of ``size``."""
    dims = variance.ndim - 2
    source = [int(n) for n in variance.shape[2:]]
    scale = torch.tensor([((m - 1) / (n - 1)) ** 2 for n, m in zip(source, size)], dtype=variance.dtype)
    field = variance * scale.view(1, dims, *[1] * dims)
    for axis, (n, m) in enumerate(zip(source, size)):
        weights = interpolation_matrix(n, m, 0, m, variance.dtype).square()
        field = torch.movedim(torch.movedim(field, 2 + axis, -1) @ weights.T, -1, 2 + axis)
    return field


def sampled_variance(network, mean, log_var, size, num_samples: int, gain: float, seed: int) -> torch.Tensor:
    """(1, D, *size) the variance of ``num_samples`` displacements sampled from N(mean, exp(log_var) gain^2)."""
    generator = torch.Generator().manual_seed(seed)
    total = squares = None
    for start in range(0, num_samples, 4):
        z = sample_velocity(mean, sample_log_var(log_var, gain), min(4, num_samples - start), generator)[:, 0]
        disp = resize_displacement_box(network.integrate(z), size, ([0] * len(size), size)).double()
        total = disp.sum(0) if total is None else total + disp.sum(0)
        squares = disp.square().sum(0) if squares is None else squares + disp.square().sum(0)
    return ((squares - total.square() / num_samples) / (num_samples - 1)).clamp_min(0).float()[None]


def variant_maps(variant: str, gain: float):
    """The command's ``posterior_maps`` with ``variant``'s displacement variance in the shipped map's place."""
    shipped = registration_network.posterior_maps

    def maps(network, mean, log_var, size, num_samples=0, std_scale=1.0, *a, **k):
        result = shipped(network, mean, log_var, size, num_samples, std_scale, *a, **k)
        if variant == "first order" or result.displacement_variance is None:
            return result
        size = tuple(int(s) for s in size)
        with torch.inference_mode():
            calibrated = calibrate_log_var(
                log_var.float(),
                std_scale,
                mean.float(),
                k.get("bias_fraction", 0.0),
                k.get("residual"),
                k.get("residual_weight", 0.0),
            )
            if variant == "independent noise, first order":
                variance = independent_noise_variance(calibrated.exp(), size)
            else:
                count = int(variant.split()[0])
                variance = sampled_variance(network, mean.float(), calibrated, size, count, gain, k.get("seed", 0))
        spacing = torch.as_tensor([float(v) ** 2 for v in k["spacing"]]).view(1, -1, 1, 1, 1)
        variance = (variance * spacing)[0]
        return PosteriorMaps(result.velocity_entropy, variance.sum(0).sqrt(), None, variance)

    return maps


def main(argv: Sequence[str] | None = None) -> int:
    ap = study_parser(__doc__, RESULTS)
    args = ap.parse_args(argv)
    started = study_start(args)
    if started is None:
        return 0
    setup = started.setup
    model = load_model(args.bundle_root, setup.model_file, calibrate=True, quality=False)
    calibration = model.calibration
    templates, subjects = subject_probe_cases(started, model.divisor)
    shipped, rows = registration_network.posterior_maps, {}
    try:
        for variant in VARIANTS:
            registration_network.posterior_maps = variant_maps(variant, calibration.sample_gain)
            score, per_case = mean_spearman(
                [subject_errors(model, s, calibration, POSTERIOR_SAMPLES, setup.refinement) for s in subjects]
            )
            rows[variant] = {"subject_spearman": score, "subject_per_case": per_case}
            print(f"{variant}: subject probe {score:.3f}", flush=True)
    finally:
        registration_network.posterior_maps = shipped
    probes, cases = population_probe_cases(args, started, calibration.error_model)
    for variant in VARIANTS:
        if variant == "first order":
            errors = [case_errors(c, calibration) for c in cases]
        elif variant == "independent noise, first order":
            errors = []
            for c in cases:
                log_var = calibrate_log_var(
                    c["log_var"],
                    calibration.std_scale,
                    c["mean"],
                    calibration.bias_fraction,
                    c["residual"],
                    calibration.residual_weight,
                )
                variance = independent_noise_variance(log_var.exp(), c["size"])[0].flatten(1)[:, c["voxels"]]
                errors.append((variance.sqrt().numpy(), *case_errors(c, calibration)[1:]))
        else:
            count = int(variant.split()[0])
            errors = [sampled_case_errors(setup.network, c, calibration, count) for c in cases]
        rows[variant]["population_spearman"], rows[variant]["population_per_case"] = mean_spearman(errors)
        print(f"{variant}: population probe {rows[variant]['population_spearman']:.3f}", flush=True)
    lines = [
        "| displacement std (shipped calibration) | Spearman per component: subject probe | population probe |",
        "|---|---|---|",
    ]
    lines += [f"| {n} | {r['subject_spearman']:.3f} | {r['population_spearman']:.3f} |" for n, r in rows.items()]
    result = {
        "calibration": calibration._asdict(),
        "templates": templates,
        "subjects": list(probes.cases),
        "rows": rows,
    }
    return finish_study(args, "first_order_std", started, result, lines)


if __name__ == "__main__":
    sys.exit(main())
