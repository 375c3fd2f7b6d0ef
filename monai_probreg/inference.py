"""Register one pair with a trained model, write the results as NIfTI and score them.

The functional core of ``bundle/configs/inference.yaml`` and ``evaluate.yaml``; the engine handlers in
:mod:`monai_probreg.inference_handlers` call it once per subject. The package conventions apply
(``monai_probreg/__init__.py``), and:

- Every output lives on the **fixed (atlas) grid after preprocessing** (reoriented to RAS, padded to the
  divisor) and is written with that grid's affine, ``fixed.affine`` of the MetaTensor after the transforms:
  the moving image is warped into the fixed grid, so the outputs overlay the atlas in world coordinates.
- Layout: one folder per subject, ``output_dir/<id>/<name>.nii.gz`` with the names in :data:`OUTPUT_NAMES`.
- ``displacement.nii.gz``: float32, shape (X, Y, Z, 1, 3), NIfTI intent "vector" (1007). Component k (5th axis)
  is the displacement along array axis k of this file's grid, **in voxels**; pull back:
  ``warped[i] = moving[i + u(i)]``. In millimetres (world axes): ``affine[:3, :3] @ u``. (ITK/ANTs expect mm
  in LPS; convert before using the field there.)
- ``warped.nii.gz`` holds the moving image's intensities as the network saw them (percentile-scaled to [0, 1]).
- Files are written atomically: a temporary name in the same folder, then ``os.replace``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import nibabel as nib
import numpy as np
import torch
from monai.data import MetaTensor
from monai.networks.utils import eval_mode
from torch import Tensor, nn

from monai_probreg.blocks.warp import warp_labels
from monai_probreg.data import DatasetIndex, pair_dicts
from monai_probreg.network_settings import check_network_settings
from monai_probreg.metrics.dice import label_dice
from monai_probreg.metrics.jacobian import JacobianStats, jacobian_determinant, jacobian_stats
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.posterior_maps import PosteriorMaps
from monai_probreg.uncertainty import velocity_entropy
from monai_probreg.validation import safe_torch_load

__all__ = ["OUTPUT_NAMES", "SAMPLED_NAMES", "OUTPUTS_README", "DISPLACEMENT_DESCRIPTION", "load_weights", "labelled_pairs",
           "register_pair", "timed_register_pair", "atomic_write", "write_text", "save_nifti", "write_outputs",
           "PairScores", "score_pair", "evaluate_pair", "write_scores", "read_scores", "summary_table"]

OUTPUT_NAMES = ("warped", "displacement", "jacobian", "entropy", "warped_label", "displacement_std", "label_entropy")
SAMPLED_NAMES = ("displacement_std", "label_entropy")  # need K >= 2 posterior samples (PosteriorMaps)
DISPLACEMENT_DESCRIPTION = "displacement in voxels, comp k = array axis k; warped[i]=moving[i+u(i)]"
OUTPUTS_README = """\
Registration outputs of monai_probreg (VoxelMorph-diff), one folder per subject: <id>/<name>.nii.gz.
Every file lies on the atlas (fixed) grid as preprocessed (reoriented to RAS, padded to the divisor) and carries
that grid's affine, so it overlays the atlas in world coordinates.
  warped.nii.gz        moving image resampled into the atlas grid (intensities percentile-scaled to [0, 1])
  displacement.nii.gz  float32 (X, Y, Z, 1, 3), NIfTI intent vector; component k = displacement along array
                       axis k of this grid, in VOXELS; pull back: warped[i] = moving[i + u(i)];
                       in millimetres (world axes): affine[:3, :3] @ u (ITK/ANTs expect mm, LPS)
  jacobian.nii.gz      det(I + grad u) of x -> x + u(x); <= 0 marks folding
  entropy.nii.gz       entropy (nats) of the calibrated velocity posterior q(z) (Dalca et al. 2018, Eq. 8),
                       resized to this grid; relative: compare regions, not absolute values
  warped_label.nii.gz  moving labels warped nearest neighbour (written when labels exist)
  displacement_std.nii.gz  sqrt(sum of the 3 variances) of K displacements drawn from the calibrated posterior,
                       in voxels: how far, roughly, each voxel's correspondence may be off (calibration and its
                       limits: the bundle docs, "Uncertainty")
  label_entropy.nii.gz entropy (nats) of the moving labels warped by the K samples: 0 = every sample agrees;
                       high values flag voxels whose warped label is likely wrong (written when labels exist)
