"""Which form of the pair's residual ranks the answer's errors best, on both calibration probes?

The calibration's residual term (``monai_probreg.uncertainty.residual``) widens the posterior where the registered
images stay unlike. Bundles 0.24.0-0.28.0 took the plain local squared difference; on the subject probe (synthetic
subjects with a bias field and Rician noise, registered by the whole command) its std ranked the errors at Spearman
0.11 per component held out, against 0.32 on the population probe (the atlas deformed, the same intensities on both
sides): a bias field and noise leave a residual everywhere. This study scores forms of the residual, each a
``(window, smoothing, gain_window)`` of :func:`~monai_probreg.uncertainty.residual.residual_variance`:

- ``plain`` (9, 1, 1): bundles 0.24.0-0.28.0;
- ``smoothed`` (9, 3, 1): both images averaged over a 3-voxel box first (the noise of single voxels);
- ``gain`` (9, 1, 25): the warped image times the local gain that matches its 25-voxel mean to the fixed image's
  (a bias field);
- ``smoothed + gain`` (9, 3, 25), and the same with a 41-voxel gain box.

Each form is scored without refitting anything: its residual is scaled, case by case, to the mean of the plain one
(so the sidecar's weight sits in the regime it was fitted in) and sampled at bundle 0.28.0's calibration (std_scale
0.045, bias_fraction 0.165, weight 10^4, 16 samples); the score is the mean over cases and components of
Spearman(sampled std, |error|): the population probe's 6 validation subjects (one deformation each, the calibration's
seeds) and the subject probe's 6 templates (the calibration's seeds). The same form then has to be refitted
(``python -m monai_probreg.fitting --only calibration``) and scored held out (``benchmarks/uncertainty_calibration.py``).

The forms are run by giving the probes' modules a ``residual_variance`` with other defaults (the product reads the
form from :func:`~monai_probreg.uncertainty.residual.residual_form`, one home).

    PYTHONPATH=benchmarks python experiments/residual_forms.py --threads 2   # ~17 min

Prints a table and writes ``experiments/results/residual_forms.json``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from study_setup import finish_study, population_probe_cases, study_parser, study_start, subject_probe_cases

import monai_probreg.fitting.population_probe as population_probe
import monai_probreg.registration.network as registration_network
from monai_probreg.fitting.population_probe import sampled_case_errors
from monai_probreg.fitting.subject_probe import subject_errors
from monai_probreg.metrics.calibration import spearman
from monai_probreg.registration.model import load_model
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES, Calibration
from monai_probreg.uncertainty.residual import PLAIN_RESIDUAL_FORM, residual_variance

RESULTS = Path(__file__).resolve().parent / "results"
# bundle 0.28.0's calibration (fitted for the plain residual): every form is sampled at it
CALIBRATION_0_28 = Calibration(0.045070806777433255, 0.16473948165107596, 2.5, 1e4)
FORMS = {
    "plain": (9, 1, 1),
    "smoothed": (9, 3, 1),
    "gain": (9, 1, 25),
    "smoothed + gain": (9, 3, 25),
    "smoothed + gain 41": (9, 3, 41),
}


def form_residual(form: tuple[int, int, int]):
    """``residual_variance`` with ``form``'s boxes, scaled to the plain residual's mean of the same pair."""
    window, smoothing, gain_window = form

    def residual(warped, fixed, velocity_shape):
        plain = residual_variance(warped, fixed, velocity_shape, **PLAIN_RESIDUAL_FORM)
        other = residual_variance(warped, fixed, velocity_shape, window, smoothing, gain_window)
        return other * (plain.mean() / other.mean().clamp_min(torch.finfo(other.dtype).tiny))

    return residual


def mean_spearman(errors: Sequence[tuple[np.ndarray, ...]]) -> tuple[float, list[float]]:
    per_case = [float(np.mean([spearman(std[k], np.abs(err[k])) for k in range(3)])) for std, err, _ in errors]
    return float(np.mean(per_case)), per_case


def main(argv: Sequence[str] | None = None) -> int:
    ap = study_parser(__doc__, RESULTS)
    ap.add_argument("--forms", nargs="+", default=list(FORMS), choices=list(FORMS))
    args = ap.parse_args(argv)
    started = study_start(args)
    if started is None:
        return 0
    setup = started.setup
    # the population probe's cases, each pair's warped and fixed images kept to score every form on the same cases
    pairs = []

    def keep_pair(warped, fixed, velocity_shape):
        pairs.append((warped.clone(), fixed.clone(), tuple(velocity_shape)))
        return residual_variance(warped, fixed, velocity_shape)

    population_probe.residual_variance = keep_pair
    probes, cases = population_probe_cases(args, started)
    model = load_model(args.bundle_root, setup.model_file, calibrate=False, quality=False)
    templates, subjects = subject_probe_cases(started, model.divisor)
    rows = {}
    for name in args.forms:
        residual = form_residual(FORMS[name])
        for case, (warped, fixed, shape) in zip(cases, pairs):
            case["residual"] = residual(warped, fixed, shape)
        population, population_cases = mean_spearman(
            [sampled_case_errors(setup.network, c, CALIBRATION_0_28, POSTERIOR_SAMPLES) for c in cases]
        )
        registration_network.residual_variance = residual  # the command's path (the subject probe)
        subject, subject_cases = mean_spearman(
            [subject_errors(model, s, CALIBRATION_0_28, POSTERIOR_SAMPLES, setup.refinement) for s in subjects]
        )
        rows[name] = {
            "form": dict(zip(("window", "smoothing", "gain_window"), FORMS[name])),
            "population_spearman": population,
            "subject_spearman": subject,
            "population_per_case": population_cases,
            "subject_per_case": subject_cases,
        }
        print(f"{name}: population {population:.3f}, subject {subject:.3f}", flush=True)
    lines = [
        "| residual form (window, smoothing, gain window) | Spearman per component: population probe | subject probe |",
        "|---|---|---|",
    ]
    lines += [
        f"| {n} {tuple(FORMS[n])} | {r['population_spearman']:.3f} | {r['subject_spearman']:.3f} |"
        for n, r in rows.items()
    ]
    result = {
        "calibration": CALIBRATION_0_28._asdict(),
        "samples": POSTERIOR_SAMPLES,
        "subjects": list(probes.cases),
        "templates": templates,
        "rows": rows,
    }
    return finish_study(args, "residual_forms", started, result, lines)


if __name__ == "__main__":
    sys.exit(main())
