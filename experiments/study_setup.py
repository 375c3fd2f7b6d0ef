"""What the calibration studies here share: their command line and their start.

Each study scores something on LPBA40's calibration cases with the bundle's network: :func:`study_parser` gives the
arguments every one takes (the dataset, the bundle, the threads, where the record goes), :func:`study_start` skips a
study cleanly without the dataset, sets the threads and reads the bundle and the dataset once,
:func:`population_probe_cases` and :func:`subject_probe_cases` give the calibration's two probes' cases, and
:func:`finish_study` writes the record. Not a package: the
studies import it as they import each other (``from study_setup import ...``: the script's folder, or pytest's
``pythonpath``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from common import write_report

from monai_probreg.data.dataset import DatasetIndex, index_dataset
from monai_probreg.fitting.calibration_probes import (
    SUBJECT_PROBE_TEMPLATES,
    CalibrationProbes,
    ProbeSettings,
    calibration_probes,
)
from monai_probreg.fitting.population_probe import VOXELS_PER_CASE
from monai_probreg.fitting.stages import BundleSetup, bundle_setup
from monai_probreg.fitting.subject_probe import SUBJECT_SEED, SubjectCase, subject_case

REPO = Path(__file__).resolve().parents[1]


def study_parser(doc: str, results: Path) -> argparse.ArgumentParser:
    """A study's parser (its description: the first line of ``doc``) with the arguments every study takes:
    ``--dataset-dir`` (LPBA40 beside the repository), ``--bundle-root``, ``--threads`` and ``--out-dir``
    (``results``); a study adds its own."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--dataset-dir", type=Path, default=REPO.parent / "shared" / "data" / "lpba40")
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out-dir", type=Path, default=results)
    return ap


class StudyStart(NamedTuple):
    """The bundle read for the dataset, the dataset's index and the study's start (``time.perf_counter()``)."""

    setup: BundleSetup
    index: DatasetIndex
    start: float


def study_start(args: argparse.Namespace) -> StudyStart | None:
    """None (after printing why) without the dataset at ``args.dataset_dir``; else the threads set and the bundle and
    the dataset read."""
    if not (args.dataset_dir / "images").is_dir():
        print(f"skipped: no dataset at {args.dataset_dir}")
        return None
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    return StudyStart(bundle_setup(args.bundle_root, args.dataset_dir), index_dataset(args.dataset_dir), start)


def population_probe_cases(
    args: argparse.Namespace, started: StudyStart, error_model: Sequence[float] | None = None
) -> tuple[CalibrationProbes, list[dict]]:
    """The calibration's population probe alone (its validation subjects, one deformation each, the fit's seeds;
    ``error_model``: the term's, None: the residual) registered, and its cases in one list."""
    setup = started.setup
    probes = calibration_probes(
        setup.network,
        setup.evaluate.get_parsed_content("preprocessing"),
        started.index,
        setup.val_ids,
        args.bundle_root,
        setup.model_file,
        setup.refinement,
        ProbeSettings(subject_probe=0),
        error_model,
    )
    return probes, [c for s in probes.cases for c in probes.cases[s]]


def subject_probe_cases(started: StudyStart, divisor: int) -> tuple[list[str], list[SubjectCase]]:
    """The calibration's subject probe: its templates (the first training subjects) and their synthetic subjects,
    drawn with the fit's seeds."""
    index, setup = started.index, started.setup
    templates = [i for i in index.ids if i not in setup.val_ids][:SUBJECT_PROBE_TEMPLATES]
    cases = [
        subject_case(t, index.images[t], SUBJECT_SEED + n, VOXELS_PER_CASE, divisor) for n, t in enumerate(templates)
    ]
    return templates, cases


def finish_study(args: argparse.Namespace, name: str, started: StudyStart, result: dict, lines: list[str]) -> int:
    """Write the study's record ``<out-dir>/<name>.json`` and print its table (``lines``), with the threads and the
    wall time added to ``result``; 0, the script's exit status."""
    wall = round(time.perf_counter() - started.start, 1)
    write_report(args.out_dir, name, {**result, "threads": args.threads, "wall_s": wall}, lines)
    return 0
