"""Refit the calibration and the quality model of the bundle's network and refinement, and write both sidecars.

    python -m monai_probreg.fitting --dataset-dir ../shared/data/lpba40 --threads 2

reads the bundle (``evaluate.yaml``: network, weights, preprocessing and the refinement of the bundle path;
``inference.yaml``: the command line's; ``train.yaml``: the validation subjects), then

1. the calibration (about 20 min on 2 threads for LPBA40): the population probe of the validation subjects and the
   subject probe of the first training subjects, registered and fitted together
   (:mod:`monai_probreg.fitting.calibration_probes`);
2. the quality model (about 2 h): the training subjects' registrations, normal, perturbed by the failure set, onto
   themselves and near copies of themselves, and through the whole command, fitted with the entropy feature under
   the calibration of step 1 (:mod:`monai_probreg.fitting.quality_fit`);

and writes ``<weights stem>.calibration.json`` and ``<weights stem>.quality.json`` next to the weights (``--out-dir``:
elsewhere), each atomically and only once both are fitted: a run stopped part-way leaves the sidecars as they were.
The defaults are the settings of the shipped sidecars. Each step logs what it has done in the work folder
(``--work-dir``, removed once the sidecars are written); ``--resume`` goes on from there. ``--only`` refits one of
the two (``--only quality`` computes the entropy feature with the calibration sidecar of the weights). How far to
trust what it fits is measured by ``benchmarks/uncertainty_calibration.py`` and ``benchmarks/failure_detection.py``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import torch
from tqdm.contrib.logging import logging_redirect_tqdm

from monai_probreg.data.dataset import index_dataset
from monai_probreg.fitting.calibration_probes import SUBJECT_PROBE_TEMPLATES, ProbeSettings
from monai_probreg.fitting.error_cases import ERROR_MODEL_TEMPLATES
from monai_probreg.fitting.population_probe import SEED_STRIDE
from monai_probreg.fitting.quality_fit import CommandSetup
from monai_probreg.fitting.stages import (
    CALIBRATION_LOG,
    QUALITY_LOG,
    bundle_setup,
    fit_calibration_stage,
    fit_quality_stage,
    write_sidecars,
)
from monai_probreg.registration.model import default_bundle_root
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES, calibration_for
from monai_probreg.utils.errors import InputError, first_line

__all__ = ["PROG", "build_parser", "main"]

PROG = "python -m monai_probreg.fitting"
_LOG = logging.getLogger("monai_probreg.fitting")
DEFAULT_DEFORMATIONS = 1  # population-probe deformations per validation subject (the shipped calibration's)
DEFAULT_TRAIN_SUBJECTS = 12  # training subjects of the quality model (the shipped model's: S12 ... S26)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, required=True, help="the dataset (atlas/, images/, labels/)")
    ap.add_argument("--bundle-root", type=Path, default=None, help="the bundle (default: the installed one)")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument("--out-dir", type=Path, default=None, help="where the sidecars go (default: next to the weights)")
    ap.add_argument(
        "--work-dir", type=Path, default=None, help="the logs of --resume (default: OUT_DIR/<stem>.fitting)"
    )
    ap.add_argument("--resume", action="store_true", help="go on from the logs of a run stopped part-way")
    ap.add_argument("--only", choices=["calibration", "quality"], default=None, help="refit one sidecar only")
    ap.add_argument("--subjects", nargs="+", default=None, help="validation subjects (default: train.yaml's val_ids)")
    ap.add_argument("--train-subjects", type=int, default=DEFAULT_TRAIN_SUBJECTS, help="quality model: the first N")
    ap.add_argument("--deformations", type=int, default=DEFAULT_DEFORMATIONS, help="population probe: per subject")
    ap.add_argument("--samples", type=int, default=POSTERIOR_SAMPLES, help="posterior samples of the calibration")
    ap.add_argument("--subject-probe", type=int, default=SUBJECT_PROBE_TEMPLATES, help="templates of the subject probe")
    ap.add_argument("--error-model-templates", type=int, default=ERROR_MODEL_TEMPLATES, help="training scans after the "
                    "subject probe's that the error model is fitted on (0: none, the term reads the residual)")  # fmt: skip
    ap.add_argument("--native-dir", type=Path, default=None, help="subjects with a scan here are left out of the "
                    "whole-command cases (default: <dataset-dir>-native, when there)")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    return ap


def _check(args: argparse.Namespace) -> None:
    """InputError (expected ..., got ...) for the first argument that cannot be used."""
    counts = [
        ("--deformations", args.deformations, 1, SEED_STRIDE),  # more would reuse the next subject's seeds
        ("--samples", args.samples, 2, None),
        ("--subject-probe", args.subject_probe, 0, None),
        ("--error-model-templates", args.error_model_templates, 0, None),
        ("--train-subjects", args.train_subjects, 1, None),
        ("--threads", args.threads, 1, None),
    ]
    for option, value, low, high in counts:
        if value < low or (high is not None and value > high):
            expected = f"{low} to {high}" if high is not None else f">= {low}"
            raise InputError(f"{option}: expected {expected}, got {value}")
    if not args.dataset_dir.is_dir():
        raise InputError(f"--dataset-dir {str(args.dataset_dir)!r}: expected a dataset folder, got no such folder")
    if args.native_dir is not None and not args.native_dir.is_dir():
        raise InputError(f"--native-dir {str(args.native_dir)!r}: expected a folder of scans, got no such folder")
    for option in ("out_dir", "work_dir"):
        path = getattr(args, option)
        if path is not None and path.exists() and not path.is_dir():
            raise InputError(f"--{option.replace('_', '-')} {str(path)!r}: expected a folder, got a file")


def _native_ids(dataset_dir: Path, native_dir: Path | None) -> frozenset[str]:
    """The subjects with a native scan (``native_dir``, or ``<dataset_dir>-native`` when there)."""
    folder = native_dir if native_dir is not None else dataset_dir.parent / f"{dataset_dir.name}-native"
    return frozenset(p.name.split(".")[0] for p in folder.glob("*.nii.gz")) if folder.is_dir() else frozenset()


def run(args: argparse.Namespace) -> list[Path]:
    """The fit ``args`` asks for; returns the sidecars written."""
    _check(args)
    bundle_root = (args.bundle_root or default_bundle_root()).resolve()
    setup = bundle_setup(bundle_root, args.dataset_dir, args.model_file)
    try:
        index = index_dataset(args.dataset_dir)
    except (OSError, ValueError) as err:
        raise InputError(
            f"--dataset-dir {str(args.dataset_dir)!r}: expected a dataset, got {first_line(err)}"
        ) from None
    subjects = args.subjects or setup.val_ids
    unknown = [s for s in subjects if s not in index.labels]
    if unknown:
        where = "--subjects" if args.subjects is not None else "train.yaml's val_ids (pass --subjects)"
        raise InputError(
            f"{where}: expected labelled subjects of {str(args.dataset_dir)!r}, got {unknown}, not there or unlabelled"
        )
    train_ids = [i for i in index.ids if i not in subjects][: args.train_subjects]
    if not train_ids:
        raise InputError(
            f"--dataset-dir {str(args.dataset_dir)!r}: expected training subjects besides {subjects}, got none"
        )
    out_dir = (args.out_dir or setup.model_file.parent).resolve()
    work_dir = (args.work_dir or out_dir / f"{setup.model_file.stem}.fitting").resolve()
    _LOG.info(f"fitting for {setup.model_file}; logs in {work_dir} ({'resumed' if args.resume else 'new'})")
    differ = setup.refinement.differences(setup.command_refinement.as_dict())
    if differ:  # the bundle path's cases follow evaluate.yaml, the whole-command ones inference.yaml
        _LOG.warning(
            "evaluate.yaml's and inference.yaml's refinement differ; the sidecars record evaluate.yaml's "
            f"(name: [inference.yaml, evaluate.yaml]): {differ}"
        )
    torch.set_num_threads(args.threads)
    calibration = None
    if args.only != "quality":
        settings = ProbeSettings(args.deformations, args.samples, args.seed, args.subject_probe)
        calibration = fit_calibration_stage(
            setup, index, subjects, bundle_root, work_dir, settings, args.resume, args.error_model_templates
        )
        fitted = calibration.calibration
        _LOG.info(
            f"calibration: std_scale {fitted.std_scale:.3f}, bias_fraction {fitted.bias_fraction:.3f}, interval dof "
            f"{fitted.interval_dof} (fitted on {len(calibration.fitted_on)} cases)"
        )
    quality = None
    if args.only != "calibration":
        try:
            in_use = calibration.calibration if calibration is not None else calibration_for(setup.model_file)
        except ValueError as err:  # a stale or corrupt sidecar
            raise InputError(f"--only quality: {err}; refit the calibration too (leave out --only)") from None
        native = _native_ids(args.dataset_dir, args.native_dir)
        command = CommandSetup(args.dataset_dir, bundle_root, setup.model_file, None, native)
        quality = fit_quality_stage(setup, in_use, train_ids, command, work_dir, seed=args.seed, resume=args.resume)
    written = write_sidecars(setup.model_file, out_dir, calibration, quality, setup.refinement)
    for name in (CALIBRATION_LOG, QUALITY_LOG):  # the sidecars are whole: the logs have done their part
        (work_dir / name).unlink(missing_ok=True)
    if work_dir.is_dir() and not any(work_dir.iterdir()):
        work_dir.rmdir()
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (1 with one line on stderr for an input that cannot be used)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        with logging_redirect_tqdm():
            written = run(args)
    except InputError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; the sidecars are as they were (--resume goes on from the logs)", file=sys.stderr)
        return 130
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
