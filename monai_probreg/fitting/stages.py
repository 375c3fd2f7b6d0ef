"""The two fits of ``python -m monai_probreg.fitting``, each resumable from its log, and the sidecars they write.

What a fit is fitted for is read from the bundle (:func:`bundle_setup`): the bundle's path (``configs/evaluate.yaml``
over ``inference.yaml``: ``network_def``, ``model_file``, ``preprocessing``, ``divisor``, ``refinement``) registers the
population probe and the quality model's bundle-path cases; the command line's (``configs/inference.yaml``: its
network and ``refinement``) the subject probe and the whole-command cases; ``configs/train.yaml``'s ``val_ids`` are the
validation subjects, every other subject of the dataset trains. :func:`bundle_parser` reads the configs, an overlay
(evaluate.yaml) always on top of its base (:data:`OVERLAY_BASES`), as the documented command lines do.

:func:`fit_calibration_stage` registers both calibration probes and fits the calibration on all their cases; its
result is logged (``calibration.json`` in the work folder), so a run stopped later does not fit it again.
:func:`fit_quality_stage` registers the quality model's training cases (each logged as it ends, ``quality.json``) and
fits the model, its entropy feature computed with the calibration given. :func:`write_sidecars` writes both only when
both are fitted, each atomically. Every log carries the settings its records were made under; ``resume`` reuses a
log only when they are the same.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from monai.bundle import ConfigParser
from torch import nn

from monai_probreg.data.dataset import DatasetIndex
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.calibration_probes import FIT_ITERATIONS, ProbeSettings, calibration_probes
from monai_probreg.fitting.error_cases import ERROR_MODEL_SEED, ERROR_MODEL_TEMPLATES, fitted_error_model
from monai_probreg.fitting.quality_cases import RecordLog, load_scans
from monai_probreg.fitting.quality_fit import CommandSetup, fit_on_records, split_records
from monai_probreg.registration.model import load_model
from monai_probreg.uncertainty.calibration import Calibration, calibration_path, save_calibration
from monai_probreg.uncertainty.quality import QualityModel, entropy_calibration_record, quality_path, save_quality_model
from monai_probreg.utils.errors import InputError, first_line
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.weights.loading import load_weights

__all__ = [
    "CONFIGS",
    "OVERLAY_BASES",
    "CALIBRATION_LOG",
    "QUALITY_LOG",
    "config_files",
    "bundle_parser",
    "BundleSetup",
    "bundle_setup",
    "FittedCalibration",
    "fit_calibration_stage",
    "fit_quality_stage",
    "write_sidecars",
]

_LOG = logging.getLogger(__name__)
CONFIGS = ("evaluate.yaml", "inference.yaml", "train.yaml")  # the configs a fit reads
# overlay -> its base: the overlay holds only what differs, so it is read after its base, never alone (the base is the
# one home of the defaults both use); the documented command lines pass both, base first
OVERLAY_BASES = {"evaluate.yaml": "inference.yaml"}
CALIBRATION_LOG, QUALITY_LOG = "calibration.json", "quality.json"  # in the work folder
_FITTED = "fitted"  # the calibration log's one record


def config_files(bundle_root: Path, names: Sequence[str]) -> list[Path]:
    """``bundle_root/configs/<names>`` in the order ``monai.bundle run --config_file "[...]"`` must read them: each
    overlay after its base (:data:`OVERLAY_BASES`, recursively), each file once, at its first place. The list to hand
    to MONAI (``ConfigParser.read_config``, ``ConfigWorkflow(config_file=...)``) wherever a config may be an overlay."""
    ordered: list[str] = []
    for name in names:
        chain = [name]
        while chain[0] in OVERLAY_BASES:
            chain.insert(0, OVERLAY_BASES[chain[0]])
        ordered += [n for n in chain if n not in ordered]
    return [Path(bundle_root) / "configs" / n for n in ordered]


def bundle_parser(bundle_root: Path, names: Sequence[str], overrides: dict[str, Any] | None = None) -> ConfigParser:
    """A ``monai.bundle.ConfigParser`` over ``bundle_root/configs/<names>`` merged in order, each overlay read on top
    of its base (:func:`config_files`: ``["evaluate.yaml"]`` reads inference.yaml, then evaluate.yaml), with
    ``bundle_root`` set to ``bundle_root`` and each ``overrides`` key set after reading, as ``monai.bundle run --key
    value`` does. The one way the package, the benchmarks and the tests read the bundle's configs."""
    parser = ConfigParser()
    parser.read_config([str(f) for f in config_files(bundle_root, names)])
    parser["bundle_root"] = str(bundle_root)
    for key, value in (overrides or {}).items():
        parser[key] = value
    return parser


