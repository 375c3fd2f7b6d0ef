"""``monai-probreg demo``: register a synthetic subject whose answer is known, and score how well it was recovered
(the lines the command prints: :func:`monai_probreg.cli.messages.demo_report`).

The subject is made from the template (by default the MNI ICBM152 template nilearn ships:
:mod:`monai_probreg.data.template`) by :func:`~monai_probreg.data.synthetic.synthesize_subject`: a random rigid turn
and shift, a random smooth diffeomorphism, a bias field and Rician noise, all drawn from ``--seed``. It is then
registered back onto the template by :func:`~monai_probreg.registration.scan.register_scan`, the code path of
``monai-probreg register`` with its options, and the result is scored against the known transform inside the
template's brain (:mod:`monai_probreg.metrics.recovery`): the displacement error in mm before registration, after
the affine stage and after the whole registration (median, 95th percentile), and the fraction of the error components
inside the calibrated 95% interval of the posterior (``--samples`` >= 2).

Outputs: those of ``register`` plus ``subject.nii.gz`` (the moving image) and ``true_warp.nii.gz`` (the known field,
in ``warp.nii.gz``'s convention); the scores in ``summary.json["demo"]``. The bundle's ``configs/demo.yaml`` runs the
same through :func:`monai_probreg.cli.main.run_bundle_demo`.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from pathlib import Path

from monai_probreg.data.synthetic import SyntheticSettings, brain_mask, synthesize_subject
from monai_probreg.metrics.recovery import displacement_recovery
from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_folder import write_field, write_volume
from monai_probreg.registration.scan import Registered, register_scan
from monai_probreg.spatial.affine import AffineSettings
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES

__all__ = ["COVERAGE_LEVEL", "DEMO_SAMPLES", "run_demo"]

# the demo's --samples default (>= 2 for the std map and its coverage; the map is first order, the same for every K):
# the package's one count, POSTERIOR_SAMPLES
DEMO_SAMPLES = POSTERIOR_SAMPLES

COVERAGE_LEVEL = 0.95  # the calibrated interval whose coverage the demo reports


def run_demo(
    model: LoadedModel,
    fixed: FixedSpace,
    out_dir: str | os.PathLike,
    seed: int = 0,
    settings: SyntheticSettings | None = None,
    options: RegistrationOptions | None = None,
    overwrite: bool = False,
    report: Callable[[str, float], None] | None = None,
) -> dict:
    """Make the subject of ``seed`` from ``fixed`` (the template), register it back, write the outputs into
    ``out_dir`` (all or nothing) and return the summary, whose ``"demo"`` record holds the scores."""
    settings = settings or SyntheticSettings()
    # the command line's rule: --seed seeds the affine stage's sampling (and any posterior samples)
    options = options or RegistrationOptions(samples=DEMO_SAMPLES, seed=seed, affine=AffineSettings(seed=seed))
    template = fixed.image
    start = time.perf_counter()
    subject = synthesize_subject(template, settings, seed)
    synthesis_s = round(time.perf_counter() - start, 3)
    if report is not None:
        report("subject", synthesis_s)  # made before the registration's stages, not counted in their total
    # named where it will be once the outputs are in place (summary.json describes the moving image by its path)
    moving = dataclasses.replace(subject.image, path=str(Path(out_dir).resolve() / "subject.nii.gz"))
    mask = brain_mask(template)

    def check(registered: Registered) -> dict:
        recovery = displacement_recovery(
            subject.true_warp,
            registered.warp,
            mask,
            registered.points,
            registered.affine,
            registered.displacement_variance,
            registered.variance_axes,
            COVERAGE_LEVEL,
            model.interval_dof,
        )
        return {
            "demo": {
                "seed": seed,
                "template": str(Path(template.path).resolve()),
                "settings": settings.as_dict(),
                "rotation_deg": [round(a, 3) for a in subject.rotation_deg],
                "shift_mm": [round(t, 3) for t in subject.shift_mm],
                "truth_inverse_error_mm": round(subject.inverse_error_mm, 4),
                "brain_voxels": int(mask.sum()),
                "interval_dof": model.interval_dof,  # the calibration's intervals: Student-t dof, None: Gaussian
                "synthesis_s": synthesis_s,
                "error_mm": "|phi(p) - phi_true(p)| over the template's non-zero voxels: before registration (the "
                "identity), after the affine stage, after the whole registration",
                **recovery.as_dict(),
            }
        }

    extra = {
        "subject.nii.gz": lambda path: write_volume(path, moving),
        "true_warp.nii.gz": lambda path: write_field(path, subject.true_warp, template.index_to_lps),
    }
    return register_scan(
        model, fixed, moving, out_dir, None, options, overwrite, report, check=check, extra_outputs=extra
    )
