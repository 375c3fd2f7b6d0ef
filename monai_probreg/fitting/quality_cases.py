"""The quality model's registrations on the bundle's path: the cases of a split and one registration's record.

Each case (:func:`cases_for`) is a moving scan, a fixed scan, a perturbation of the moving one (``NORMAL``: none; else
one of :data:`~monai_probreg.fitting.failure_set.PERTURBATIONS`, or for a training subject onto itself one of
:data:`~monai_probreg.fitting.self_cases.SELF_PERTURBATIONS`) and a seed; :func:`run_case` registers it as
evaluate.yaml does (network, preprocessing, the refined mean when the refinement is on) on the dataset grid and
records the quality features of the network's own registration (what the estimate reads:
:mod:`monai_probreg.uncertainty.quality`, "Whose features"), those of the refined one (``answer_features``), the Dice
of the registration users get, the Dice of no registration and whether it failed. :class:`RecordLog` keeps the
records done so far (each rewritten atomically as it ends), so that a fit stopped part-way goes on where it stopped.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from monai.data import Dataset
from monai.networks.utils import eval_mode
from tqdm import tqdm

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import ATLAS_ID, scan_dicts
from monai_probreg.data.transforms import registration_transforms
from monai_probreg.engines.refinement import refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.fitting.failure_set import PERTURBATIONS
from monai_probreg.fitting.self_cases import SELF_PERTURBATIONS
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.metrics.scores import score_pair
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.uncertainty.quality import failed
from monai_probreg.uncertainty.quality_features import QualityFeatures, quality_features
from monai_probreg.utils.errors import InputError, first_line
from monai_probreg.utils.files import write_text
from monai_probreg.utils.tensors import plain_tensor

__all__ = [
    "NORMAL",
    "TRAIN_PARTNERS",
    "RecordLog",
    "logged_cases",
    "load_scans",
    "cases_for",
    "run_case",
    "record_features",
]

_LOG = logging.getLogger(__name__)

NORMAL = "none"
TRAIN_PARTNERS = 2  # normal training registrations per subject besides the atlas
_PERTURB = {**PERTURBATIONS, **SELF_PERTURBATIONS}  # every perturbation of a case's moving scan, by name


def load_scans(dataset_dir: Path, ids: list[str], divisor: int) -> dict[str, dict]:
    """Each scan (the subjects ``ids`` and the atlas) once through the preprocessing: image, label (1, 1, *S), spacing."""
    index = index_dataset(dataset_dir)
    transform = registration_transforms(with_labels=True, divisor=divisor, image_keys=["image"], label_keys=["label"])
    out = {}
    for item in Dataset(scan_dicts(index, ids, include_atlas=True, require_labels=True), transform=transform):
        image = item["image"]
        spacing = np.linalg.norm(np.asarray(image.affine)[:3, :3], axis=0).tolist()
        out[item["id"]] = {
            "image": plain_tensor(image)[None].float(),
            "label": plain_tensor(item["label"])[None],
            "spacing": spacing,
        }
    return out


def cases_for(ids: list[str], seed: int, training: bool) -> list[dict[str, Any]]:
    """The registrations of one split: (moving, fixed, perturbation, seed) dicts, normal ones first. Validation:
    every ordered pair, every subject to the atlas, each perturbation onto the atlas and onto another subject.
    Training (many more subjects): each subject to the atlas and to ``TRAIN_PARTNERS`` others, each perturbation
    onto the atlas or another subject, alternately, and last each subject onto itself, unchanged and as a near copy
    (:data:`~monai_probreg.fitting.self_cases.SELF_PERTURBATIONS`; last, so the other cases keep their seeds)."""
    cases = []
    for n, sid in enumerate(ids):
        cases.append({"moving": sid, "fixed": ATLAS_ID, "perturbation": NORMAL})
        others = [o for o in ids[n + 1 :] + ids[:n]]
        for other in others[:TRAIN_PARTNERS] if training else others:
            cases.append({"moving": sid, "fixed": other, "perturbation": NORMAL})
    for n, sid in enumerate(ids):
        others = [o for o in ids[n + 1 :] + ids[:n]] or [ATLAS_ID]
        for k, name in enumerate(PERTURBATIONS):
            other = others[k % len(others)]
            targets = [(ATLAS_ID, other)[(n + k) % 2]] if training else [ATLAS_ID, other]
            for fixed in dict.fromkeys(targets):
                cases.append({"moving": sid, "fixed": fixed, "perturbation": name})
    if training:
        cases += [{"moving": sid, "fixed": sid, "perturbation": name} for sid in ids for name in SELF_PERTURBATIONS]
    return [{**c, "seed": seed + i} for i, c in enumerate(cases)]


def run_case(network, calibration, scans: dict, case: dict, refinement=None) -> dict:
    """One registration of the bundle path (the mean refined for the pair when ``refinement`` is enabled): the quality
    features of the network's own registration (what the estimate reads: quality.py, "Whose features") and, when
    refined, of the refined one; Dice of the registration users get, Dice of no registration and whether it failed."""
    moving, fixed = scans[case["moving"]], scans[case["fixed"]]
    image, label = moving["image"], moving["label"]
    if case["perturbation"] != NORMAL:
        g = torch.Generator().manual_seed(case["seed"])
        image, label = _PERTURB[case["perturbation"]](image, label, g)
    network_output = register_pair(network, image, fixed["image"])
    output = None
    if refinement is not None and refinement.enabled:  # from the same network output: one forward pass
        with eval_mode(network):
            output = refine_registration(network, image, fixed["image"], network_output, refinement)

    def features_of(out) -> QualityFeatures:
        entropy = posterior_maps(
            network,
            out.velocity_mean,
            out.velocity_log_var,
            out.displacement.shape[2:],
            std_scale=calibration.std_scale,
            bias_fraction=calibration.bias_fraction,
        ).velocity_entropy
        return quality_features(
            image[0, 0],
            fixed["image"][0, 0],
            out.warped[0, 0],
            out.displacement[0],
            entropy,
            fixed["spacing"],
            jacobian=jacobian_determinant(out.displacement)[0],
        )

    after = score_pair((output or network_output).displacement, label, fixed["label"]).mean_dice
    identity = score_pair(None, label, fixed["label"]).mean_dice
    return {
        **case,
        "dice": after,
        "dice_identity": identity,
        "failed": failed(after, identity, identity),
        "features": features_of(network_output)._asdict(),
        "answer_features": None if output is None else features_of(output)._asdict(),
    }


def record_features(records: list[dict]) -> list[QualityFeatures]:
    """The quality features of each record (the network's registration's, what the estimate reads)."""
    return [QualityFeatures(**r["features"]) for r in records]


class RecordLog:
    """The registrations done so far, one record per case, rewritten (atomically) after each new one at ``path``.

    ``header``: what makes a record (JSON values: weights' SHA-256, refinement, entropy calibration, subjects, seed).
    ``resume``: reuse the records of ``path`` when it exists; one made under another header is refused, naming the
    fields that differ (records of other settings are never mixed in). Without ``resume`` the log starts empty and
    replaces ``path`` at its first record. ``path`` None: nothing is kept (every case is registered)."""

    def __init__(self, path: Path | None, header: dict[str, Any], resume: bool = False) -> None:
        self.path, self.header, self.records = path, json.loads(json.dumps(header)), {}
        if resume and path is not None and path.is_file():
            try:
                stored = json.loads(path.read_text())
                recorded, records = stored["header"], dict(stored["records"])
            except (OSError, ValueError, TypeError, KeyError) as err:
                raise InputError(
                    f"{path}: expected a log of registrations (header and records), got an unreadable file "
                    f"({first_line(err)}); run without --resume to start again"
                ) from None
            differ = {k: [recorded.get(k), v] for k, v in self.header.items() if recorded.get(k) != v}
            if differ:
                raise InputError(
                    f"{path}: logged under other settings, not resumed (name: [logged, now]): {differ}; "
                    "run without --resume to start again"
                )
            self.records = records
        self.reused = len(self.records)

    @staticmethod
    def key(kind: str, case: dict[str, Any]) -> str:
        """``kind`` (train, val, command) and the case's moving, fixed, perturbation and seed."""
        return json.dumps([kind, *(case[k] for k in ("moving", "fixed", "perturbation", "seed"))])

    def get(self, kind: str, case: dict[str, Any]) -> dict | None:
        return self.records.get(self.key(kind, case))

    def put(self, kind: str, case: dict[str, Any], record: dict) -> dict:
        self.records[self.key(kind, case)] = record
        self.save()
        return record

    def save(self) -> None:
        """Write the header and every record to ``path`` (atomically; nothing without a path)."""
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_text(self.path, json.dumps({"header": self.header, "records": self.records}) + "\n")


def logged_cases(kind: str, cases: list[dict], run: Callable[[dict], dict], log: RecordLog) -> list[dict]:
    """``run(case)`` for each case, in order, but those ``log`` holds (taken from it); each new record is logged."""
    records = []
    for n, case in enumerate(tqdm(cases, desc=f"{kind} registrations", unit="pair", disable=None)):
        r = log.get(kind, case)
        if r is None:
            r = log.put(kind, case, run(case))
            _LOG.info(
                f"[{kind} {n + 1}/{len(cases)}] {r['moving']} -> {r['fixed']} ({r['perturbation']}): Dice "
                f"{r['dice_identity']:.3f} -> {r['dice']:.3f}{' FAILED' if r['failed'] else ''}  "
                f"ncc {r['features']['ncc_before']:.2f} -> {r['features']['ncc_after']:.2f}"
            )
        records.append(r)
    return records
