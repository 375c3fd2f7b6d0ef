"""How far the UNet's arithmetic moves the local-NCC warning rule: the margin of ``LNCC_DROP_MARGIN``.

The quality estimate warns when the deformable step lowered the local NCC of the pair
(:mod:`monai_probreg.uncertainty.quality`). With no margin, a registration that changes almost nothing (a scan onto a
near copy of itself) sits on the rule's edge, and bf16 rounding of the UNet (the default on CPUs with native bf16)
decides whether it warns: the same registration warned on one machine and not on another. This measures, on the
bundle path (evaluate.yaml's network and calibration, the dataset grid), in bf16 and in fp32:

- the normal validation pairs (every ordered pair of the validation subjects, each onto the atlas S01): the local
  NCC before and after, the smallest gain, and how much lncc_after moves between the two precisions;
- the self pairs (each validation subject and the atlas onto itself): the rule's edge, where nothing is to be done.

The margin must sit well above the precision's effect (so the rule says the same in both) and well below the drops
of the failure set (``benchmarks/failure_detection.py``'s records in benchmarks/results, checked here when present).

    PYTHONPATH=benchmarks python experiments/lncc_margin.py --threads 2   # -> experiments/results/lncc_margin.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_DATASET, DEFAULT_OUT, REPO
from uncertainty_calibration import validation_model

from monai_probreg.data.pairs import ATLAS_ID
from monai_probreg.fitting.quality_cases import NORMAL, cases_for, load_scans, run_case
from monai_probreg.uncertainty.calibration import calibration_for
from monai_probreg.uncertainty.quality import LNCC_DROP_MARGIN
from monai_probreg.utils.files import write_text

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
PRECISIONS = ("bf16", "fp32")


def lncc_records(network, calibration, scans: dict, cases: list[dict]) -> list[dict]:
    """lncc_before / lncc_after of each case in each precision of :data:`PRECISIONS`."""
    out = []
    for case in cases:
        row = {"moving": case["moving"], "fixed": case["fixed"]}
        for precision in PRECISIONS:
            network.unet_precision = precision
            features = run_case(network, calibration, scans, case)["features"]
            row[precision] = {"lncc_before": features["lncc_before"], "lncc_after": features["lncc_after"]}
        out.append(row)
        print(
            f"{row['moving']} -> {row['fixed']}: lncc {row['fp32']['lncc_before']:.4f} -> "
            f"{row['fp32']['lncc_after']:.4f} (fp32), {row['bf16']['lncc_after']:.4f} (bf16)",
            flush=True,
        )
    return out


def summarise(normal: list[dict], self_pairs: list[dict], failure_drops: list[float], margin: float) -> dict:
    def drop(r, p):
        return r[p]["lncc_before"] - r[p]["lncc_after"]

    shift = [abs(r["bf16"]["lncc_after"] - r["fp32"]["lncc_after"]) for r in normal + self_pairs]
    return {
        "margin": margin,
        "normal_smallest_gain": {p: float(min(-drop(r, p) for r in normal)) for p in PRECISIONS},
        "normal_warned": {p: int(sum(drop(r, p) > margin for r in normal)) for p in PRECISIONS},
        "precision_shift_of_lncc_after": {"max": float(max(shift)), "median": float(np.median(shift))},
        "self_pair_drop": {p: [float(drop(r, p)) for r in self_pairs] for p in PRECISIONS},
        "self_pairs_disagreeing": int(
            sum((drop(r, "bf16") > margin) != (drop(r, "fp32") > margin) for r in self_pairs)
        ),
        "failure_set_positive_drops_below_margin": int(sum(0 < d <= margin for d in failure_drops)),
        "failure_set_positive_drops": len([d for d in failure_drops if d > 0]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bundle-root", type=Path, default=REPO / "bundle")
    ap.add_argument("--model-file", type=Path, default=None, help="weights (default: evaluate.yaml's model_file)")
    ap.add_argument("--subjects", nargs="+", default=None, help="validation subjects (default: val_ids of train.yaml)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not args.dataset_dir.is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    torch.set_num_threads(args.threads)
    start = time.time()
    evaluate, model_file, network, val_ids = validation_model(args)  # the shared loading of the validation benchmarks
    calibration = calibration_for(model_file)
    scans = load_scans(args.dataset_dir, val_ids, int(evaluate.get_parsed_content("divisor")))
    normal = [c for c in cases_for(val_ids, 0, training=False) if c["perturbation"] == NORMAL]
    self_cases = [{"moving": s, "fixed": s, "perturbation": NORMAL, "seed": 0} for s in [*val_ids, ATLAS_ID]]
    normal_rows = lncc_records(network, calibration, scans, normal)
    self_rows = lncc_records(network, calibration, scans, self_cases)
    stored = DEFAULT_OUT / "failure_detection.json"
    failure_drops = []
    if stored.is_file():
        records = json.loads(stored.read_text())
        failure_drops = [
            r["features"]["lncc_before"] - r["features"]["lncc_after"]
            for r in records.get("train_records", []) + records.get("val_records", [])
            if r["failed"]
        ]
    summary = summarise(normal_rows, self_rows, failure_drops, LNCC_DROP_MARGIN)
    print(json.dumps(summary, indent=1))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_text(
        args.out_dir / "lncc_margin.json",
        json.dumps(
            {
                "model_file": str(model_file),
                "summary": summary,
                "seconds": round(time.time() - start, 1),
                "normal": normal_rows,
                "self_pairs": self_rows,
            },
            indent=1,
        )
        + "\n",
    )
    print(f"wrote {args.out_dir / 'lncc_margin.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
