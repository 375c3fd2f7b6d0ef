"""Ignite/MONAI engine pieces of the inference and evaluation bundle workflows (a thin layer on
:mod:`monai_probreg.engines.outputs`).

A ``SupervisedEvaluator`` with ``prepare_batch=monai_probreg.engines.training.prepare_registration_batch`` and
``decollate=False`` calls ``inferer(moving, network, fixed)`` -> :class:`RegistrationInferer` (timed
:func:`~monai_probreg.engines.registration.register_pair`); its handlers then see ``state.output`` =
``{"image": moving, "label": batch tensors, "pred": RegistrationOutput}`` and ``state.batch["id"]``:
:class:`RegistrationWriter` writes the NIfTI outputs, :class:`RegistrationScorer` scores each subject and
writes ``scores.csv`` / ``summary.json`` when the run completes.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from ignite.engine import Engine, Events
from monai.inferers import Inferer
from torch import Tensor

from monai_probreg.data.screening import InputFailures
from monai_probreg.engines.outputs import OUTPUT_NAMES, OUTPUTS_README, SAMPLED_NAMES, write_outputs
from monai_probreg.engines.quality_check import QualityCheck
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.engines.registration import timed_register_pair
from monai_probreg.engines.score_files import summary_table, write_scores
from monai_probreg.metrics.scores import PairScores, score_pair
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.uncertainty.calibration import check_calibration
from monai_probreg.uncertainty.error_model import check_error_model, pair_term
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.utils.files import write_text

__all__ = ["RegistrationInferer", "RegistrationWriter", "RegistrationScorer"]

_LOG = logging.getLogger(__name__)


class RegistrationInferer(Inferer):
    """Engine inferer: ``network(moving, fixed)`` through :func:`timed_register_pair`, its mean refined per pair when
    ``refinement`` is enabled (:mod:`monai_probreg.engines.refinement`); the wall time of the last call (the whole
    batch, refinement included) is kept in ``last_runtime_s`` for the handlers."""

    last_runtime_s: float = math.nan

    def __init__(self, refinement: RefinementSettings | None = None) -> None:
        super().__init__()
        self.refinement = refinement

    def __call__(self, inputs: Tensor, network: Callable, *args: Any, **kwargs: Any) -> RegistrationOutput:
        if len(args) != 1 or kwargs:
            raise ValueError(
                f"expected one extra argument, the fixed image; got {len(args)}, keywords {sorted(kwargs)}"
            )
        output, self.last_runtime_s = timed_register_pair(network, inputs, args[0], self.refinement)  # type: ignore[arg-type]
        return output


def _total(engine: Engine) -> int | str:
    """Subjects in this run for progress logs: ignite's epoch length, else the wrapped loader's batch count."""
    return engine.state.epoch_length or getattr(engine.state.dataloader, "num_batches", None) or "?"


class _PerSubjectHandler:
    """Ignite handler base: ``start``, then ``each(engine, sid, pair, targets, runtime)`` per batch item (pair and
    targets sliced to B = 1; runtime = the inferer's batch time / batch size), then ``done``."""

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.STARTED, self.start)
        engine.add_event_handler(Events.ITERATION_COMPLETED, self._iteration)
        engine.add_event_handler(Events.COMPLETED, self.done)

    def _iteration(self, engine: Engine) -> None:
        pred, targets = engine.state.output["pred"], engine.state.output["label"]  # type: ignore[index]
        ids, batch = engine.state.batch["id"], pred.displacement.shape[0]  # type: ignore[index]
        runtime = getattr(getattr(engine, "inferer", None), "last_runtime_s", math.nan) / batch
        for b, sid in enumerate(ids):
            pair = RegistrationOutput(*(t[b : b + 1] if t is not None else None for t in pred))
            with torch.inference_mode():
                self.each(engine, sid, pair, {k: v[b : b + 1] for k, v in targets.items()}, runtime)

    def each(self, engine: Engine, sid: str, pair: RegistrationOutput, targets: dict, runtime: float) -> None:
        raise NotImplementedError

    def start(self, engine: Engine) -> None:
        pass

    def done(self, engine: Engine) -> None:
        pass


