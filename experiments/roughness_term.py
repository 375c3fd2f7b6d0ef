"""Does the answer's own roughness say where it is wrong, beside the pair's residual?

The calibration's residual term (``monai_probreg.uncertainty.residual``) widens the posterior where the registered
images stay unlike; on the subject probe (synthetic subjects registered by the whole command, their truth a smooth
deformation) its std ranks the errors at Spearman 0.16 per component held out. A scratch look at three of that
probe's cases found the errors larger where the answer's displacement bends most (the local mean of its squared
Laplacian: 0.22-0.25 against the shipped std's 0.16-0.19): the data pulled the field away from the prior's
smoothness there, and the truth does not bend like that. This study scores, without refitting anything, spreads made
of the residual ``r`` and a roughness ``R`` of the refined mean velocity on the velocity grid:

- ``gradient``: the prior's own energy density (paper Eq. 5's ``mu^T L mu`` per voxel: the squared differences of
  each component along each axis, summed), averaged over a ``window``-voxel box;
- ``laplacian``: the squared Laplacian of each component, summed, averaged over the box;

each scaled, pair by pair, to the mean of ``r`` (so the sidecar's weight sits in the regime it was fitted in) and
mixed as ``(1 - a) r + a R``, sampled at the shipped calibration (16 samples). The score is the mean over cases and
components of Spearman(sampled std, |error|): the population probe's 6 validation subjects (one deformation each,
the calibration's seeds) and the subject probe's 6 templates (the calibration's seeds), as
``experiments/residual_forms.py`` scores them. A form that ranks better on both would then be refitted
(``python -m monai_probreg.fitting --only calibration``) and scored held out (``benchmarks/uncertainty_calibration.py``).

    PYTHONPATH=benchmarks python experiments/roughness_term.py --threads 2   # ~15 min

Prints a table and writes ``experiments/results/roughness_term.json``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import torch
from residual_forms import mean_spearman
from study_setup import finish_study, population_probe_cases, study_parser, study_start, subject_probe_cases

import monai_probreg.registration.network as registration_network
from monai_probreg.fitting.population_probe import sampled_case_errors
from monai_probreg.fitting.subject_probe import subject_errors
from monai_probreg.losses.lncc import box_sum
from monai_probreg.registration.model import load_model
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES

RESULTS = Path(__file__).resolve().parent / "results"
# name -> (roughness, box window on the velocity grid, mixing fraction a)
FORMS = {
    "residual (shipped)": (None, 1, 0.0),
    "gradient 3": ("gradient", 3, 1.0),
    "laplacian 3": ("laplacian", 3, 1.0),
    "laplacian 5": ("laplacian", 5, 1.0),
    "residual + gradient 3": ("gradient", 3, 0.5),
    "residual + laplacian 3": ("laplacian", 3, 0.5),
    "residual + laplacian 5": ("laplacian", 5, 0.5),
    "residual + laplacian 3 (a = 0.25)": ("laplacian", 3, 0.25),
    "residual + laplacian 3 (a = 0.75)": ("laplacian", 3, 0.75),
}


def roughness(mean: torch.Tensor, kind: str, window: int) -> torch.Tensor:
    """(1, 1, *V) the local roughness of the mean velocity (1, D, *V), velocity-grid units."""
    dims = mean.ndim - 2
    mean = mean.double()
    if kind == "gradient":
        energy = sum(g.square() for g in torch.gradient(mean, dim=tuple(range(2, mean.ndim))))
    else:
        padded = torch.nn.functional.pad(mean, [1, 1] * dims, mode="replicate")
        centre = padded[(slice(None), slice(None), *[slice(1, -1)] * dims)]
        lap = -2 * dims * centre
        for axis in range(dims):
            for lo, hi in ((0, -2), (2, None)):
                index = [slice(1, -1)] * dims
                index[axis] = slice(lo, hi)
                lap = lap + padded[(slice(None), slice(None), *index)]
        energy = lap.square()
    energy = energy.sum(1, keepdim=True)
    return (box_sum(energy, window) / window**dims if window > 1 else energy).float()


def mixed(residual: torch.Tensor, mean: torch.Tensor, form) -> torch.Tensor:
    kind, window, a = form
    if kind is None or a == 0:
        return residual
    rough = roughness(mean, kind, window)
    rough = rough * (residual.mean() / rough.mean().clamp_min(torch.finfo(rough.dtype).tiny))
    return (1 - a) * residual + a * rough


def main(argv: Sequence[str] | None = None) -> int:
    ap = study_parser(__doc__, RESULTS)
    ap.add_argument("--forms", nargs="+", default=list(FORMS), choices=list(FORMS))
    args = ap.parse_args(argv)
    started = study_start(args)
    if started is None:
        return 0
    setup = started.setup
    probes, cases = population_probe_cases(args, started)
    shipped = [c["residual"] for c in cases]
    model = load_model(args.bundle_root, setup.model_file, calibrate=True, quality=False)
    calibration = model.calibration
    templates, subjects = subject_probe_cases(started, model.divisor)
    command_maps = registration_network.posterior_maps
    rows = {}
    for name in args.forms:
        form = FORMS[name]
        for case, residual in zip(cases, shipped):
            case["residual"] = mixed(residual, case["mean"], form)
        population, population_cases = mean_spearman(
            [sampled_case_errors(setup.network, c, calibration, POSTERIOR_SAMPLES) for c in cases]
        )

        def maps(network, mean, log_var, *a, residual=None, form=form, **k):  # the command's path (subject probe)
            return command_maps(network, mean, log_var, *a, residual=mixed(residual, mean, form), **k)

        registration_network.posterior_maps = maps
        subject, subject_cases = mean_spearman(
            [subject_errors(model, s, calibration, POSTERIOR_SAMPLES, setup.refinement) for s in subjects]
        )
        rows[name] = {
            "form": dict(zip(("roughness", "window", "fraction"), form)),
            "population_spearman": population,
            "subject_spearman": subject,
            "population_per_case": population_cases,
            "subject_per_case": subject_cases,
        }
        print(f"{name}: population {population:.3f}, subject {subject:.3f}", flush=True)
    lines = [
        "| spread (velocity grid, each term at the residual's mean) | Spearman per component: population probe "
        "| subject probe |",
        "|---|---|---|",
    ]
    lines += [f"| {n} | {r['population_spearman']:.3f} | {r['subject_spearman']:.3f} |" for n, r in rows.items()]
    result = {
        "calibration": calibration._asdict(),
        "samples": POSTERIOR_SAMPLES,
        "subjects": list(probes.cases),
        "templates": templates,
        "rows": rows,
    }
    return finish_study(args, "roughness_term", started, result, lines)


if __name__ == "__main__":
    sys.exit(main())
