"""What the calibration studies here share: their command line and their start.

Each study scores something on LPBA40's calibration cases with the bundle's network: :func:`study_parser` gives the
arguments every one takes (the dataset, the bundle, the threads, where the record goes), :func:`study_start` skips a
study cleanly without the dataset, sets the threads and reads the bundle and the dataset once. Not a package: the
studies import it as they import each other (``from study_setup import ...``: the script's folder, or pytest's
``pythonpath``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import NamedTuple

import torch

from monai_probreg.data.dataset import DatasetIndex, index_dataset
from monai_probreg.fitting.stages import BundleSetup, bundle_setup

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