"""


def _plain(t: Tensor) -> Tensor:
    return t.as_tensor() if isinstance(t, MetaTensor) else t


def load_weights(network: nn.Module, model_file: str | os.PathLike, device: str | torch.device = "cpu") -> nn.Module:
    """Load a plain state_dict (``torch.load(weights_only=True)``, strict) into ``network``; move it to ``device``
    and put it in eval mode. A missing file is a one-line ``FileNotFoundError`` naming the path; a file holding more
    than tensors (a pickle that could run code) an ``UntrustedFileError`` (:func:`~monai_probreg.validation.
    safe_torch_load`: nothing in it is run); a truncated or corrupt one an ``InputError``, and so is a network whose
    settings differ from those recorded next to the file (:mod:`monai_probreg.network_settings`)."""
    path = Path(model_file)
    if not path.is_file():
        raise FileNotFoundError(f"model file {str(path)!r} does not exist (train.yaml writes models/model.pt; "
                                "or pass --model_file PATH)")
    check_network_settings(path, network)  # network_size etc. leave no trace in the tensors: their JSON sidecar
    network.load_state_dict(safe_torch_load(path, "model file", map_location=device))
    return network.to(device).eval()


def labelled_pairs(index: DatasetIndex, ids: Sequence[str] | None = None) -> list[dict]:
    """:func:`~monai_probreg.data.pair_dicts` of the subjects (``ids``, default all) with labels; a clear error
    when there are none."""
    pairs = pair_dicts(index, ids, require_labels=True)
    if not pairs:
        where = ("the atlas has no *_label file" if index.atlas_label is None
                 else "no labels/<id>.nii.gz matches an image")
        raise ValueError(f"nothing to evaluate in {str(index.atlas_image.parent.parent)!r}: {where}; "
                         "evaluation needs labels (use inference.yaml to register unlabelled images)")
    return pairs


def register_pair(network: nn.Module, moving: Tensor, fixed: Tensor) -> RegistrationOutput:
    """Register ``moving`` onto ``fixed`` (both (B, C, *S)) in eval mode (posterior mean velocity), under
    ``torch.inference_mode()``; the network's previous train/eval mode is restored afterwards."""
    with eval_mode(network), torch.inference_mode():
        return network(_plain(moving), _plain(fixed))


def timed_register_pair(network: nn.Module, moving: Tensor, fixed: Tensor) -> tuple[RegistrationOutput, float]:
    """:func:`register_pair` and its wall time in seconds (network + integration + warp; CUDA synchronised)."""
    sync = torch.cuda.synchronize if moving.is_cuda else (lambda: None)
    sync()
    start = time.perf_counter()
    output = register_pair(network, moving, fixed)
    sync()
    return output, time.perf_counter() - start


def _atomic_write(path: Path, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file next to ``path`` (same suffixes), then rename it onto ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = str(path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp{''.join(path.suffixes)}")  # umask perms
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Write a file atomically with any writer: ``write(tmp)`` on a temporary name next to ``path`` that keeps
    its suffixes (so ``itk.imwrite`` picks the right format), then ``os.replace`` onto ``path``."""
    return _atomic_write(Path(path), write)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file atomically."""
    return _atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text))


def save_nifti(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray, description: str = "",
               intent: str | None = None) -> Path:
    """Write ``data`` (array axes = the affine's voxel axes) atomically; qform and sform both = ``affine``."""
    image = nib.Nifti1Image(data, np.asarray(affine, dtype=np.float64))
    image.set_qform(image.affine, code=1)
    image.set_sform(image.affine, code=1)
    image.header["descrip"] = description.encode()[:79]
    if intent is not None:
        image.header.set_intent(intent)
    return _atomic_write(Path(path), lambda tmp: nib.save(image, tmp))


