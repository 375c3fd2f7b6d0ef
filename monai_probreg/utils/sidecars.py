"""The JSON sidecars next to a weights file: where each lives, and the one way to read, verify and write one.

A sidecar (``models/model.calibration.json``, ``models/model.quality.json``) holds what was fitted for one weights
file (the calibration of its posterior, its quality model), stamped with that file's SHA-256: read with other weights
it would silently describe another model, so :func:`read_sidecar` refuses it. The fits that write them:
``python -m monai_probreg.fitting``. What each record holds is its own module's business
(:mod:`monai_probreg.uncertainty.calibration`, :mod:`monai_probreg.uncertainty.quality`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import file_sha256

__all__ = ["REFIT_COMMAND", "read_sidecar", "sidecar_path", "write_sidecar"]

REFIT_COMMAND = "python -m monai_probreg.fitting"  # what every refusal tells the user to run


def sidecar_path(weights_file: str | os.PathLike, kind: str) -> Path:
    """Where the ``kind`` sidecar of ``weights_file`` lives: ``models/model.pt`` -> ``models/model.<kind>.json``."""
    path = Path(weights_file)
    return path.with_name(f"{path.stem}.{kind}.json")


def read_sidecar(
    weights_file: str | os.PathLike, kind: str, what: str, instead: str = "", path: str | os.PathLike | None = None
) -> dict[str, Any]:
    """The record of ``weights_file``'s ``kind`` sidecar (or of ``path``) as a mapping, verified to be a JSON object
    fitted for exactly these weights (its ``weights_sha256``).

    ``what`` names the record in messages ("calibration record"); ``instead``: what the user may do besides refitting
    (appended to the mismatch message). Raises FileNotFoundError when there is none (callers decide whether that is
    an error), ValueError naming the file for an unreadable record or one fitted for other weights."""
    path = sidecar_path(weights_file, kind) if path is None else Path(path)
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a {what} ({err})") from None
    if not isinstance(record, dict):
        raise ValueError(f"{path}: not a {what} (expected a JSON object, got {type(record).__name__})")
    if not isinstance(record.get("weights_sha256"), str):
        raise ValueError(f"{path}: not a {what} (expected the weights' SHA-256, weights_sha256; it has none)")
    stamped, actual = record["weights_sha256"], file_sha256(weights_file)
    if stamped != actual:
        raise ValueError(
            f"{path} was fitted for weights with SHA-256 {stamped[:12]}..., but {weights_file} has {actual[:12]}...; "
            f"refit it ({REFIT_COMMAND}){instead}"
        )
    return record


def write_sidecar(
    weights_file: str | os.PathLike, kind: str, record: dict[str, Any], path: str | os.PathLike | None = None
) -> Path:
    """Write ``record`` as ``weights_file``'s ``kind`` sidecar (or at ``path``) atomically, stamped with the weights'
    name and SHA-256 (``weights_file``, ``weights_sha256``: the keys :func:`read_sidecar` checks)."""
    record = {**record, "weights_file": Path(weights_file).name, "weights_sha256": file_sha256(weights_file)}
    return write_text(sidecar_path(weights_file, kind) if path is None else path, json.dumps(record, indent=2) + "\n")
