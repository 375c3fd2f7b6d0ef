"""Score files of the bundle's evaluation: ``scores.csv``, ``summary.json``, ``scores.json`` (read back
to merge sharded runs) and the printed summary table."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from monai_probreg.metrics.scores import PairScores
from monai_probreg.utils.files import write_text

__all__ = ["write_scores", "read_scores", "summary_table"]


def _mean_std(values: Sequence[float]) -> dict[str, float | None]:
    arr = np.asarray([v for v in values if not math.isnan(v)], dtype=np.float64)
    return {"mean": float(arr.mean()), "std": float(arr.std())} if arr.size else {"mean": None, "std": None}


def _jsonable(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    return value if isinstance(value, (bool, int, float, str, type(None))) else str(value)


def _label_mean(scores: Sequence[PairScores], label: int) -> float | None:
    return _mean_std([s.dice.get(label, math.nan) for s in scores])["mean"]


def write_scores(
    output_dir: str | os.PathLike,
    rows: Sequence[tuple[str, PairScores, PairScores]],
    config: Mapping[str, Any] | None = None,
    failed: Sequence[tuple[str, str]] = (),
    quality: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """Write ``scores.csv`` (one row per subject), ``summary.json`` (mean and population std over subjects,
    registered and no-registration, per-label means, ``config``) and ``scores.json`` (every score of every subject,
    :func:`read_scores` reads it back: how sharded runs are merged) into ``output_dir``; return the summary.
    ``failed``: ``(id, reason)`` of the subjects skipped for bad input (:mod:`monai_probreg.data.screening`), listed in
    summary.json. ``quality``: per subject id, its quality estimate (``predicted_dice``, ``failure_probability``,
    ``warning``; :mod:`monai_probreg.engines.quality_check`): three more columns in scores.csv, the warnings in
    summary.json, the whole record in scores.json."""
    if not rows:
        raise ValueError("no scored subjects to summarise")
    labels = sorted({lab for _, reg, _ in rows for lab in reg.dice})
    fields = ["mean_dice", "num_folding", "percent_folding", "std_log_jacobian", "runtime_s"]
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    quality_fields = ["predicted_dice", "failure_probability", "warning"] if quality is not None else []
    writer.writerow(["id", *fields, "mean_dice_no_registration", *quality_fields, *(f"dice_{lab}" for lab in labels)])
    for sid, reg, base in rows:
        estimate = (quality or {}).get(sid, {})
        writer.writerow(
            [
                sid,
                *(getattr(reg, f) for f in fields),
                base.mean_dice,
                *(("" if estimate.get(f) is None else estimate[f]) for f in quality_fields),
                *(reg.dice.get(lab, "") for lab in labels),
            ]
        )
    summary = {
        "num_subjects": len(rows),
        "registered": {f: _mean_std([float(getattr(reg, f)) for _, reg, _ in rows]) for f in fields},
        "no_registration": {"mean_dice": _mean_std([base.mean_dice for _, _, base in rows])},
        "dice_per_label": {
            str(lab): {
                "registered": _label_mean([reg for _, reg, _ in rows], lab),
                "no_registration": _label_mean([base for _, _, base in rows], lab),
            }
            for lab in labels
        },
        "num_failed": len(failed),
        "failed": [{"id": sid, "reason": reason} for sid, reason in failed],
        "config": {k: _jsonable(v) for k, v in (config or {}).items()},
    }
    if quality is not None:
        warned = [
            {"id": sid, "warning": quality[sid]["warning"]}
            for sid, _, _ in rows
            if sid in quality and quality[sid].get("warning")
        ]
        summary["quality"] = {
            "predicted_dice": _mean_std(
                [
                    math.nan if quality[sid].get("predicted_dice") is None else float(quality[sid]["predicted_dice"])
                    for sid, _, _ in rows
                    if sid in quality
                ]
            ),
            "num_warnings": len(warned),
            "warnings": warned,
        }
    out = Path(output_dir)
    write_text(out / "scores.csv", table.getvalue())
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    records = [
        {
            "id": sid,
            "registered": _subject_scores(reg),
            "no_registration": _subject_scores(base),
            **({"quality": _jsonable(quality[sid])} if quality is not None and sid in quality else {}),
        }
        for sid, reg, base in rows
    ]
    write_text(out / "scores.json", json.dumps({"subjects": records, "config": summary["config"]}) + "\n")
    return summary


def _subject_scores(scores: PairScores) -> dict[str, Any]:
    """PairScores as JSON (NaN -> null, label ids as strings)."""

    def num(v: float) -> float | None:
        return None if math.isnan(v) else float(v)

    return {
        **{f: num(float(getattr(scores, f))) for f in PairScores._fields if f != "dice"},
        "dice": {str(k): num(v) for k, v in scores.dice.items()},
    }


def read_scores(path: str | os.PathLike) -> tuple[list[tuple[str, PairScores, PairScores]], dict[str, Any]]:
    """The rows and config of a ``scores.json`` written by :func:`write_scores`, ready to pass back to it."""
    data = json.loads(Path(path).read_text())

    def scores(record: Mapping[str, Any]) -> PairScores:
        value = {f: math.nan if record[f] is None else record[f] for f in PairScores._fields if f != "dice"}
        dice = {int(k): math.nan if v is None else v for k, v in record["dice"].items()}
        return PairScores(dice=dice, **{**value, "num_folding": int(value["num_folding"])})

    rows = [(r["id"], scores(r["registered"]), scores(r["no_registration"])) for r in data["subjects"]]
    return rows, data.get("config", {})


def summary_table(summary: Mapping[str, Any]) -> str:
    """A few lines of text: mean +- std over subjects, registered and (for Dice) without registration."""

    def fmt(stat: Mapping[str, float | None], digits: int) -> str:
        return "n/a" if stat["mean"] is None else f"{stat['mean']:.{digits}f} +- {stat['std']:.{digits}f}"

    reg, lines = summary["registered"], [f"{'':<16}{'registered':>22}{'no registration':>22}"]
    baseline = fmt(summary["no_registration"]["mean_dice"], 3)
    lines.append(f"{'mean Dice':<16}{fmt(reg['mean_dice'], 3):>22}{baseline:>22}")
    for name, key, digits in (
        ("|J|<=0 voxels", "num_folding", 1),
        ("|J|<=0 %", "percent_folding", 4),
        ("std log|J|", "std_log_jacobian", 3),
        ("runtime (s)", "runtime_s", 3),
    ):
        lines.append(f"{name:<16}{fmt(reg[key], digits):>22}")
    failed = summary.get("num_failed", 0)
    head = f"{summary['num_subjects']} subjects" + (
        f" ({failed} more failed and were skipped: failed.csv)" if failed else ""
    )
    return "\n".join([head, *lines])
