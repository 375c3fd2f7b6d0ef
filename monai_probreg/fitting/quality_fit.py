"""The quality model's fit: the registrations of one split of subjects, and the fit on the training split's records.

The training split is what the shipped model is fitted on (``python -m monai_probreg.fitting``); the validation
split, made the same way, is what ``benchmarks/failure_detection.py`` scores it on. A split's records
(:func:`split_records`) are its bundle-path cases (:mod:`~monai_probreg.fitting.quality_cases`: each subject to the
atlas and to other subjects, and perturbed by the failure set) and, unless left out, its whole-command cases
(:mod:`~monai_probreg.fitting.command_cases`), each taken from the log when it holds it. :func:`fit_on_records` fits
:class:`~monai_probreg.uncertainty.quality.QualityModel` on the training split's records.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from torch import nn

from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.command_cases import command_cases
from monai_probreg.fitting.quality_cases import NORMAL, RecordLog, cases_for, logged_cases, record_features, run_case
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.quality import QualityModel, fit_quality_model

__all__ = [
    "VALIDATION_SEED_OFFSET",
    "CommandSetup",
    "identity_dice",
    "split_records",
    "with_command_cases",
    "fit_on_records",
]

VALIDATION_SEED_OFFSET = 100_000  # the validation split's cases are seeded from seed + this (the training's from seed)


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
    cases = cases_for(list(ids), seed, training=split == "train")
    records = logged_cases(split, cases, lambda case: run_case(network, calibration, scans, case, refinement), log)
    return records if command is None else with_command_cases(records, seed, command, calibration, log)


def with_command_cases(
    records: list[dict], seed: int, command: CommandSetup, calibration: Calibration, log: RecordLog | None = None
) -> list[dict]:
    """``records`` and the whole-command cases of their subjects but ``command.exclude``
    (:func:`~monai_probreg.fitting.command_cases.command_cases`, seeded with ``seed``, the entropy feature under
    ``calibration``; their "no registration" Dice from ``records``)."""
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
    )