class BundleSetup(NamedTuple):
    """``evaluate``: evaluate.yaml's parser (its ``dataset_dir`` set); ``network``: its network with ``model_file``'s
    weights on the CPU; ``refinement``: evaluate.yaml's (the bundle path's), ``command_refinement``: inference.yaml's
    (the command line's); ``val_ids``: train.yaml's; ``divisor``: evaluate.yaml's padding multiple."""

    evaluate: ConfigParser
    model_file: Path
    network: nn.Module
    refinement: RefinementSettings
    command_refinement: RefinementSettings
    val_ids: list[str]
    divisor: int


def bundle_setup(bundle_root: Path, dataset_dir: Path, model_file: Path | None = None) -> BundleSetup:
    """Read the bundle at ``bundle_root`` for ``dataset_dir``, with ``model_file``'s weights (default: evaluate.yaml's
    ``model_file``). InputError naming the file when a config is missing or unusable or the weights do not load."""
    bundle_root = Path(bundle_root).resolve()
    for name in CONFIGS:
        if not (bundle_root / "configs" / name).is_file():
            raise InputError(
                f"--bundle-root {str(bundle_root)!r}: expected a bundle with configs/{name}, got no such file"
            )
    try:
        evaluate = bundle_parser(bundle_root, ["evaluate.yaml"], {"dataset_dir": str(Path(dataset_dir).resolve())})
        model_file = Path(model_file or evaluate.get_parsed_content("model_file")).resolve()
        refinement = evaluate.get_parsed_content("refinement")
        command_refinement = bundle_parser(bundle_root, ["inference.yaml"]).get_parsed_content("refinement")
        val_ids = [str(i) for i in bundle_parser(bundle_root, ["train.yaml"]).get_parsed_content("val_ids")]
        divisor = int(evaluate.get_parsed_content("divisor"))
        network_def = evaluate.get_parsed_content("network_def", lazy=False)
    except Exception as err:  # noqa: BLE001 - any config error becomes one line
        raise InputError(
            f"--bundle-root {str(bundle_root)!r}: expected usable configs, got {first_line(err)}"
        ) from None
    if not model_file.is_file():
        raise InputError(f"--model-file {str(model_file)!r}: expected a weights file, got no such file")
    try:
        network = load_weights(network_def, model_file, "cpu")
    except InputError as err:  # untrusted (a pickle that could run code), truncated or corrupt: its own message
        raise InputError(str(err).replace("model file", "--model-file", 1)) from None
    except (RuntimeError, KeyError, ValueError) as err:
        raise InputError(
            f"--model-file {str(model_file)!r}: expected weights of evaluate.yaml's network, got {first_line(err)}"
        ) from None
    return BundleSetup(evaluate, model_file, network, refinement, command_refinement, val_ids, divisor)


def _calibration(stored: dict[str, Any]) -> Calibration:
    """A calibration as the log stores it (``Calibration._asdict()`` through JSON: the error model a list)."""
    error_model = stored.get("error_model")
    return Calibration(**{**stored, "error_model": None if error_model is None else tuple(error_model)})


class FittedCalibration(NamedTuple):
    """The fitted calibration, the cases it was fitted on (the sidecar's ``fitted_on``) and their posterior samples."""

    calibration: Calibration
    fitted_on: list[str]
    samples: int


