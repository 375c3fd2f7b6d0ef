"""``monai-probreg register-batch``: many scans, one model and fixed image; one bad scan never stops the batch.

Each scan is registered by :func:`monai_probreg.registration.scan.register_scan` into ``out/<name>/`` (all or nothing),
with its own initial transform when a folder of them is given (:func:`initial_transform_for`). A scan
that fails for any reason (a missing, damaged or odd file: :mod:`monai_probreg.spatial.checks`; or an error while
registering) becomes a ``failed`` row with its one-line reason, and the next scan starts. ``out/batch_summary.csv``
is rewritten atomically after every scan, so an interrupted batch (Ctrl-C: the scans not reached are listed as
``not run``; or a hard kill) still has an up-to-date summary. Columns: :data:`BATCH_COLUMNS`.
"""

from __future__ import annotations

import csv
import io
import sys
import traceback
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.options import InitialTransform, RegistrationOptions
from monai_probreg.registration.scan import register_scan
from monai_probreg.spatial.transform_files import AFFINE_SUFFIXES
from monai_probreg.utils.errors import InputError, first_line
from monai_probreg.utils.files import write_text

__all__ = [
    "BATCH_COLUMNS",
    "BatchItem",
    "BatchRow",
    "error_text",
    "initial_transform_for",
    "write_batch_summary",
    "register_batch",
]

BATCH_COLUMNS = [
    "scan",
    "status",
    "mean_dice",
    "mean_dice_affine_only",
    "num_jacobian_nonpositive",
    "time_s",
    "error",
    "predicted_dice",
    "failure_probability",
    "warning",
]


class BatchItem(NamedTuple):
    name: str  # output folder out/<name>/ and the row's "scan"
    moving: Path
    moving_label: Path | None = None
    moving_mask: Path | None = None  # its cost-function mask (--moving-mask-dir), or None


class BatchRow(NamedTuple):
    """One line of batch_summary.csv; ``status`` is ``ok``, ``failed`` or ``not run``."""

    scan: str
    status: str
    mean_dice: float | None = None
    mean_dice_affine_only: float | None = None
    num_jacobian_nonpositive: int | None = None
    time_s: float | None = None
    error: str = ""
    predicted_dice: float | None = None  # the quality estimate (None: the weights have none)
    failure_probability: float | None = None
    warning: str = ""  # the quality estimate's warning: the scan registered ("ok") but probably failed


def error_text(err: BaseException) -> str:
    """One line: an InputError's own message (it names the file); otherwise the exception's type and first line."""
    if isinstance(err, InputError):
        return first_line(err, limit=None)
    first = first_line(err, limit=None)
    return type(err).__name__ if first == type(err).__name__ else f"{type(err).__name__}: {first}"


def write_batch_summary(path: str | Path, rows: Sequence[BatchRow]) -> Path:
    """Write ``batch_summary.csv`` (CSV quoting, floats to 4 decimals, empty = not available) atomically."""
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(BATCH_COLUMNS)
    for row in rows:
        writer.writerow(["" if v is None else f"{v:.4f}" if isinstance(v, float) else v for v in row])
    return write_text(path, table.getvalue())


PREVIOUS_AFFINE = "affine.tfm"  # what an earlier run wrote into each scan's folder


def initial_transform_for(folder: Path, name: str) -> Path:
    """The scan ``name``'s affine in ``folder``: ``name`` with an affine file's suffix, or ``name/affine.tfm`` (an
    earlier batch's output folder); InputError naming what was looked for when there is none, or several."""
    candidates = [folder / f"{name}{suffix}" for suffix in AFFINE_SUFFIXES] + [folder / name / PREVIOUS_AFFINE]
    found = [path for path in candidates if path.is_file()]
    if len(found) != 1:
        raise InputError(
            f"--initial-transform {str(folder)!r}: expected one transform for scan {name!r} "
            f"({', '.join(str(p.relative_to(folder)) for p in candidates)}), got "
            + (", ".join(repr(str(p.relative_to(folder))) for p in found) if found else "none")
        )
    return found[0]


def _register_one(
    model: LoadedModel,
    fixed: FixedSpace,
    item: BatchItem,
    out: Path,
    options: RegistrationOptions,
    overwrite: bool,
    report,
    initial_transforms: Path | None = None,
    initial_use: str | None = None,
) -> BatchRow:
    if not item.moving.is_file():  # one missing scan is that scan's failure, not the batch's
        raise InputError(f"--moving {str(item.moving)!r}: no such file")
    if initial_transforms is not None:  # read here: one scan's bad transform is that scan's failure
        path = initial_transform_for(initial_transforms, item.name)
        options = replace(options, initial=InitialTransform.read(path, initial_use))
    summary = register_scan(
        model,
        fixed,
        item.moving,
        out / item.name,
        item.moving_label,
        options,
        overwrite,
        report=report,
        moving_mask_path=item.moving_mask,
    )
    dice, quality = summary["dice"] or {}, summary.get("quality") or {}
    return BatchRow(
        item.name,
        "ok",
        dice.get("mean"),
        dice.get("mean_affine_only"),
        summary["jacobian"]["num_nonpositive"],
        summary["timings_s"]["total"],
        predicted_dice=quality.get("predicted_dice"),
        failure_probability=quality.get("failure_probability"),
        warning=summary.get("warning") or "",
    )


def register_batch(
    model: LoadedModel,
    fixed: FixedSpace,
    items: Sequence[BatchItem],
    out: str | Path,
    options: RegistrationOptions,
    overwrite: bool = False,
    quiet: bool = False,
    debug: bool = False,
    initial_transforms: Path | None = None,
    initial_use: str | None = None,
) -> list[BatchRow]:
    """Register every item; returns one row per item (failures included) and keeps out/batch_summary.csv current.
    ``debug`` prints each failure's traceback to stderr. Ctrl-C writes the summary (the rest ``not run``), re-raises.
    ``initial_transforms``: a folder of each scan's initial transform (:func:`initial_transform_for`), used as
    ``initial_use`` says (:class:`~monai_probreg.registration.options.InitialTransform`); one transform for every scan
    comes in ``options.initial`` instead."""
    from tqdm import tqdm

    out = Path(out)
    rows: list[BatchRow] = []
    bar = tqdm(items, desc="registering", unit="scan", disable=quiet, file=sys.stderr)
    try:
        for item in bar:
            bar.set_postfix_str(item.name)
            try:
                row = _register_one(
                    model,
                    fixed,
                    item,
                    out,
                    options,
                    overwrite,
                    report=lambda stage, s, n=item.name: bar.set_postfix_str(f"{n}: {stage} done"),
                    initial_transforms=initial_transforms,
                    initial_use=initial_use,
                )
            except Exception as err:  # noqa: BLE001 - one scan's failure must not stop the batch
                row = BatchRow(item.name, "failed", error=error_text(err))
                if debug:
                    traceback.print_exc()
            rows.append(row)
            write_batch_summary(out / "batch_summary.csv", rows)
    except KeyboardInterrupt:
        done = {row.scan for row in rows}
        rows += [BatchRow(item.name, "not run", error="interrupted") for item in items if item.name not in done]
        write_batch_summary(out / "batch_summary.csv", rows)
        raise
    finally:
        bar.close()
    return rows
