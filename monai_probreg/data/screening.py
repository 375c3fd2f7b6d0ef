"""Batch workflows that survive a bad scan: the damaged subject is reported, the others are processed.

Registration runs unattended over whole folders, so in ``inference.yaml`` and ``evaluate.yaml`` (not in training,
where a bad scan must stop the run before any step) one unreadable or invalid file must not end the batch:

- :class:`SkipBadInputs` is MONAI's ``Dataset`` whose items that fail the package's input checks
  (:class:`~monai_probreg.utils.errors.InputError`: truncated or corrupt file, header/data mismatch, NaN voxels,
  constant image, non-integer labels, ...) become a small marker ``{"id": ..., FAILED_KEY: "<one line>"}`` instead of
  an exception. Any other exception is a bug and still propagates. It works in DataLoader worker processes too: the
  marker travels through the batch.
- :class:`SkipFailedBatches` wraps the DataLoader for the engine: marker batches are recorded in an
  :class:`InputFailures` and never reach the network; it has no length, so ignite learns the epoch length from the
  batches that remain.
- :meth:`InputFailures.finish` (the configs' ``finalize``) writes ``failed.csv`` (id, reason) into the output folder,
  prints one line per failed subject and exits with status 1 when any subject failed, after the others were written.
  ``summary.json`` of ``evaluate.yaml`` lists them too (``failed``).
"""

from __future__ import annotations

import csv
import io
import logging
import os
from collections.abc import Iterable, Iterator, Sized
from pathlib import Path
from typing import Any

from monai.data import Dataset

from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import write_text

__all__ = [
    "FAILED_KEY",
    "FAILED_FILE",
    "InputFailures",
    "SkipBadInputs",
    "SkipFailedBatches",
    "input_error_in",
    "read_failures",
]

FAILED_KEY = "input_error"
FAILED_FILE = "failed.csv"
_LOG = logging.getLogger(__name__)


def input_error_in(error: BaseException) -> InputError | None:
    """The :class:`InputError` in ``error``'s cause/context chain (MONAI wraps transform errors), or None."""
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        if isinstance(current, InputError):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


class SkipBadInputs(Dataset):
    """``monai.data.Dataset`` whose items with bad input files become failure markers (module docstring).

    Args:
        data: the pair dicts (each with an ``id``), as for ``Dataset``.
        transform: the loading and preprocessing chain.
    """

    def _transform(self, index: int) -> Any:
        try:
            return super()._transform(index)
        except Exception as err:  # noqa: BLE001 - only InputError is turned into a marker; the rest re-raised
            found = input_error_in(err)
            if found is None:
                raise
            item = self.data[index]
            sid = item.get("id", str(index)) if isinstance(item, dict) else str(index)
            return {"id": str(sid), FAILED_KEY: str(found)}


class InputFailures:
    """The subjects a batch run could not process: ``(id, reason)`` in the order met."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str]] = []

    def add(self, subject_id: str, reason: str) -> None:
        self.items.append((str(subject_id), str(reason)))
        _LOG.error(f"{subject_id}: skipped: {reason}")

    def as_records(self) -> list[dict[str, str]]:
        return [{"id": sid, "reason": reason} for sid, reason in self.items]

    def finish(self, output_dir: str | os.PathLike, exit_on_failure: bool = True) -> None:
        """Write ``failed.csv`` into ``output_dir`` (none when nothing failed; an old one is removed), print the
        failures and, with ``exit_on_failure``, end the process with status 1 if any subject failed."""
        path = Path(output_dir) / FAILED_FILE
        if not self.items:
            path.unlink(missing_ok=True)
            return
        table = io.StringIO()
        writer = csv.writer(table, lineterminator="\n")
        writer.writerow(["id", "reason"])
        writer.writerows(self.items)
        write_text(path, table.getvalue())
        lines = [f"{len(self.items)} subject(s) failed and were skipped (reasons in {path}):"]
        lines += [f"  {sid}: {reason}" for sid, reason in self.items]
        print("\n".join(lines), flush=True)
        if exit_on_failure:
            self.exit_if_any()

    def exit_if_any(self) -> None:
        """End the process with status 1 if any subject failed (after everything else was written)."""
        if self.items:
            raise SystemExit(1)


class SkipFailedBatches:
    """Iterable over ``loader``'s batches without the failure markers, which go to ``failures``.

    Batches must hold one subject each, or only good ones: the configs use ``batch_size: 1``."""

    def __init__(self, loader: Iterable[dict], failures: InputFailures) -> None:
        self.loader, self.failures = loader, failures

    @property
    def num_batches(self) -> int | None:
        """Batches of the wrapped loader, failures included (for progress logs; deliberately not ``__len__``)."""
        return len(self.loader) if isinstance(self.loader, Sized) else None

    def __iter__(self) -> Iterator[dict]:
        for batch in self.loader:
            if isinstance(batch, dict) and FAILED_KEY in batch:
                for sid, reason in zip(batch["id"], batch[FAILED_KEY]):
                    self.failures.add(sid, reason)
                continue
            yield batch


def read_failures(path: str | os.PathLike) -> list[tuple[str, str]]:
    """The ``(id, reason)`` rows of a ``failed.csv`` written by :meth:`InputFailures.finish` (none if absent)."""
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="") as handle:
        return [(row["id"], row["reason"]) for row in csv.DictReader(handle)]
