"""The quality model's fit: the registrations of one split of subjects, and the fit on the training split's records.

The training split is what the shipped model is fitted on (``python -m monai_probreg.fitting``); the validation
split, made the same way, is what ``benchmarks/failure_detection.py`` scores it on. A split's records
(:func:`split_records`) are its bundle-path cases (:mod:`~monai_probreg.fitting.quality_cases`: each subject to the
atlas and to other subjects, and perturbed by the failure set) and, unless left out, its whole-command cases
(:mod:`~monai_probreg.fitting.command_cases`), each taken from the log when it holds it; the training split's also
have each subject onto itself and onto a near copy (:mod:`~monai_probreg.fitting.self_cases`: pairs with almost
nothing to register, so that the fit's range reaches NCC 1). :func:`fit_quality_model` fits
:class:`~monai_probreg.uncertainty.quality.QualityModel`: the failure model on every record, the Dice regression on
the records with something to register (not the self cases: why in :mod:`~monai_probreg.fitting.self_cases`);
:func:`fit_on_records` fits it on the training split's records.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from torch import nn

from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.command_cases import command_cases
from monai_probreg.fitting.quality_cases import NORMAL, RecordLog, cases_for, logged_cases, record_features, run_case
from monai_probreg.fitting.self_cases import SELF_NAMES
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.quality import DEFAULT_THRESHOLD, QualityModel, entropy_calibration_record, logistic
from monai_probreg.uncertainty.quality_features import QualityFeatures

__all__ = [
    "VALIDATION_SEED_OFFSET",
    "CommandSetup",
    "identity_dice",
    "split_records",
    "with_command_cases",
    "RIDGE",
    "NEWTON_STEPS",
    "fit_quality_model",
    "fit_on_records",
]

VALIDATION_SEED_OFFSET = 100_000  # the validation split's cases are seeded from seed + this (the training's from seed)
RIDGE = 1e-2  # L2 penalty of both fits, on standardised features (numerical safety, not tuning)
NEWTON_STEPS = 50  # logistic fit: Newton iterations (converges in < 15 on the failure set)


def identity_dice(records: Iterable[Mapping[str, Any]]) -> dict[str, float]:
    """Each subject's Dice of no registration onto the atlas, from its normal bundle-path record: the "no
    registration" Dice of its whole-command cases (same scan, same atlas grid)."""
    return {r["moving"]: r["dice_identity"] for r in records if r["fixed"] == ATLAS_ID and r["perturbation"] == NORMAL}


class CommandSetup(NamedTuple):
    """What the whole-command cases need: the dataset, the bundle and weights the command loads (inference.yaml's
    refinement, or ``refine`` steps of it), and the subjects left out of them (``exclude``: the native scans'
    subjects, which the benchmark registers as users bring them)."""

    dataset_dir: Path
    bundle_root: Path
    model_file: Path | None = None
    refine: int | None = None
    exclude: frozenset[str] = frozenset()


def split_records(
    split: str,
    ids: Sequence[str],
    seed: int,
    network: nn.Module,
    calibration: Calibration,
    scans: dict[str, dict],
    refinement: RefinementSettings,
    log: RecordLog,
    command: CommandSetup | None = None,
) -> list[dict]:
    """The records of ``split`` ("train": the fit's cases, "val": every pair) of the subjects ``ids``: the bundle-path
    cases registered by ``network`` on ``scans`` (:func:`~monai_probreg.fitting.quality_cases.load_scans`), the
    entropy feature under ``calibration``, then (``command`` given) :func:`with_command_cases`. ``log``: records taken
    from it and added to it."""
    training = split == "train"
    cases = cases_for(list(ids), seed, training=training)
    records = logged_cases(split, cases, lambda case: run_case(network, calibration, scans, case, refinement), log)
    return records if command is None else with_command_cases(records, seed, command, calibration, log, training)


def with_command_cases(
    records: list[dict],
    seed: int,
    command: CommandSetup,
    calibration: Calibration,
    log: RecordLog | None = None,
    training: bool = False,
) -> list[dict]:
    """``records`` and the whole-command cases of their subjects but ``command.exclude``
    (:func:`~monai_probreg.fitting.command_cases.command_cases`, seeded with ``seed``, the entropy feature under
    ``calibration``; their "no registration" Dice from ``records``); ``training``: each subject onto itself too."""
    return records + command_cases(
        command.dataset_dir,
        sorted({r["moving"] for r in records} - command.exclude),
        command.bundle_root,
        command.model_file,
        identity_dice(records),
        seed,
        command.refine,
        calibration,
        log,
        self_cases=training,
    )