def write_outputs(output_dir: str | os.PathLike, subject_id: str, output: RegistrationOutput,
                  affine: Tensor | np.ndarray, moving_label: Tensor | None = None,
                  names: Sequence[str] = OUTPUT_NAMES, maps: PosteriorMaps | None = None) -> dict[str, Path]:
    """Write one subject's results into ``output_dir/<subject_id>/`` (see the module docstring).

    Shapes: ``output`` of one pair (B = 1) on the fixed grid S; ``affine`` (4, 4) of that grid;
    ``moving_label`` (1, 1, *S) integer, or None (no ``warped_label``). ``names``: which of :data:`OUTPUT_NAMES`
    to write. ``maps``: calibrated :class:`~monai_probreg.posterior_maps.PosteriorMaps` (then ``entropy`` is
    theirs, and :data:`SAMPLED_NAMES` are written when present); None: ``entropy`` of the raw posterior and no
    sampled maps. Returns {name: path written}.
    """
    unknown = set(names) - set(OUTPUT_NAMES)
    if unknown:
        raise ValueError(f"unknown output names {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")
    disp = output.displacement.detach().float()
    if disp.ndim != 5 or disp.shape[0] != 1:
        raise ValueError(f"expected one 3-d pair, displacement (1, 3, X, Y, Z); got {tuple(disp.shape)}")
    folder, aff, size = Path(output_dir) / subject_id, np.asarray(torch.as_tensor(affine).cpu()), disp.shape[2:]
    makers: dict[str, tuple[Callable[[], Tensor], str, str | None]] = {
        "warped": (lambda: output.warped[0, 0], "moving image warped to the fixed grid, intensities in [0, 1]", None),
        "displacement": (lambda: disp[0].movedim(0, -1).unsqueeze(-2), DISPLACEMENT_DESCRIPTION, "vector"),
        "jacobian": (lambda: jacobian_determinant(disp)[0], "Jacobian determinant of x -> x + u(x)", None),
        "entropy": (lambda: velocity_entropy(output.velocity_log_var.float(), size)[0, 0] if maps is None
                    else maps.velocity_entropy, "velocity entropy" + (" (raw)" if maps is None else ""), None),
        "displacement_std": (lambda: maps.displacement_std, "displacement std over posterior samples, voxels", None),
        "label_entropy": (lambda: maps.label_entropy, "entropy of labels warped by posterior samples", None),
        "warped_label": (lambda: warp_labels(_plain(moving_label).to(disp.device), disp)[0, 0].to(torch.int16),
                         "moving labels warped to the fixed grid, nearest neighbour", None),
    }
    written = {}
    for name in names:
        if name == "warped_label" and moving_label is None:
            continue
        if name in SAMPLED_NAMES and (maps is None or getattr(maps, name) is None):
            continue
        compute, description, intent = makers[name]
        array = _plain(compute()).detach().cpu().numpy()
        array = array if array.dtype == np.int16 else array.astype(np.float32)
        written[name] = save_nifti(folder / f"{name}.nii.gz", array, aff, description, intent)
    return written


class PairScores(NamedTuple):
    """Scores of one registration: Dice per fixed label and their mean; |J| <= 0 count and percentage and std of
    log|J| over the whole fixed grid (padding included); runtime in seconds (0 for no registration)."""

    dice: dict[int, float]
    mean_dice: float
    num_folding: int
    percent_folding: float
    std_log_jacobian: float
    runtime_s: float


def score_pair(displacement: Tensor | None, moving_label: Tensor, fixed_label: Tensor, runtime_s: float = 0.0,
               labels: Sequence[int] | None = None) -> PairScores:
    """Score a displacement (1, 3, *S) (None = no registration, the identity) with labels (1, 1, *S) on the
    same grid: Dice of the nearest-neighbour warped moving labels against the fixed labels for ``labels``
    (default: the non-zero labels of ``fixed_label``) and folding statistics of the displacement."""
    moving_label, fixed_label = _plain(moving_label), _plain(fixed_label)
    if displacement is None:
        warped, stats = moving_label, JacobianStats(0, 0.0, 0.0)
    else:
        displacement = _plain(displacement).float()
        warped = warp_labels(moving_label.to(displacement.device), displacement)
        stats = jacobian_stats(jacobian_determinant(displacement))
    dice = label_dice(warped.cpu(), fixed_label.cpu(), labels)
    values = [d for d in dice.values() if not math.isnan(d)]
    mean = sum(values) / len(values) if values else float("nan")
    return PairScores(dice, mean, stats.num_folding, stats.percent_folding, stats.std_log_jacobian, runtime_s)