class RegistrationWriter(_PerSubjectHandler):
    """Writes :func:`write_outputs` for every subject into ``output_dir``: the maps in ``names`` (default all of
    :data:`~monai_probreg.engines.outputs.OUTPUT_NAMES`; the label maps only when the batch has labels).

    With ``network`` given, the uncertainty maps are :func:`~monai_probreg.uncertainty.posterior_maps.posterior_maps` of the
    posterior calibrated by ``std_scale``, ``bias_fraction``, ``residual_weight``, ``error_model``, ``sample_gain`` and
    ``interval_dof`` (1, 0, 0, None, 1 and None = raw; :class:`~monai_probreg.uncertainty.calibration.Calibration`'s
    fields), the label entropy from ``num_samples`` seeded samples (``num_samples`` >= 2 is needed for
    :data:`~monai_probreg.engines.outputs.SAMPLED_NAMES`); without it, ``entropy`` is the raw posterior's.
    With ``quality``, each subject's quality estimate is written as ``<id>/quality.json`` (and a probable failure
    logged as a warning)."""

    def __init__(
        self,
        output_dir: str | os.PathLike,
        names: Sequence[str] = OUTPUT_NAMES,
        network: torch.nn.Module | None = None,
        num_samples: int = 0,
        std_scale: float = 1.0,
        seed: int = 0,
        bias_fraction: float = 0.0,
        quality: QualityCheck | None = None,
        residual_weight: float = 0.0,
        error_model: Sequence[float] | None = None,
        sample_gain: float = 1.0,
        interval_dof: float | None = None,
    ) -> None:
        unknown = set(names) - set(OUTPUT_NAMES)
        if unknown:
            raise ValueError(f"unknown output names {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")
        sampled = sorted(set(names) & set(SAMPLED_NAMES))
        if sampled and (network is None or num_samples < 2):
            raise ValueError(
                f"outputs {sampled} need the network and num_samples >= 2; got "
                f"{'no network' if network is None else f'num_samples {num_samples}'}"
            )
        self.output_dir, self.names = Path(output_dir), tuple(names)
        self.network, self.num_samples, self.std_scale, self.seed = network, int(num_samples), float(std_scale), seed
        self.bias_fraction, self.residual_weight = float(bias_fraction), float(residual_weight)
        check_calibration(self.std_scale, self.bias_fraction, interval_dof, self.residual_weight, float(sample_gain))
        self.sample_gain, self.interval_dof = float(sample_gain), interval_dof
        check_error_model(error_model)
        self.error_model = None if error_model is None else tuple(float(c) for c in error_model)
        self.quality = quality

    def start(self, engine: Engine) -> None:
        write_text(self.output_dir / "README.txt", OUTPUTS_README)

    def each(self, engine: Engine, sid: str, pair: RegistrationOutput, targets: dict, runtime: float) -> None:
        affine = targets["fixed"].affine
        affine = affine[0] if affine.ndim == 3 else affine
        maps = None
        if self.network is not None:
            sampled = set(self.names) & set(SAMPLED_NAMES)
            label = targets.get("moving_label") if "label_entropy" in self.names else None
            residual = None  # the map the calibration's term weighs (uncertainty.error_model.pair_term)
            if self.residual_weight > 0:
                residual = pair_term(
                    self.error_model,
                    pair.warped,
                    targets["fixed"],
                    pair.velocity_mean,
                    pair.velocity_log_var,
                    pair.displacement,
                )
            maps = posterior_maps(
                self.network,
                pair.velocity_mean,
                pair.velocity_log_var,
                pair.displacement.shape[2:],
                self.num_samples if sampled else 0,
                self.std_scale,
                label,
                self.seed,
                self.bias_fraction,
                residual=residual,
                residual_weight=self.residual_weight,
                sample_gain=self.sample_gain,
                interval_dof=self.interval_dof,
            )
        write_outputs(self.output_dir, sid, pair, affine, targets.get("moving_label"), self.names, maps)
        record = self.quality(sid, pair, targets) if self.quality is not None else None
        if record is not None:
            write_text(self.output_dir / sid / "quality.json", json.dumps(record, indent=2) + "\n")
        _LOG.info(f"[{engine.state.iteration}/{_total(engine)}] {sid}: {runtime:.2f} s -> {self.output_dir / sid}")


class RegistrationScorer(_PerSubjectHandler):
    """Scores every subject with :func:`score_pair` (and the identity), then :func:`write_scores` and prints
    the summary table. ``config`` is stored in summary.json; ``labels`` default to the atlas' non-zero ids;
    ``failures`` (subjects skipped for bad input) are listed in summary.json; with ``quality``, each subject's quality
    estimate goes into scores.csv and summary.json (and a probable failure is logged as a warning)."""

    def __init__(
        self,
        output_dir: str | os.PathLike,
        config: Mapping[str, Any] | None = None,
        labels: Sequence[int] | None = None,
        failures: InputFailures | None = None,
        quality: QualityCheck | None = None,
    ) -> None:
        self.output_dir, self.config, self.labels = Path(output_dir), dict(config or {}), labels
        self.failures, self.quality = failures, quality
        self.rows: list[tuple[str, PairScores, PairScores]] = []
        self.quality_records: dict[str, dict] = {}  # per subject: uncertainty.quality.quality_record

    def start(self, engine: Engine) -> None:
        self.rows, self.quality_records = [], {}

    def each(self, engine: Engine, sid: str, pair: RegistrationOutput, targets: dict, runtime: float) -> None:
        if "moving_label" not in targets:
            raise ValueError(f"subject {sid!r} has no labels loaded; scoring needs moving_label and fixed_label")
        reg = score_pair(pair.displacement, targets["moving_label"], targets["fixed_label"], runtime, self.labels)
        base = score_pair(None, targets["moving_label"], targets["fixed_label"], 0.0, self.labels)
        self.rows.append((sid, reg, base))
        record = self.quality(sid, pair, targets) if self.quality is not None else None
        if record is not None:
            self.quality_records[sid] = record
        _LOG.info(
            f"[{engine.state.iteration}/{_total(engine)}] {sid}: Dice {reg.mean_dice:.3f} "
            f"(no registration {base.mean_dice:.3f}), |J|<=0 {reg.num_folding}, {runtime:.2f} s"
        )

    def done(self, engine: Engine) -> None:
        failed = self.failures.items if self.failures is not None else []
        if not self.rows:
            _LOG.error(f"no subject could be scored ({len(failed)} failed); no scores written")
            return
        summary = write_scores(
            self.output_dir,
            self.rows,
            self.config,
            failed,
            self.quality_records if self.quality is not None and self.quality.enabled else None,
        )
        print(summary_table(summary) + f"\nper-subject scores: {self.output_dir / 'scores.csv'}", flush=True)