def fit_calibration_stage(
    setup: BundleSetup,
    index: DatasetIndex,
    subjects: Sequence[str],
    bundle_root: Path,
    work_dir: Path,
    settings: ProbeSettings,
    resume: bool = False,
    error_model_templates: int = ERROR_MODEL_TEMPLATES,
) -> FittedCalibration:
    """The calibration of ``setup``'s network and refinement, fitted on the cases ``settings`` asks for: the
    population probe of ``subjects`` and the subject probe of the first training subjects
    (:func:`~monai_probreg.fitting.calibration_probes.calibration_probes`), with the error model fitted first on the
    ``error_model_templates`` training subjects after those (:mod:`~monai_probreg.fitting.error_cases`; none: the term
    reads the residual); taken from the log when ``resume`` finds one of the same settings."""
    header = {
        "weights_sha256": file_sha256(setup.model_file),
        "refinement": setup.refinement.as_dict(),
        "command_refinement": setup.command_refinement.as_dict(),  # the subject probe's network is inference.yaml's
        "subjects": list(subjects),
        "training_subjects": [i for i in index.ids if i not in subjects],
        **settings._asdict(),
        "fit_iterations": FIT_ITERATIONS,
        "error_model_templates": error_model_templates,
        "error_model_seed": ERROR_MODEL_SEED,
        "displacement_std": "first order",  # a log of a fit on the sampled std is not resumed
    }
    log = RecordLog(work_dir / CALIBRATION_LOG, header, resume=resume)
    if _FITTED in log.records:
        stored = log.records[_FITTED]
        _LOG.info(f"resumed: the calibration fitted before, from {log.path}")
        return FittedCalibration(_calibration(stored["calibration"]), stored["fitted_on"], settings.samples)
    _LOG.info(
        f"calibration: registering the probes of the {'refined' if setup.refinement.enabled else 'network'} mean "
        f"({setup.refinement.num_iterations} refinement steps)"
    )
    # the error model first, on training scans after the subject probe's: the probes' cases are then registered with
    # the term it gives (fitting.error_cases); with too few training scans the term reads the pair's residual
    training = [i for i in index.ids if i not in subjects]
    templates = training[settings.subject_probe : settings.subject_probe + error_model_templates]
    error_model = None
    if templates:
        command_model = load_model(bundle_root, setup.model_file, calibrate=False, quality=False)
        error_model = fitted_error_model(command_model, index, templates, setup.refinement)
        _LOG.info(f"error model fitted on the synthetic subjects of {', '.join(templates)}")
    probes = calibration_probes(
        setup.network,
        setup.evaluate.get_parsed_content("preprocessing"),
        index,
        subjects,
        bundle_root,
        setup.model_file,
        setup.refinement,
        settings,
        error_model,
    )
    fitted = FittedCalibration(
        probes.fit(list(probes.cases), list(probes.subject_cases)), probes.fitted_on(), settings.samples
    )
    log.records[_FITTED] = {"calibration": fitted.calibration._asdict(), "fitted_on": fitted.fitted_on}
    log.save()
    return fitted


def fit_quality_stage(
    setup: BundleSetup,
    calibration: Calibration,
    train_ids: Sequence[str],
    command: CommandSetup,
    work_dir: Path,
    *,
    seed: int,
    resume: bool,
) -> QualityModel:
    """The quality model of ``setup``'s network and refinement, fitted on the training cases of ``train_ids`` (the
    bundle path's and, but ``command.exclude``, the whole command's), the entropy feature under ``calibration``; each
    registration taken from the log when ``resume`` finds one of the same settings."""
    header = {
        "weights_sha256": file_sha256(setup.model_file),
        "refinement": setup.refinement.as_dict(),
        "entropy_calibration": entropy_calibration_record(calibration),
        "train_ids": list(train_ids),
        "seed": seed,
        "command_refinement": setup.command_refinement.as_dict(),
        "command_exclude": sorted(command.exclude),
    }
    log = RecordLog(work_dir / QUALITY_LOG, header, resume=resume)
    if log.reused:
        _LOG.info(f"resumed: {log.reused} registrations from {log.path}")
    scans = load_scans(command.dataset_dir, list(train_ids), setup.divisor)
    records = split_records("train", train_ids, seed, setup.network, calibration, scans, setup.refinement, log, command)
    return fit_on_records(records, setup.refinement.as_dict(), calibration)


def write_sidecars(
    model_file: Path, out_dir: Path, calibration: FittedCalibration | None, quality: QualityModel | None, refinement
) -> list[Path]:
    """Write the fitted sidecars of ``model_file`` into ``out_dir`` (each atomically: a temporary file renamed into
    place), named as :func:`~monai_probreg.uncertainty.calibration.calibration_path` and
    :func:`~monai_probreg.uncertainty.quality.quality_path` name them; ``refinement``: the bundle path's settings the
    calibration was fitted for. Returns the paths written."""
    written = []
    if calibration is not None:
        path = out_dir / calibration_path(model_file).name
        fitted = calibration.calibration
        save_calibration(
            model_file,
            fitted.std_scale,
            calibration.fitted_on,
            calibration.samples,
            bias_fraction=fitted.bias_fraction,
            refinement=refinement.as_dict() if refinement.enabled else None,
            interval_dof=fitted.interval_dof,
            path=path,
            residual_weight=fitted.residual_weight,
            error_model=fitted.error_model,
            sample_gain=fitted.sample_gain,
        )
        written.append(path)
    if quality is not None:
        written.append(save_quality_model(quality, model_file, out_dir / quality_path(model_file).name))
    return written
