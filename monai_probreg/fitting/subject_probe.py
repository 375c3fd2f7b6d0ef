"""The calibration's subject probe: synthetic subjects made as the demo makes its own, registered by the command.

The population probe (:mod:`monai_probreg.fitting.population_probe`) deforms the atlas by a field like the model's own
subject -> atlas fields and registers it back on the dataset grid: the same intensities on both sides, no affine
stage. A user's scan (and ``monai-probreg demo``'s subject) also differs by a turn and a shift that the affine stage
takes out only roughly, a bias field and noise, and goes through the whole command (affine, network, refinement),
whose residual error is not proportional to the displacement (the bias term's model). This probe measures that:

- the templates are training subjects' scans (never the MNI152 template that the demo and
  ``benchmarks/generalization.py`` score on, never a validation subject), one synthetic subject each;
- each subject is :func:`~monai_probreg.data.synthetic.synthesize_subject` of its template with the demo's
  ``SyntheticSettings`` (a random rigid turn and shift, a random smooth deformation, a bias field, Rician noise),
  seed ``SUBJECT_SEED + n`` (far from the demo's seeds 0-2);
- it is registered back onto its template by :func:`~monai_probreg.registration.scan.register_scan`, the code path of
  ``monai-probreg register``, its std map made at a given calibration;
- per brain voxel (subsampled) and component: the first-order std of the deformable displacement, its error against the
  truth in the posterior's frame (:mod:`monai_probreg.metrics.recovery`'s ``delta = L^-1 (phi - phi_true)``) and the
  length of the deformable displacement ``L^-1 (phi(p) - A(p))``, all mm: the arrays ``fit_calibration`` takes.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from monai_probreg.data.synthetic import SyntheticSettings, SyntheticSubject, brain_mask, synthesize_subject
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.registration.inputs import FixedSpace, prepare_fixed
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.scan import Registered, register_scan
from monai_probreg.spatial.affine import AffineSettings
from monai_probreg.uncertainty.calibration import Calibration

__all__ = ["SUBJECT_SEED", "SubjectCase", "registered_case", "subject_case", "subject_errors"]

SUBJECT_SEED = 1000  # template n's synthetic subject is drawn with seed SUBJECT_SEED + n (the demo uses 0, 1, 2)


class SubjectCase(NamedTuple):
    """One template and its synthetic subject; ``voxels``: the subsampled brain voxels (flat indices)."""

    template_id: str
    fixed: FixedSpace
    subject: SyntheticSubject
    seed: int
    voxels: np.ndarray


def subject_case(template_id: str, path: str | Path, seed: int, voxels: int, divisor: int = 16) -> SubjectCase:
    """The synthetic subject of the scan at ``path`` (its template) for ``seed``, and ``voxels`` brain voxels drawn
    with the same seed."""
    fixed = prepare_fixed(path, divisor=divisor)
    subject = synthesize_subject(fixed.image, SyntheticSettings(), seed)
    inside = np.flatnonzero(brain_mask(fixed.image))
    pick = np.random.default_rng(seed).permutation(inside.size)[:voxels]
    return SubjectCase(template_id, fixed, subject, seed, np.sort(inside[pick]))


def registered_case(
    model: LoadedModel,
    case: SubjectCase,
    samples: int,
    refinement: RefinementSettings | None,
    error_features: bool = False,
) -> Registered:
    """``case``'s synthetic subject registered onto its template by the command's path (no files kept), ``samples``
    (>= 2: the std map; 0: none) and the affine stage seeded by the case; ``error_features``: the registration also hands the
    pair's error-model features (``RegistrationOptions.error_features``)."""
    options = RegistrationOptions(
        samples=samples,
        seed=case.seed,
        qc=False,
        inverse=False,
        maps=False,
        affine=AffineSettings(seed=case.seed),
        refinement=refinement,
        error_features=error_features,
    )
    kept: list[Registered] = []

    def keep(registered: Registered) -> dict:
        kept.append(registered)
        return {}

    with tempfile.TemporaryDirectory() as tmp:  # the outputs themselves are not needed
        register_scan(model, case.fixed, case.subject.image, Path(tmp) / "out", options=options, check=keep)
    return kept[0]


def subject_errors(
    model: LoadedModel,
    case: SubjectCase,
    calibration: Calibration,
    samples: int,
    refinement: RefinementSettings | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(std, error, |deformable displacement|), each (3, N) mm: the registration of ``case`` by the command's path
    with its posterior calibrated by ``calibration`` (``refinement``: the model's own when None), ``samples`` >= 2 for
    the std map (the same map for every such count; seeded by the case)."""
    model = dataclasses.replace(model, calibration=calibration, quality=None)
    registered = registered_case(model, case, samples, refinement)

    def flat(field: np.ndarray) -> np.ndarray:  # (*S, 3) -> (N, 3) at the case's voxels
        return field.reshape(-1, 3)[case.voxels].astype(np.float64)

    points, truth, warp = flat(case.fixed.points), flat(case.subject.true_warp), flat(registered.warp)
    linear, offset = registered.affine[:3, :3], registered.affine[:3, 3]
    axes = np.asarray(registered.variance_axes, np.float64)
    # the posterior's frame: the deformable step works before the affine, phi = A o (id + d)
    error = np.linalg.solve(linear, (warp - truth).T).T @ axes
    deformable = np.linalg.solve(linear, (points + warp - points @ linear.T - offset).T).T
    std = np.sqrt(np.maximum(flat(registered.displacement_variance), 0.0))
    norm = np.broadcast_to(np.linalg.norm(deformable, axis=1), (3, len(case.voxels)))
    return std.T, error.T, np.ascontiguousarray(norm)