def fit_quality_model(
    features: Sequence[QualityFeatures],
    dice: Sequence[float],
    failures: Sequence[bool],
    threshold: float = DEFAULT_THRESHOLD,
    fitted_on: Sequence[str] = (),
    refinement: dict | None = None,
    entropy_calibration: Calibration | None = None,
    for_dice: Sequence[bool] | None = None,
) -> QualityModel:
    """Fit both models on registrations with known outcome (training subjects only): ``features`` of the network's
    registrations, ``dice`` and ``failures`` of the registrations users get (refined with ``refinement``, a
    ``RefinementSettings.as_dict()``, or the network's own: None). ``entropy_calibration``: the posterior
    calibration the features' entropy was computed with (recorded, and used by every estimate); None: not recorded.
    ``for_dice``: the registrations the Dice regression is fitted on, and whose range its input is clipped to
    (:func:`fit_on_records`: all but the self cases); None: all. The failure model and ``low``/``high``: all."""
    x = np.asarray([list(f) for f in features], dtype=np.float64)
    y = np.asarray(dice, dtype=np.float64)
    t = np.asarray(failures, dtype=np.float64)
    if x.ndim != 2 or len(x) < 2 or len(y) != len(x) or len(t) != len(x):
        raise ValueError(
            f"need >= 2 registrations with one Dice and one failure flag each; got {len(x)} feature "
            f"rows, {len(y)} Dice values, {len(t)} flags"
        )
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("features and Dice must be finite")
    ranked = np.ones(len(x), dtype=bool) if for_dice is None else np.asarray(for_dice, dtype=bool)
    if ranked.shape != (len(x),) or ranked.sum() < 2:
        raise ValueError(f"for_dice must flag >= 2 of the {len(x)} registrations; got {for_dice}")
    mean, scale = x.mean(0), x.std(0)
    scale[scale < 1e-8] = 1.0  # a constant feature carries nothing: keep it, with weight fitted to ~0
    z = np.hstack([(x - mean) / scale, np.ones((len(x), 1))])
    penalty = RIDGE * np.eye(z.shape[1])
    penalty[-1, -1] = 0.0  # no penalty on the intercept
    dice_w = np.linalg.solve(z[ranked].T @ z[ranked] + penalty, z[ranked].T @ y[ranked])
    fail_w = np.zeros(z.shape[1])
    for _ in range(NEWTON_STEPS):  # Newton's method on the penalised log-likelihood (convex)
        p = logistic(z @ fail_w)
        gradient = z.T @ (p - t) + penalty @ fail_w
        hessian = (z * (p * (1 - p))[:, None]).T @ z + penalty + 1e-9 * np.eye(z.shape[1])
        step = np.linalg.solve(hessian, gradient)
        fail_w -= step
        if np.abs(step).max() < 1e-8:
            break
    return QualityModel(
        list(QualityFeatures._fields),
        x.min(0).tolist(),
        x.max(0).tolist(),
        mean.tolist(),
        scale.tolist(),
        dice_w[:-1].tolist(),
        float(dice_w[-1]),
        fail_w[:-1].tolist(),
        float(fail_w[-1]),
        float(threshold),
        dice_range=[float(y[ranked].min()), float(y[ranked].max())],
        dice_low=[] if for_dice is None else x[ranked].min(0).tolist(),
        dice_high=[] if for_dice is None else x[ranked].max(0).tolist(),
        fitted_on=list(fitted_on),
        refinement=dict(refinement or {}),
        entropy_calibration={} if entropy_calibration is None else entropy_calibration_record(entropy_calibration),
    )


def fit_on_records(
    records: Sequence[Mapping[str, Any]], refinement: Mapping[str, Any] | None, calibration: Calibration
) -> QualityModel:
    """The quality model fitted on the training ``records``: their features, Dice and failures; ``refinement``: the
    bundle path's settings (``RefinementSettings.as_dict()``; recorded when it refines); ``calibration``: the one the
    records' entropy feature was computed with."""
    return fit_quality_model(
        record_features(records),
        [r["dice"] for r in records],
        [r["failed"] for r in records],
        fitted_on=sorted({r["moving"] for r in records}),
        refinement=refinement if refinement and refinement.get("num_iterations") else None,
        entropy_calibration=calibration,
        for_dice=[r["perturbation"] not in SELF_NAMES for r in records],
    )
