"""Does the quality estimate warn when a registration failed? Fit on training subjects, score on validation ones.

This script measures; ``python -m monai_probreg.fitting`` fits the quality model the weights ship with, on the same
training registrations and by the same fit (:mod:`monai_probreg.fitting.quality_fit`), which this script repeats
in-process on its training split before scoring the validation one.

Registrations (bundle path: evaluate.yaml's network, preprocessing and calibrated posterior, on the dataset grid):
- normal: every ordered pair of the validation subjects and each validation subject -> atlas (S01);
- the failure set (:mod:`monai_probreg.fitting.failure_set`): each validation subject, perturbed by each perturbation, onto the atlas and
  onto another validation subject (seeded).
The detector (:mod:`monai_probreg.uncertainty.quality`) is fitted on the same kinds of registrations of the
*training* subjects only (each to the atlas and to another training subject, each perturbed by every
perturbation onto the atlas or another training subject, and each onto itself and onto a near copy of itself:
:mod:`monai_probreg.fitting.self_cases`), never on a validation subject.
With refinement (evaluate.yaml's ``refine_iterations``, the default path; ``--refine N``), each registration's
features are those of the network's own registration and its Dice and "failed" those of the refined one
(:mod:`monai_probreg.uncertainty.quality`, "Whose features"); the refined one's features are kept as
``answer_features``; the whole-command cases do the same through the command.

The whole command path (on by default; ``--no-command-cases`` leaves it out): the features of a registration depend on its path
(the command line's affine stage undoes part of a wrong header, and its features are taken on the model grid behind
a brain mask), and a detector fitted on the bundle path alone passed a turned native header as normal for some
weights. So each subject (training ones for the fit, validation ones for the score; the native scans' subjects are
left out) also goes through the whole command (:mod:`monai_probreg.fitting.command_cases`) onto the atlas,
with its header as it is ("command") and turned by 90 and 180 degrees ("command_turn90", "command_turn180"). Its
"no registration" Dice is the bundle path's (same scan, same atlas grid); "before" is the command's affine-only Dice.

The native scans (``--native-dir``, default ``../shared/data/lpba40-native``) go through the whole command
(``monai-probreg register`` onto the atlas, affine stage included), as users bring them: as they are, and with their
orientation header turned by 90 and by 180 degrees about the S axis (the case that gave Dice 0.001 and no warning
before), with the sidecars next to the weights; reported with their Dice where they have labels, not part of the
scored set (a handful of cases).

A registration *failed* when its Dice is below the Dice before the deformable step or below no registration + 0.05
(on this path the moving scan is already affinely aligned, so both "before" Dice are the identity's). Reported:
Spearman(predicted, actual Dice) over the normal validation pairs (between subjects, to the atlas, both), AUROC of
the failure probability for "failed" over every validation registration, false warnings on the normal validation
pairs, and per perturbation: Dice before and after, the share that failed and the share warned.

    python benchmarks/failure_detection.py --threads 2 --train-subjects 12   # the table, JSON and figure in results/
    python benchmarks/failure_detection.py --records benchmarks/results/failure_detection.json  # re-scored, no registration

The registrations take one to two hours. Each one is logged as it ends (``OUT_DIR/failure_detection.partial.json``,
written atomically); ``--resume`` reuses the logged ones and registers only the rest, so a run stopped part-way goes on
where it stopped. A log made under other settings (weights, refinement, calibration, subjects, seed) is refused.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_NATIVE, DEFAULT_OUT, REPO, bundle_parser, run_command

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.fitting.command_cases import COMMAND, COMMAND_NAMES, HEADER_TURNS, turned_inputs
from monai_probreg.fitting.failure_set import PERTURBATIONS
from monai_probreg.fitting.quality_cases import NORMAL, RecordLog, load_scans, record_features
from monai_probreg.fitting.quality_fit import (
    VALIDATION_SEED_OFFSET,
    CommandSetup,
    fit_on_records,
    split_records,
    with_command_cases,
)
from monai_probreg.fitting.self_cases import SELF_NAMES
from monai_probreg.metrics.calibration import auroc, spearman
from monai_probreg.uncertainty.calibration import Calibration, calibration_for
from monai_probreg.uncertainty.quality import entropy_calibration_record
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.weights.loading import load_weights

PARTIAL_LOG = "failure_detection.partial.json"  # the registrations done so far, in OUT_DIR (--resume)


def score(model, records: list[dict]) -> dict[str, Any]:
    dice_hat, probability = model.predict(record_features(records))
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
    for name in [NORMAL, *PERTURBATIONS, *COMMAND_NAMES, *SELF_NAMES]:  # the self cases: training only
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
    """The benchmark; a log or records of other settings end it with their one-line reason."""
    try:
        return _main(argv)
    except InputError as err:
        raise SystemExit(str(err)) from None


def _main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument("--train-subjects", type=int, default=None, help="use only the first N training subjects")
    ap.add_argument("--subjects", nargs="+", default=None, help="validation subjects (default: val_ids of train.yaml)")
    ap.add_argument("--records", type=Path, default=None, help="reuse the registrations of an earlier run's JSON")
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
        help="native scans for the whole-command check (absent: skipped)",
    )
    args = ap.parse_args(argv)
    if args.records is None and not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the fitting's progress lines
    torch.set_num_threads(args.threads)
    start = time.time()
    bundle_root = args.bundle_root.resolve()
    evaluate = bundle_parser(bundle_root, ["evaluate.yaml"], {"dataset_dir": str(args.dataset_dir.resolve())})
    model_file = (args.model_file or Path(evaluate.get_parsed_content("model_file"))).resolve()
    native_ids = {p.name.split(".")[0] for p in args.native_dir.glob("*.nii.gz")} if args.native_dir.is_dir() else set()
    command = None  # the whole-command cases (module docstring), but of the native scans' subjects
    if args.command_cases and args.dataset_dir.is_dir():
        command = CommandSetup(args.dataset_dir, bundle_root, model_file, args.refine, frozenset(native_ids))
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
            refinement = refinement.with_fields(num_iterations=args.refine)
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
        train_records, val_records = (
            split_records(split, ids, seed, network, calibration, scans, refinement, log, command)
            for split, ids, seed in (
                ("train", train_ids, args.seed),
                ("val", val_ids, args.seed + VALIDATION_SEED_OFFSET),
            )
        )
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
    if command is not None and not any(r["perturbation"] in COMMAND_NAMES for r in train_records):  # old records
        train_records, val_records = (
            with_command_cases(records, seed, command, calibration, training=training)
            for records, seed, training in (
                (train_records, args.seed, True),
                (val_records, args.seed + VALIDATION_SEED_OFFSET, False),
            )
        )
    model = fit_on_records(train_records, refinement_record, calibration)  # as python -m monai_probreg.fitting fits
    train_result, result = score(model, train_records), score(model, val_records)
    table = markdown(result, model.threshold)
    print(table)
    print(
        f"(training registrations, the fit itself: AUROC {train_result['auroc_failure']:.3f}, Spearman normal "
        f"{train_result['spearman_normal_pairs']:.3f}, false warnings {100 * train_result['false_warnings_normal']:.1f}%)"
    )
    native = []
    if args.native_dir.is_dir() and args.dataset_dir.is_dir():  # the sidecars next to the weights, as users run them
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
