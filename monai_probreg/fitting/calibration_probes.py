"""The calibration's cases and its fit: the population probe and the subject probe, registered once, fitted together.

:func:`calibration_probes` registers the cases of both probes (:mod:`~monai_probreg.fitting.population_probe` on the
bundle's validation subjects, :mod:`~monai_probreg.fitting.subject_probe` on the first training subjects' scans) and
keeps each case's posterior, so that :meth:`CalibrationProbes.errors_at` can map its first-order std again at any
calibration.
:meth:`CalibrationProbes.fit` chooses the residual term's weight (:meth:`CalibrationProbes.residual_weight_for`) and is
the coverage-matching fit of (std_scale, bias_fraction, interval_dof) at that weight on any subset of the cases, each probe's coverage matched on its own (``fit_calibration``'s ``groups``): on all of them for the
sidecar (``python -m monai_probreg.fitting``), on the other folds for the held-out numbers of
``benchmarks/uncertainty_calibration.py``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from monai.data import Dataset
from torch import nn
from tqdm import tqdm

from monai_probreg.data.dataset import DatasetIndex, labelled_pairs
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.population_probe import (
    SEED_STRIDE,
    VOXELS_PER_CASE,
    case_errors,
    case_velocity_std,
    displacement_case,
    pool_errors,
    population_velocities,
    sampled_case_variance,
)
from monai_probreg.fitting.subject_probe import SUBJECT_SEED, SubjectCase, subject_case, subject_errors
from monai_probreg.metrics.calibration import interval_coverage, spearman
from monai_probreg.registration.model import LoadedModel, load_model
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES, Calibration, fit_calibration
from monai_probreg.utils.tensors import plain_tensor

__all__ = [
    "FIT_ITERATIONS",
    "FIT_TOLERANCE",
    "GAIN_ITERATIONS",
    "GAIN_TOLERANCE",
    "RESIDUAL_WEIGHTS",
    "SUBJECT_PROBE_TEMPLATES",
    "POPULATION",
    "SUBJECTS",
    "ProbeSettings",
    "CalibrationProbes",
    "calibration_probes",
]

_LOG = logging.getLogger(__name__)

FIT_ITERATIONS = 3  # at most this many re-samplings at the fitted pair and refits (the std is not linear in it;
# the two scalars trade along a ridge of near-equal coverage, and more refits drift on to a
# smaller scale and a larger bias fraction without covering better)
FIT_TOLERANCE = 0.02  # ... stopping once a refit asks for less than this: |scale - 1| and the bias fraction
GAIN_ITERATIONS = 6  # at most this many measurements of the samples' damping (sample_gain_for) ...
GAIN_TOLERANCE = 0.01  # ... stopping once the samples' mean variance is within this fraction of the map's
SUBJECT_PROBE_TEMPLATES = 6  # training subjects whose synthetic subjects make the subject probe (0: none)
POPULATION, SUBJECTS = 0, 1  # the fit's groups: each probe's coverage is matched on its own (fit_calibration)
RAW = Calibration(1.0, 0.0)
# the residual term's weights the fit tries (Calibration.residual_weight; velocity-grid voxels^2 per squared intensity):
# the one whose std map ranks the population probe's errors best (Spearman per component) is kept
RESIDUAL_WEIGHTS: tuple[float, ...] = (0.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0, 10000.0)


class ProbeSettings(NamedTuple):
    """The probes' cases: ``deformations`` population-probe cases per subject, ``samples`` posterior samples (the
    fit's measure of the samples' damping, ``sample_gain``), the
    ``seed`` of the population probe, ``subject_probe`` templates, the population probe's model (``probe``:
    "population", or "noise": smoothed noise of the RMS of the subject's own registration) and the image it deforms
    (``reference``: "atlas", or "subject")."""

    deformations: int = 1
    samples: int = POSTERIOR_SAMPLES
    seed: int = 0
    subject_probe: int = SUBJECT_PROBE_TEMPLATES
    probe: str = "population"
    reference: str = "atlas"


@dataclass
class CalibrationProbes:
    """The registered cases of both probes. ``cases``: each validation subject's population-probe cases (posterior and
    truth); ``items``: its preprocessed pair (moving = the subject, fixed = the atlas); ``subject_cases``: each
    template's synthetic subject; ``raw`` / ``subject_raw``: their errors and the raw posterior's std map."""

    network: nn.Module
    samples: int
    refinement: RefinementSettings
    cases: dict[str, list[dict]]
    items: dict[str, dict]
    subject_cases: dict[str, SubjectCase]
    command_model: LoadedModel | None
    raw: dict[str, list[tuple[np.ndarray, ...]]]
    subject_raw: dict[str, tuple[np.ndarray, ...]]
    residual_weights: tuple[float, ...] = RESIDUAL_WEIGHTS  # the residual term's weights fit() chooses among
    # the error model the term reads (Calibration.error_model; the cases were registered with it); None: the residual
    error_model: tuple[float, ...] | None = None

    def population_errors(self, sid: str, calibration: Calibration) -> list[tuple[np.ndarray, ...]]:
        """(std, error, norm) of each population case of ``sid``, the std map at ``calibration``."""
        return [case_errors(c, calibration) for c in self.cases[sid]]

    def subject_errors(self, tid: str, calibration: Calibration) -> tuple[np.ndarray, ...]:
        """(std, error, norm) of template ``tid``'s synthetic subject, registered by the command's path."""
        return subject_errors(self.command_model, self.subject_cases[tid], calibration, self.samples, self.refinement)

    def errors_at(
        self,
        sids: list[str],
        tids: list[str],
        calibration: Calibration | None,
    ) -> tuple[np.ndarray, ...]:
        """(std, error, norm, group) pooled over the population cases of ``sids`` and the subject cases of
        ``tids``, the std maps at ``calibration`` (None: the raw posterior's, already mapped)."""
        parts = [
            (*e, np.full(e[0].shape, POPULATION))
            for s in sids
            for e in (self.raw[s] if calibration is None else self.population_errors(s, calibration))
        ]
        parts += [
            (*e, np.full(e[0].shape, SUBJECTS))
            for e in (self.subject_raw[t] if calibration is None else self.subject_errors(t, calibration) for t in tids)
        ]
        return pool_errors(parts)

    def fit(self, sids: list[str], tids: list[str], iterations: int = FIT_ITERATIONS) -> Calibration:
        """The residual term's weight (:meth:`residual_weight_for`), then coverage-matching (scale, bias fraction,
        dof) on the population cases of ``sids`` and the subject-probe cases of ``tids``, each probe matched on its
        own: fitted on the std maps of the unscaled posterior with that weight, then mapped again at the current pair
        and refitted, at most ``iterations`` times (the map is first order: a refit (c, a) of maps at (s, b) means a
        variance of about c^2 (s^2 sigma^2 + b^2 |mu|^2) + a^2 |u|^2, u ~ mu once integrated, so the new pair is
        (c s, sqrt(c^2 b^2 + a^2)); the bias term is where the map is not exactly linear). Last, the samples' gain
        (:meth:`sample_gain_for`)."""
        weight = self.residual_weight_for(sids) if len(self.residual_weights) > 1 else self.residual_weights[0]
        unit = self.unit_scale(sids, weight)
        # the term's spread, as large as the network's alone
        base = Calibration(unit, 0.0, None, weight, self.error_model)
        std, error, norm, groups = self.errors_at(sids, tids, None if weight == 0 else base)
        first = fit_calibration(std, error, norm, groups=groups)
        current = Calibration(first.std_scale * unit, first.bias_fraction, first.interval_dof, weight, self.error_model)
        for iteration in tqdm(range(1, iterations + 1), desc="calibration refits", unit="refit", disable=None):
            std, error, norm, groups = self.errors_at(sids, tids, current)
            refit = fit_calibration(std, error, norm, groups=groups)
            if (
                abs(refit.std_scale - 1) < FIT_TOLERANCE
                and refit.bias_fraction < FIT_TOLERANCE
                and refit.interval_dof == current.interval_dof
            ):
                break  # the maps at the current pair already cover as nominal as the fit can make them
            current = Calibration(  # the dof is the refit's: it reads the tails of the maps at current
                refit.std_scale * current.std_scale,
                math.hypot(refit.std_scale * current.bias_fraction, refit.bias_fraction),
                refit.interval_dof,
                weight,
                self.error_model,
            )
        current = current._replace(sample_gain=self.sample_gain_for(sids, current))
        _LOG.info(
            f"  fit on {', '.join(sids + [t + ' (subject probe)' for t in tids])}: "
            f"refit {iteration} ({refit.std_scale:.3f}, "
            f"{refit.bias_fraction:.3f}, dof {refit.interval_dof}) -> std_scale {current.std_scale:.4f}, bias_fraction "
            f"{current.bias_fraction:.3f}, interval dof {current.interval_dof}, residual weight {weight:g}, sample gain "
            f"{current.sample_gain:.3f}"
        )
        return current

    def sample_gain_for(self, sids: list[str], calibration: Calibration) -> float:
        """The gain whose samples spread as far as the std map says, on average over the population cases of
        ``sids`` at ``calibration``: independent velocity noise reaches the displacement damped (interpolation and
        integration average neighbours) by kappa, the mean variance of :attr:`samples` sampled displacements over the
        map's; the gain starts at 1 and is multiplied by 1 / sqrt(kappa) measured at it until kappa is within
        :data:`GAIN_TOLERANCE` of 1, at most :data:`GAIN_ITERATIONS` times (the integration is not linear in the noise:
        the damping grows with the spread, so one pass leaves the samples short)."""
        cases = [c for s in sids for c in self.cases[s]]
        mapped = np.mean([np.square(case_errors(c, calibration)[0]).mean() for c in cases])
        gain = 1.0
        for _ in range(GAIN_ITERATIONS):
            at = calibration._replace(sample_gain=gain)
            kappa = np.mean([sampled_case_variance(self.network, c, at, self.samples).mean() for c in cases]) / mapped
            if abs(kappa - 1.0) < GAIN_TOLERANCE:
                break
            gain *= float(1.0 / math.sqrt(kappa))
        return gain

    def unit_scale(self, sids: list[str], weight: float) -> float:
        """The scale that gives the posterior with the residual term of ``weight`` the mean velocity variance of the
        network's alone over the population cases' voxels of ``sids`` (1 for weight 0): the fit starts from a spread
        of the network's own size whatever the weight."""
        if weight == 0:
            return 1.0
        cases = [c for s in sids for c in self.cases[s]]
        network = np.mean([float(c["velocity_std"].square().mean()) for c in cases])
        widened = np.mean([float(case_velocity_std(c, weight).square().mean()) for c in cases])
        return float(math.sqrt(network / widened))

    def residual_weight_for(self, sids: list[str]) -> float:
        """The weight of :attr:`residual_weights` whose posterior ranks the errors of the population cases of ``sids``
        best: the mean over cases and components of Spearman(std map, |error|), each weight mapped at its
        :meth:`unit_scale`. The scale hardly changes a ranking, so it is chosen before the coverage fit; the subject
        probe, which needs the whole command per weight, is left out of the choice (its coverage is matched as
        before)."""
        scores = []
        for weight in self.residual_weights:
            at = Calibration(self.unit_scale(sids, weight), 0.0, None, weight, self.error_model)
            errors = [e for s in sids for e in self.population_errors(s, at)]
            scores.append(
                float(np.mean([spearman(std[k], np.abs(err[k])) for std, err, _ in errors for k in range(3)]))
            )
        best = self.residual_weights[int(np.argmax(scores))]
        _LOG.info(
            "  residual weight by Spearman(std, |error|) per component: "
            + ", ".join(f"{w:g}: {r:.3f}" for w, r in zip(self.residual_weights, scores))
            + f" -> {best:g}"
        )
        return best

    def fitted_on(self) -> list[str]:
        """The cases' names as the sidecar records them: the subjects, then each template with its seed."""
        return list(self.cases) + [f"{t} (subject probe, seed {c.seed})" for t, c in self.subject_cases.items()]


def calibration_probes(
    network: nn.Module,
    preprocessing,
    index: DatasetIndex,
    subjects: Sequence[str],
    bundle_root: str | Path,
    model_file: str | Path,
    refinement: RefinementSettings,
    settings: ProbeSettings = ProbeSettings(),
    error_model: Sequence[float] | None = None,
) -> CalibrationProbes:
    """Register both probes' cases (``settings``). ``network`` (evaluate.yaml's, eval mode) registers the population
    probe of the labelled ``subjects`` of ``index`` (``preprocessing``: evaluate.yaml's), subject n's r-th case drawn
    with seed ``seed + SEED_STRIDE n + r``, its deformation model made of the other subjects' velocities. The subject
    probe takes the first ``subject_probe`` other subjects' scans, registered by the command line's model of
    ``bundle_root`` with ``model_file`` (raw posterior). ``refinement``: the refinement of the mean both probes
    calibrate; ``error_model``: the error model the calibration's term reads (None: the pair's residual)."""
    error_model = None if error_model is None else tuple(float(c) for c in error_model)
    deformations, samples, seed, subject_probe, probe, reference = settings
    pairs = labelled_pairs(index, list(subjects))
    population = None
    if probe == "population":  # training subjects only: the scored subjects never shape the probe
        train_ids = [i for i in index.ids if i not in subjects]
        population = population_velocities(network, Dataset(labelled_pairs(index, train_ids), transform=preprocessing))
        _LOG.info(
            f"population probe: mean and {len(population[1])} deviations of the model's velocities of "
            f"{', '.join(train_ids)} -> atlas"
        )
    cases, items = {}, {}
    progress = tqdm(Dataset(pairs, transform=preprocessing), desc="population probe", unit="subject", disable=None)
    for n, item in enumerate(progress):
        pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
        sid, items[pair["id"]] = pair["id"], pair
        with torch.inference_mode():
            real = network(pair["moving"], pair["fixed"]).displacement  # eval mode: the mean registration
        brain = pair["moving"][0, 0] > 0
        rms = float(real[0][:, brain].pow(2).sum(0).mean().sqrt())
        fixed = pair["fixed"] if reference == "atlas" else pair["moving"]
        cases[sid] = [
            displacement_case(
                network, fixed, rms, samples, seed + SEED_STRIDE * n + r, population, refinement, error_model
            )
            for r in range(deformations)
        ]
        truth_rms = [float(c["truth"].pow(2).sum(0).mean().sqrt()) for c in cases[sid]]
        _LOG.info(
            f"[{n + 1}/{len(pairs)}] {sid}: {deformations} {probe} deformations of the {reference}, "
            f"true RMS {', '.join(f'{r:.2f}' for r in truth_rms)} voxels (the model's own for {sid} -> atlas: "
            f"{rms:.2f})"
        )
    raw = {sid: [case_errors(c, RAW) for c in cs] for sid, cs in cases.items()}

    templates = [i for i in index.ids if i not in subjects][:subject_probe]
    command_model = load_model(bundle_root, model_file, calibrate=False, quality=False) if templates else None
    subject_cases = {
        tid: subject_case(tid, index.images[tid], SUBJECT_SEED + n, VOXELS_PER_CASE, command_model.divisor)
        for n, tid in enumerate(templates)
    }
    probes = CalibrationProbes(
        network, samples, refinement, cases, items, subject_cases, command_model, raw, {}, error_model=error_model
    )
    for n, tid in enumerate(tqdm(subject_cases, desc="subject probe", unit="template", disable=None)):
        probes.subject_raw[tid] = errors = probes.subject_errors(tid, RAW)
        _LOG.info(
            f"[subject probe {n + 1}/{len(subject_cases)}] {tid}: raw coverage 95% "
            f"{interval_coverage(*errors[:2], 0.95):.3f}, median error {np.median(np.abs(errors[1])):.2f} mm per "
            "component"
        )
    return probes