def evaluate_pair(network: nn.Module, moving: Tensor, fixed: Tensor, moving_label: Tensor, fixed_label: Tensor,
                  labels: Sequence[int] | None = None) -> tuple[PairScores, PairScores]:
    """Register one pair (timed) and score it; returns (registered, no registration) scores."""
    output, runtime = timed_register_pair(network, moving, fixed)
    return (score_pair(output.displacement, moving_label, fixed_label, runtime, labels),
            score_pair(None, moving_label, fixed_label, 0.0, labels))


def _mean_std(values: Sequence[float]) -> dict[str, float | None]:
    arr = np.asarray([v for v in values if not math.isnan(v)], dtype=np.float64)
    return {"mean": float(arr.mean()), "std": float(arr.std())} if arr.size else {"mean": None, "std": None}


def _jsonable(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value if isinstance(value, (bool, int, float, str, type(None))) else str(value)


def _label_mean(scores: Sequence[PairScores], label: int) -> float | None:
    return _mean_std([s.dice.get(label, math.nan) for s in scores])["mean"]


def write_scores(output_dir: str | os.PathLike, rows: Sequence[tuple[str, PairScores, PairScores]],
                 config: Mapping[str, Any] | None = None,
                 failed: Sequence[tuple[str, str]] = ()) -> dict[str, Any]:
    """Write ``scores.csv`` (one row per subject), ``summary.json`` (mean and population std over subjects,
    registered and no-registration, per-label means, ``config``) and ``scores.json`` (every score of every subject,
    :func:`read_scores` reads it back: how sharded runs are merged) into ``output_dir``; return the summary.
    ``failed``: ``(id, reason)`` of the subjects skipped for bad input (:mod:`monai_probreg.screening`), listed in
    summary.json."""
    if not rows:
        raise ValueError("no scored subjects to summarise")
    labels = sorted({lab for _, reg, _ in rows for lab in reg.dice})
    fields = ["mean_dice", "num_folding", "percent_folding", "std_log_jacobian", "runtime_s"]
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(["id", *fields, "mean_dice_no_registration", *(f"dice_{lab}" for lab in labels)])
    for sid, reg, base in rows:
        writer.writerow([sid, *(getattr(reg, f) for f in fields), base.mean_dice,
                         *(reg.dice.get(lab, "") for lab in labels)])
    summary = {
        "num_subjects": len(rows),
        "registered": {f: _mean_std([float(getattr(reg, f)) for _, reg, _ in rows]) for f in fields},
        "no_registration": {"mean_dice": _mean_std([base.mean_dice for _, _, base in rows])},
        "dice_per_label": {str(lab): {"registered": _label_mean([reg for _, reg, _ in rows], lab),
                                      "no_registration": _label_mean([base for _, _, base in rows], lab)}
                           for lab in labels},
        "num_failed": len(failed),
        "failed": [{"id": sid, "reason": reason} for sid, reason in failed],
        "config": {k: _jsonable(v) for k, v in (config or {}).items()},
    }
    out = Path(output_dir)
    write_text(out / "scores.csv", table.getvalue())
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    records = [{"id": sid, "registered": _subject_scores(reg), "no_registration": _subject_scores(base)}
               for sid, reg, base in rows]
    write_text(out / "scores.json", json.dumps({"subjects": records, "config": summary["config"]}) + "\n")
    return summary


def _subject_scores(scores: PairScores) -> dict[str, Any]:
    """PairScores as JSON (NaN -> null, label ids as strings)."""
    def num(v: float) -> float | None:
        return None if math.isnan(v) else float(v)
    return {**{f: num(float(getattr(scores, f))) for f in PairScores._fields if f != "dice"},
            "dice": {str(k): num(v) for k, v in scores.dice.items()}}


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
    for name, key, digits in (("|J|<=0 voxels", "num_folding", 1), ("|J|<=0 %", "percent_folding", 4),
                              ("std log|J|", "std_log_jacobian", 3), ("runtime (s)", "runtime_s", 3)):
        lines.append(f"{name:<16}{fmt(reg[key], digits):>22}")
    failed = summary.get("num_failed", 0)
    head = f"{summary['num_subjects']} subjects" + (f" ({failed} more failed and were skipped: failed.csv)" if failed else "")
    return "\n".join([head, *lines])
