"""The quality model's whole-command cases: each subject through ``monai-probreg register``'s path onto the atlas.

The features of a registration depend on its path (the command line's affine stage undoes part of a wrong header, and
its features are taken on the model grid behind a brain mask), and a detector fitted on the bundle path alone passed a
turned native header as normal for some weights. So each subject also goes through the whole command
(:func:`monai_probreg.registration.scan.register_scan`) onto the atlas, with its header as it is (``COMMAND``) and
turned by 90 and 180 degrees about the S axis (:func:`turned_header`). Its "no registration" Dice is the bundle path's (same scan,
same atlas grid); "before" is the command's affine-only Dice. A training subject also goes through the whole command
onto itself (``COMMAND_SELF``; :mod:`~monai_probreg.fitting.self_cases`), its header moved by a small seeded rigid
motion (:func:`moved_header`) that the affine stage undoes: "no registration" is then the scan itself, Dice 1.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tempfile
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from tqdm import tqdm

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.fitting.quality_cases import RecordLog
from monai_probreg.fitting.self_cases import COMMAND_SELF, SELF_DICE, rigid_motion
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.scan import register_scan
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.quality import QualityModel, entropy_calibration_record, failed
from monai_probreg.uncertainty.quality_features import QualityFeatures
from monai_probreg.utils.errors import InputError

__all__ = [
    "HEADER_TURNS",
    "COMMAND",
    "COMMAND_NAMES",
    "COMMAND_SELF",
    "command_cases",
    "moved_header",
    "turned_header",
    "turned_inputs",
]

HEADER_TURNS = (0, 90, 180)  # degrees about the S axis through the scan's centre, applied to its header only
COMMAND = "command"  # the whole-command cases' perturbation name; turned ones add "_turn<degrees>"
COMMAND_NAMES = tuple(f"{COMMAND}_turn{d}" if d else COMMAND for d in HEADER_TURNS)
_LOG = logging.getLogger(__name__)


def command_cases(
    dataset_dir: Path,
    ids: list[str],
    bundle_root: Path,
    model_file: Path | None,
    identity_dice: dict[str, float],
    seed: int,
    refine: int | None = None,
    entropy_calibration: Calibration | None = None,
    log: RecordLog | None = None,
    self_cases: bool = False,
) -> list[dict]:
    """Each subject through the whole command onto the atlas, its header as it is and turned (module docstring), with
    inference.yaml's refinement (``refine`` steps when given), as ``monai-probreg register`` runs it.
    ``entropy_calibration``: the posterior calibration of the entropy feature (None: the weights' sidecar's, read
    only then). ``self_cases`` (training subjects only): each subject onto itself too, its header moved
    (``COMMAND_SELF``, the motion seeded with ``seed`` + the subject's place in ``ids``).
    ``log``: the cases it holds are taken from it, the others registered and added to it."""
    index = index_dataset(dataset_dir)
    # the summary records the features only when the weights have a quality model; the one being fitted has none yet,
    # so a neutral one (every coefficient 0) stands in: its estimate is ignored, the features are what is kept
    n = len(QualityFeatures._fields)
    neutral = QualityModel(
        list(QualityFeatures._fields),
        [-math.inf] * n,
        [math.inf] * n,
        [0.0] * n,
        [1.0] * n,
        [0.0] * n,
        0.5,
        [0.0] * n,
        0.0,
        entropy_calibration={} if entropy_calibration is None else entropy_calibration_record(entropy_calibration),
    )
    # the weights' calibration sidecar only where the entropy needs it: a refit for new weights finds a stale one
    loaded = load_model(bundle_root, model_file, calibrate=entropy_calibration is None, quality=False)
    model = dataclasses.replace(loaded, quality=neutral)
    fixed = prepare_fixed(index.atlas_image, index.atlas_label, model.divisor)
    # None: the command's default path (the config's refinement)
    refinement = None if refine is None else model.refinement.with_fields(num_iterations=refine)
    started = None if log is None else log.header.get("command_refinement")
    differ = {} if started is None else model.refinement.differences(started)
    if differ:  # inference.yaml changed since the run started
        raise InputError(
            f"inference.yaml's refinement is not the one this run started with (name: [at the start, now]): {differ}"
        )
    options = RegistrationOptions(qc=False, inverse=False, maps=False, seed=seed, refinement=refinement)
    records = []
    with tempfile.TemporaryDirectory(prefix="failure_command_") as tmp:
        for n, sid in enumerate(tqdm(ids, desc="whole-command registrations", unit="subject", disable=None)):
            cases = [
                ({"moving": sid, "fixed": ATLAS_ID, "perturbation": name, "seed": seed}, degrees)
                for degrees, name in zip(HEADER_TURNS, COMMAND_NAMES)
            ]
            if self_cases:
                cases.append(({"moving": sid, "fixed": sid, "perturbation": COMMAND_SELF, "seed": seed + n}, None))
            for case, degrees in cases:
                logged = log.get(COMMAND, case) if log is not None else None
                if logged is not None:
                    records.append(logged)
                    continue
                out = Path(tmp) / f"{sid}_{case['perturbation']}"
                if degrees is None:  # onto itself, its header (and its labels') moved
                    onto = prepare_fixed(index.images[sid], index.labels[sid], model.divisor)
                    scan, labels = _moved_inputs(index.images[sid], index.labels[sid], case["seed"], Path(tmp))
                    summary, identity = register_scan(model, onto, scan, out, labels, options), SELF_DICE
                else:
                    scan, labels = turned_inputs(index.images[sid], index.labels[sid], degrees, Path(tmp))
                    summary, identity = register_scan(model, fixed, scan, out, labels, options), identity_dice[sid]
                dice, before = summary["dice"]["mean"], summary["dice"]["mean_affine_only"]
                record = {
                    **case,
                    "dice": dice,
                    "dice_identity": identity,
                    "dice_before": before,
                    "failed": failed(dice, before, identity),
                    "features": summary["quality"]["features"],
                    "answer_features": summary["quality"]["answer_features"],
                }
                records.append(record if log is None else log.put(COMMAND, case, record))
                _LOG.info(
                    f"[command] {sid} ({case['perturbation']}): Dice {before:.3f} (affine) -> {dice:.3f}"
                    f"{' FAILED' if record['failed'] else ''}"
                )
    return records


def _grid_centre(scan: Path) -> np.ndarray:
    """The world (RAS) point at the centre of ``scan``'s voxel grid."""
    image = nib.load(scan)
    return (image.affine @ np.r_[(np.asarray(image.shape[:3]) - 1) / 2, 1.0])[:3]


def _moved_inputs(scan: Path, labels: Path, seed: int, folder: Path) -> tuple[Path, Path]:
    """``scan`` and its ``labels`` with their header moved by one :func:`~monai_probreg.fitting.self_cases.rigid_motion`
    (seeded with ``seed``) about the scan's grid centre, written into ``folder``."""
    motion = rigid_motion(torch.Generator().manual_seed(seed), _grid_centre(scan))
    stem = scan.name.split(".")[0]
    return tuple(moved_header(f, motion, folder / f"{stem}_{k}_moved.nii.gz") for k, f in enumerate((scan, labels)))


def moved_header(scan: Path, motion: np.ndarray, out: Path) -> Path:
    """``scan`` with the (4, 4) world transform ``motion`` applied to its header only (the voxels untouched), written
    to ``out``: voxel ``i`` now lies at ``motion @ affine @ i``."""
    image = nib.load(scan)
    affine = motion @ image.affine
    moved = nib.Nifti1Image(np.asanyarray(image.dataobj), affine, image.header)
    moved.set_qform(affine, code=1)
    moved.set_sform(affine, code=1)
    nib.save(moved, out)
    return out


def turned_header(scan: Path, degrees: float, out: Path, reference: Path | None = None) -> Path:
    """``scan`` with its header turned by ``degrees`` about the world S axis through the centre of ``reference``'s
    grid (default: its own; the voxels untouched): what a wrong orientation header does to a scan (and its labels)."""
    centre = _grid_centre(reference if reference is not None else scan)
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    return moved_header(scan, turn, out)


def turned_inputs(scan: Path, labels: Path | None, degrees: float, folder: Path) -> tuple[Path, Path | None]:
    """``scan`` and its ``labels`` (or None) with their header turned by ``degrees`` (0: the files as they are),
    written into ``folder``: the labels share the scan's (wrong) header, turned about the scan's grid centre."""
    if not degrees:
        return scan, labels
    stem = scan.name.split(".")[0]
    turned = turned_header(scan, degrees, folder / f"{stem}_turn{degrees}.nii.gz")
    if labels is not None:
        labels = turned_header(labels, degrees, folder / f"{stem}_labels_turn{degrees}.nii.gz", reference=scan)
    return turned, labels
