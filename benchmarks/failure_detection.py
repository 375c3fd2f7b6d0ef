"""Does the quality estimate warn when a registration failed? Fit on training subjects, score on validation ones.

Registrations (bundle path: evaluate.yaml's network, preprocessing and calibrated posterior, on the dataset grid):
- normal: every ordered pair of the validation subjects and each validation subject -> atlas (S01);
- the failure set (``failure_set.py``): each validation subject, perturbed by each perturbation, onto the atlas and
  onto another validation subject (seeded).
The detector (:mod:`monai_probreg.uncertainty.quality`) is fitted on the same kinds of registrations of the
*training* subjects only (each to the atlas and to another training subject, and each perturbed by every
perturbation onto the atlas or another training subject), never on a validation subject.
With refinement (evaluate.yaml's ``refine_iterations``, the default path; ``--refine N``), each registration's
features are those of the network's own registration and its Dice and "failed" those of the refined one
(:mod:`monai_probreg.uncertainty.quality`, "Whose features"); the refined one's features are kept as
``answer_features``; the whole-command cases do the same through the command.

The whole command path (on by default; ``--no-command-cases`` leaves it out): the features of a registration depend on its path
(the command line's affine stage undoes part of a wrong header, and its features are taken on the model grid behind
a brain mask), and a detector fitted on the bundle path alone passed a turned native header as normal for some
weights. So each subject (training ones for the fit, validation ones for the score; the native scans' subjects are
left out) also goes through the whole command (:func:`monai_probreg.cli.pipeline.register_scan`) onto the atlas,
with its header as it is ("command") and turned by 90 and 180 degrees ("command_turn90", "command_turn180"). Its
"no registration" Dice is the bundle path's (same scan, same atlas grid); "before" is the command's affine-only Dice.

The native scans (``--native-dir``, default ``../shared/data/lpba40-native``) go through the whole command
(``monai-probreg register`` onto the atlas, affine stage included), as users bring them: as they are, and with their
orientation header turned by 90 and by 180 degrees about the S axis (the case that gave Dice 0.001 and no warning
before); reported with their Dice where they have labels, not part of the scored set (a handful of cases).

A registration *failed* when its Dice is below the Dice before the deformable step or below no registration + 0.05
(on this path the moving scan is already affinely aligned, so both "before" Dice are the identity's). Reported:
Spearman(predicted, actual Dice) over the normal validation pairs (between subjects, to the atlas, both), AUROC of
the failure probability for "failed" over every validation registration, false warnings on the normal validation
pairs, and per perturbation: Dice before and after, the share that failed and the share warned.

    python benchmarks/failure_detection.py --threads 2 --fit    # fits and writes <weights>.quality.json too
    python benchmarks/failure_detection.py --records benchmarks/results/failure_detection.json --fit  # refit only

The registrations take one to two hours. Each one is logged as it ends (``OUT_DIR/failure_detection.partial.json``,
written atomically); ``--resume`` reuses the logged ones and registers only the rest, so a run stopped part-way goes on
where it stopped. A log made under other settings (weights, refinement, calibration, subjects, seed) is refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_NATIVE, DEFAULT_OUT, REPO, bundle_parser, run_command
from failure_set import PERTURBATIONS
from monai.data import Dataset
from monai.networks.utils import eval_mode

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import ATLAS_ID, scan_dicts
from monai_probreg.data.transforms import registration_transforms
from monai_probreg.engines.refinement import refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.metrics.calibration import auroc, spearman
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.metrics.scores import score_pair
from monai_probreg.uncertainty.calibration import Calibration, calibration_for
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.uncertainty.quality import (
    QualityModel,
    entropy_calibration_record,
    failed,
    fit_quality_model,
    save_quality_model,
)
from monai_probreg.uncertainty.quality_features import QualityFeatures, quality_features
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.utils.tensors import plain_tensor
from monai_probreg.weights.loading import load_weights

NORMAL = "none"
HEADER_TURNS = (0, 90, 180)  # degrees about the S axis through the scan's centre, applied to its header only
COMMAND = "command"  # the whole-command cases' perturbation name; turned ones add "_turn<degrees>"
COMMAND_NAMES = tuple(f"{COMMAND}_turn{d}" if d else COMMAND for d in HEADER_TURNS)
TRAIN_PARTNERS = 2  # normal training registrations per subject besides the atlas
PARTIAL_LOG = "failure_detection.partial.json"  # the registrations done so far, in OUT_DIR (--resume)


class RecordLog:
    """The registrations done so far, one record per case, rewritten (atomically) after each new one at ``path``.

    ``header``: what makes a record (JSON values: weights' SHA-256, refinement, entropy calibration, subjects, seed).
    ``resume``: reuse the records of ``path`` when it exists; one made under another header is refused, naming the
    fields that differ (records of other settings are never mixed in). Without ``resume`` the log starts empty and
    replaces ``path`` at its first record. ``path`` None: nothing is kept (every case is registered)."""

    def __init__(self, path: Path | None, header: dict[str, Any], resume: bool = False) -> None:
        self.path, self.header, self.records = path, json.loads(json.dumps(header)), {}
        if resume and path is not None and path.is_file():
            stored = json.loads(path.read_text())
            recorded = stored.get("header", {})
            differ = {k: [recorded.get(k), v] for k, v in self.header.items() if recorded.get(k) != v}
            if differ:
                raise SystemExit(
                    f"{path}: logged under other settings, not resumed (name: [logged, now]): {differ}; "
                    "run without --resume to start again"
                )
            self.records = dict(stored["records"])
        self.reused = len(self.records)

    @staticmethod
    def key(kind: str, case: dict[str, Any]) -> str:
        """``kind`` (train, val, command) and the case's moving, fixed, perturbation and seed."""
        return json.dumps([kind, *(case[k] for k in ("moving", "fixed", "perturbation", "seed"))])

    def get(self, kind: str, case: dict[str, Any]) -> dict | None:
        return self.records.get(self.key(kind, case))

    def put(self, kind: str, case: dict[str, Any], record: dict) -> dict:
        self.records[self.key(kind, case)] = record
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_text(self.path, json.dumps({"header": self.header, "records": self.records}) + "\n")
        return record


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
    onto the atlas or another subject, alternately."""
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
    return [{**c, "seed": seed + i} for i, c in enumerate(cases)]


def run_case(network, calibration, scans: dict, case: dict, refinement=None) -> dict:
    """One registration of the bundle path (the mean refined for the pair when ``refinement`` is enabled): the quality
    features of the network's own registration (what the estimate reads: quality.py, "Whose features") and, when
    refined, of the refined one; Dice of the registration users get, Dice of no registration and whether it failed."""
    moving, fixed = scans[case["moving"]], scans[case["fixed"]]
    image, label = moving["image"], moving["label"]
    if case["perturbation"] != NORMAL:
        g = torch.Generator().manual_seed(case["seed"])
        image, label = PERTURBATIONS[case["perturbation"]](image, label, g)
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
) -> list[dict]:
    """Each subject through the whole command onto the atlas, its header as it is and turned (module docstring), with
    inference.yaml's refinement (``refine`` steps when given), as ``monai-probreg register`` runs it.
    ``entropy_calibration``: the posterior calibration of the entropy feature (None: the weights' sidecar's).
    ``log``: the cases it holds are taken from it, the others registered and added to it."""
    from monai_probreg.cli.model import load_model  # the command line's own loading, calibration and brain mask
    from monai_probreg.cli.pipeline import RegistrationOptions, prepare_fixed, register_scan

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
    model = dataclasses.replace(load_model(bundle_root, model_file, quality=False), quality=neutral)
    fixed = prepare_fixed(index.atlas_image, index.atlas_label, model.divisor)
    # None: the command's default path (the config's refinement)
    refinement = None if refine is None else dataclasses.replace(model.refinement, num_iterations=refine)
    started = None if log is None else log.header.get("command_refinement")
    differ = {} if started is None else model.refinement.differences(started)
    if differ:  # inference.yaml changed since the run started
        raise SystemExit(
            f"inference.yaml's refinement is not the one this run started with (name: [at the start, now]): {differ}"
        )
    records = []
    with tempfile.TemporaryDirectory(prefix="failure_command_") as tmp:
        for sid in ids:
            for degrees, name in zip(HEADER_TURNS, COMMAND_NAMES):
                case = {"moving": sid, "fixed": ATLAS_ID, "perturbation": name, "seed": seed}
                logged = log.get(COMMAND, case) if log is not None else None
                if logged is not None:
                    records.append(logged)
                    continue
                scan, labels = turned_inputs(index.images[sid], index.labels[sid], degrees, Path(tmp))
                summary = register_scan(
                    model,
                    fixed,
                    scan,
                    Path(tmp) / f"{sid}_{degrees}",
                    labels,
                    RegistrationOptions(qc=False, inverse=False, maps=False, seed=seed, refinement=refinement),
                )
                dice, before = summary["dice"]["mean"], summary["dice"]["mean_affine_only"]
                record = {
                    **case,
                    "dice": dice,
                    "dice_identity": identity_dice[sid],
                    "dice_before": before,
                    "failed": failed(dice, before, identity_dice[sid]),
                    "features": summary["quality"]["features"],
                    "answer_features": summary["quality"]["answer_features"],
                }
                records.append(record if log is None else log.put(COMMAND, case, record))
                print(
                    f"[command] {sid} header turned {degrees} deg: Dice {before:.3f} (affine) -> {dice:.3f}"
                    f"{' FAILED' if record['failed'] else ''}",
                    flush=True,
                )
    return records


def logged_cases(kind: str, cases: list[dict], run: Callable[[dict], dict], log: RecordLog) -> list[dict]:
    """``run(case)`` for each case, in order, but those ``log`` holds (taken from it); each new record is logged."""
    records = []
    for n, case in enumerate(cases):
        r = log.get(kind, case)
        if r is None:
            r = log.put(kind, case, run(case))
            print(
                f"[{kind} {n + 1}/{len(cases)}] {r['moving']} -> {r['fixed']} ({r['perturbation']}): Dice "
                f"{r['dice_identity']:.3f} -> {r['dice']:.3f}{' FAILED' if r['failed'] else ''}  "
                f"ncc {r['features']['ncc_before']:.2f} -> {r['features']['ncc_after']:.2f}",
                flush=True,
            )
        records.append(r)
    return records


def _features(records: list[dict]) -> list[QualityFeatures]:
    return [QualityFeatures(**r["features"]) for r in records]


def score(model, records: list[dict]) -> dict[str, Any]:
    dice_hat, probability = model.predict(_features(records))
    for r, d, p in zip(records, dice_hat, probability):
        r["predicted_dice"], r["failure_probability"], r["warned"] = float(d), float(p), bool(p >= model.threshold)
    normal = [r for r in records if r["perturbation"] == NORMAL]
    between = [r for r in normal if r["fixed"] != ATLAS_ID]
    to_atlas = [r for r in normal if r["fixed"] == ATLAS_ID]

    def rho(rs):
        return (
            spearman(np.asarray([r["predicted_dice"] for r in rs]), np.asarray([r["dice"] for r in rs]))
            if len(rs) > 2
            else math.nan
        )

    outcome = [r["failed"] for r in records]
    per = {}
    for name in [NORMAL, *PERTURBATIONS, *COMMAND_NAMES]:
        rs = [r for r in records if r["perturbation"] == name]
        if rs:
            per[name] = {
                "n": len(rs),
                "dice_before": float(np.mean([r["dice_identity"] for r in rs])),
                "dice_after": float(np.mean([r["dice"] for r in rs])),
                "failed": float(np.mean([r["failed"] for r in rs])),
                "warned": float(np.mean([r["warned"] for r in rs])),
                "warned_of_failed": (
                    float(np.mean([r["warned"] for r in rs if r["failed"]])) if any(r["failed"] for r in rs) else None
                ),
            }
    return {
        "spearman_normal_pairs": rho(normal),
        "spearman_between_subjects": rho(between),
        "spearman_to_atlas": rho(to_atlas),
        "auroc_failure": auroc(np.asarray([r["failure_probability"] for r in records]), np.asarray(outcome))
        if 0 < sum(outcome) < len(outcome)
        else math.nan,
        "false_warnings_normal": float(np.mean([r["warned"] for r in normal])) if normal else math.nan,
        "num_registrations": len(records),
        "num_failed": int(sum(outcome)),
        "warned_of_failed": float(np.mean([r["warned"] for r in records if r["failed"]])) if any(outcome) else None,
        "per_perturbation": per,
    }


def markdown(result: dict[str, Any], threshold: float) -> str:
    lines = [
        "| what | value | target |",
        "|---|---|---|",
        (
            f"| Spearman(predicted, actual Dice), normal validation pairs (to atlas and between subjects) | "
            f"{result['spearman_normal_pairs']:.3f} (between subjects {result['spearman_between_subjects']:.3f}, to "
            f"atlas {result['spearman_to_atlas']:.3f}) | >= 0.5 |"
        ),
        (
            f"| failure detection AUROC ({result['num_failed']} failed of {result['num_registrations']}) | "
            f"{result['auroc_failure']:.3f} | >= 0.9 |"
        ),
        (
            f"| false warnings on normal validation pairs (threshold {threshold:.2f}) | "
            f"{100 * result['false_warnings_normal']:.1f}% | <= 5% |"
        ),
        "",
        "| perturbation of the moving scan | n | Dice before | Dice after | failed | warned | warned, of the failed |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, p in result["per_perturbation"].items():
        wf = "–" if p["warned_of_failed"] is None else f"{100 * p['warned_of_failed']:.0f}%"
        lines.append(
            f"| {name} | {p['n']} | {p['dice_before']:.3f} | {p['dice_after']:.3f} | {100 * p['failed']:.0f}% "
            f"| {100 * p['warned']:.0f}% | {wf} |"
        )
    return "\n".join(lines)


def figure(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    names = [NORMAL, *PERTURBATIONS, *COMMAND_NAMES]
    colours = plt.cm.tab10(np.linspace(0, 1, len(names)))
    for name, colour in zip(names, colours):
        rs = [r for r in records if r["perturbation"] == name]
        if rs:
            ax.scatter(
                [r["dice"] for r in rs],
                [r["failure_probability"] for r in rs],
                s=18,
                color=colour,
                marker="o" if name in (NORMAL, COMMAND) else "x",
                label=name,
            )
    ax.set_xlabel("actual mean Dice")
    ax.set_ylabel("estimated probability of failure")
    ax.set_title("validation registrations: the quality estimate (fitted on training subjects)")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def turned_header(scan: Path, degrees: float, out: Path, reference: Path | None = None) -> Path:
    """``scan`` with its header turned by ``degrees`` about the world S axis through the centre of ``reference``'s
    grid (default: its own; the voxels untouched): what a wrong orientation header does to a scan (and its labels)."""
    image = nib.load(scan)
    grid = nib.load(reference) if reference is not None else image
    centre = grid.affine @ np.r_[(np.asarray(grid.shape[:3]) - 1) / 2, 1.0]
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    turn[:3, 3] = centre[:3] - turn[:3, :3] @ centre[:3]
    turned = nib.Nifti1Image(np.asanyarray(image.dataobj), turn @ image.affine, image.header)
    turned.set_qform(turn @ image.affine, code=1)
    turned.set_sform(turn @ image.affine, code=1)
    nib.save(turned, out)
    return out


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


def native_cases(native_dir: Path, dataset_dir: Path, threads: int) -> list[dict]:
    """The whole command on each native scan, as it is and with a turned header; its quality estimate and Dice."""
    index = index_dataset(dataset_dir)
    rows = []
    with tempfile.TemporaryDirectory(prefix="failure_native_") as tmp:
        for scan in sorted(p for p in native_dir.glob("*.nii.gz") if not p.name.endswith("_labels.nii.gz")):
            sid = scan.name[: -len(".nii.gz")]
            labels = native_dir / f"{sid}_labels.nii.gz"
            for degrees in HEADER_TURNS:
                moving, moving_labels = turned_inputs(scan, labels if labels.is_file() else None, degrees, Path(tmp))
                out = Path(tmp) / f"{sid}_{degrees}"
                args = ["--moving", str(moving), "--fixed", str(index.atlas_image), "--out", str(out)]
                args += ["--threads", str(threads), "--quiet", "--no-qc", "--no-inverse"]
                if labels.is_file():
                    args += ["--moving-label", str(moving_labels), "--fixed-label", str(index.atlas_label)]
                done, _ = run_command("register", *args)
                summary = json.loads((out / "summary.json").read_text())
                dice, quality = summary["dice"] or {}, summary["quality"] or {}
                rows.append(
                    {
                        "scan": sid,
                        "header_turn_deg": degrees,
                        "dice": dice.get("mean"),
                        "dice_affine_only": dice.get("mean_affine_only"),
                        "predicted_dice": quality.get("predicted_dice"),
                        "failure_probability": quality.get("failure_probability"),
                        "warning": summary["warning"],
                        "printed": "warning:" in done.stderr,
                    }
                )
                print(
                    f"native {sid}, header turned {degrees} deg: Dice {rows[-1]['dice']}, predicted "
                    f"{rows[-1]['predicted_dice']}, failure probability {rows[-1]['failure_probability']}, "
                    f"{'WARNED' if rows[-1]['warning'] else 'no warning'}",
                    flush=True,
                )
    return rows


def native_markdown(rows: list[dict]) -> str:
    def num(v):
        return "–" if v is None else f"{v:.3f}"

    lines = [
        (
            "| native scan (whole command) | header turned | Dice (affine only) | predicted Dice | failure probability "
            "| warning |"
        ),
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scan']} | {r['header_turn_deg']} deg | {num(r['dice'])} ({num(r['dice_affine_only'])}) | "
            f"{num(r['predicted_dice'])} | {num(r['failure_probability'])} | {'yes' if r['warning'] else 'no'} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument("--train-subjects", type=int, default=None, help="use only the first N training subjects")
    ap.add_argument("--subjects", nargs="+", default=None, help="validation subjects (default: val_ids of train.yaml)")
    ap.add_argument("--records", type=Path, default=None, help="reuse the registrations of an earlier run's JSON")
    ap.add_argument("--fit", action="store_true", help="write the fitted model next to the weights")
    ap.add_argument(
        "--resume",
        action="store_true",
        help=f"reuse the registrations logged in OUT_DIR/{PARTIAL_LOG} by a run stopped part-way (module docstring)",
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    ap.add_argument(
        "--refine",
        type=int,
        default=None,
        metavar="N",
        help="refinement steps of the bundle-path registrations (default: evaluate.yaml's "
        "refine_iterations, the default path; the whole-command cases follow inference.yaml's)",
    )
    ap.add_argument(
        "--no-command-cases",
        dest="command_cases",
        action="store_false",
        help="leave out the whole-command registrations (module docstring)",
    )
    ap.add_argument(
        "--native-dir",
        type=Path,
        default=DEFAULT_NATIVE,
        help="native scans for the whole-command check (after --fit; absent: skipped)",
    )
    args = ap.parse_args(argv)
    if args.records is None and not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    torch.set_num_threads(args.threads)
    start = time.time()
    bundle_root = args.bundle_root.resolve()
    evaluate = bundle_parser(bundle_root, ["evaluate.yaml"], {"dataset_dir": str(args.dataset_dir.resolve())})
    model_file = (args.model_file or Path(evaluate.get_parsed_content("model_file"))).resolve()
    if args.records is not None:
        stored = json.loads(args.records.read_text())
        train_records, val_records = stored["train_records"], stored["val_records"]
        refinement_record = stored.get("refinement")
        if "entropy_calibration" not in stored:  # a guess would pair the features with another calibration, silently
            raise SystemExit(
                f"{args.records}: the records do not say which posterior calibration their entropy feature was "
                'computed with; add "entropy_calibration": {"std_scale": ..., "bias_fraction": ...} (that of the '
                "calibration sidecar when they were made)"
            )
        calibration = Calibration(**stored["entropy_calibration"])
        log = None  # the whole-command cases (records without them) are registered anew
    else:
        network = load_weights(evaluate.get_parsed_content("network_def", lazy=False), model_file, "cpu")
        calibration = calibration_for(model_file)
        refinement = evaluate.get_parsed_content("refinement")
        if args.refine is not None:
            refinement = dataclasses.replace(refinement, num_iterations=args.refine)
        print(
            f"registrations: the network's mean{' refined' if refinement.enabled else ''} "
            f"({refinement.num_iterations} refinement steps)",
            flush=True,
        )
        refinement_record = refinement.as_dict()
        val_ids = args.subjects or list(bundle_parser(bundle_root, ["train.yaml"]).get_parsed_content("val_ids"))
        index = index_dataset(args.dataset_dir)
        train_ids = [i for i in index.ids if i not in val_ids][: args.train_subjects]
        scans = load_scans(args.dataset_dir, train_ids + val_ids, int(evaluate.get_parsed_content("divisor")))
        log = RecordLog(
            args.out_dir / PARTIAL_LOG,
            {
                "weights_sha256": file_sha256(model_file),
                "refinement": refinement_record,
                "entropy_calibration": entropy_calibration_record(calibration),
                "train_ids": train_ids,
                "val_ids": val_ids,
                "seed": args.seed,
                "command_refine": args.refine,  # the whole-command cases: inference.yaml's refinement, or N steps of it
                "command_refinement": bundle_parser(bundle_root, ["inference.yaml"])
                .get_parsed_content("refinement")
                .as_dict(),
            },
            resume=args.resume,
        )
        if log.reused:
            print(f"resumed: {log.reused} registrations from {log.path}", flush=True)
        records = {}
        for split, ids, seed in (("train", train_ids, args.seed), ("val", val_ids, args.seed + 100_000)):
            cases = cases_for(ids, seed, training=split == "train")
            records[split] = logged_cases(
                split, cases, lambda case: run_case(network, calibration, scans, case, refinement), log
            )
        train_records, val_records = records["train"], records["val"]
        args.out_dir.mkdir(parents=True, exist_ok=True)  # the registrations first: a refit needs only these
        write_text(
            args.out_dir / "failure_detection.json",
            json.dumps(
                {
                    "model_file": str(model_file),
                    "refinement": refinement_record,
                    "entropy_calibration": entropy_calibration_record(calibration),
                    "train_records": train_records,
                    "val_records": val_records,
                }
            )
            + "\n",
        )
    if (
        args.command_cases
        and args.dataset_dir.is_dir()
        and not any(r["perturbation"] in COMMAND_NAMES for r in train_records)
    ):
        native_ids = (
            {p.name.split(".")[0] for p in args.native_dir.glob("*.nii.gz")} if args.native_dir.is_dir() else set()
        )
        identity = {
            r["moving"]: r["dice_identity"]
            for r in train_records + val_records
            if r["fixed"] == ATLAS_ID and r["perturbation"] == NORMAL
        }
        for records, seed in ((train_records, args.seed), (val_records, args.seed + 100_000)):
            ids = sorted({r["moving"] for r in records} - native_ids)
            records += command_cases(
                args.dataset_dir, ids, bundle_root, model_file, identity, seed, args.refine, calibration, log
            )
    fitted_on = sorted({r["moving"] for r in train_records})
    model = fit_quality_model(
        _features(train_records),
        [r["dice"] for r in train_records],
        [r["failed"] for r in train_records],
        fitted_on=fitted_on,
        refinement=refinement_record if refinement_record and refinement_record.get("num_iterations") else None,
        entropy_calibration=calibration,
    )
    train_result, result = score(model, train_records), score(model, val_records)
    table = markdown(result, model.threshold)
    print(table)
    print(
        f"(training registrations, the fit itself: AUROC {train_result['auroc_failure']:.3f}, Spearman normal "
        f"{train_result['spearman_normal_pairs']:.3f}, false warnings {100 * train_result['false_warnings_normal']:.1f}%)"
    )
    native = []
    if args.fit:
        print(f"wrote {save_quality_model(model, model_file)}")
        if args.native_dir.is_dir() and args.dataset_dir.is_dir():
            native = native_cases(args.native_dir, args.dataset_dir, args.threads)
            table += "\n\n" + native_markdown(native)
            print(native_markdown(native))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_text(
        args.out_dir / "failure_detection.json",
        json.dumps(
            {
                "model_file": str(model_file),
                "refinement": refinement_record,
                "entropy_calibration": entropy_calibration_record(calibration),
                "validation": result,
                "training_fit": train_result,
                "markdown": table,
                "native": native,
                "model": {k: v for k, v in model.__dict__.items()},
                "seconds": round(time.time() - start, 1),
                "train_records": train_records,
                "val_records": val_records,
            },
            indent=1,
        )
        + "\n",
    )
    figure(val_records, args.out_dir / "failure_detection.png")
    print(f"wrote {args.out_dir / 'failure_detection.json'} and failure_detection.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
