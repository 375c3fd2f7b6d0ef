"""How long the bundle's uncertainty maps take for one pair, this tree side by side with another source.

The bundle's writer (``engines/handlers.py``) makes, per pair, the map the calibration's term reads (the error model's
prediction since bundle 0.33.0, the registered pair's residual before: ``uncertainty.error_model.pair_term``) and
:func:`~monai_probreg.uncertainty.posterior_maps.posterior_maps` with K posterior samples: the displacement std (first
order since bundle 0.34.0: no sample drawn; the std of the K samples before), and the label entropy of the K samples
when the moving labels are given (drawn as the writer draws them: since bundle 0.35.0 Student-t with the
calibration's ``interval_dof``). On each LPBA40 validation pair
(``refinement_speed.PAIRS``, the aligned 160 x 192 x 160 grid; the network's registration refined as the bundle
refines it, untimed) both are timed: "std" (``displacement_std`` alone) and "std + label entropy", after one untimed
warm-up, as the writer calls them with the weights' calibration, freed memory kept for reuse as the bundle's
inference keeps it (``reuse_cpu_memory``; ``--no-memory-reuse``: glibc's defaults).

``--baseline-source DIR`` times the same calls by the ``monai_probreg`` package under DIR (a ``git worktree`` of an
earlier commit) with that checkout's own bundle (weights, calibration: a calibration is fitted for its package's
form of the residual, and a package refuses one of another form): every round runs this tree and the baseline each in
a fresh process, one after the other, so a slow moment of the machine hits both; each pair's median over the rounds
is reported, and the ratio.

    python benchmarks/maps_speed.py --threads 2                   # table + benchmarks/results/maps_speed.json
    git worktree add /tmp/base 6006ade
    python benchmarks/maps_speed.py --threads 2 --baseline-source /tmp/base
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from common import DEFAULT_DATASET, DEFAULT_OUT, write_report

from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES

KINDS = ("std", "std + label entropy")


def time_maps(dataset: Path, samples: int, threads: int, memory_reuse: bool = True) -> dict:
    """In this process: {pair: {kind: seconds}} of one timed call each after a warm-up, and where the package
    was imported from."""
    import torch
    from refinement_speed import PAIRS, load_pair

    import monai_probreg
    from monai_probreg.engines.refinement import refine_registration
    from monai_probreg.engines.registration import register_pair
    from monai_probreg.registration.model import load_model
    from monai_probreg.uncertainty.posterior_maps import posterior_maps
    from monai_probreg.uncertainty.residual import residual_variance

    try:  # the term's one rule since bundle 0.33.0 (the error model's prediction, or the residual)
        from monai_probreg.uncertainty.error_model import pair_term
    except ImportError:  # an earlier checkout (--baseline-source): its term read the residual
        pair_term = None
    from monai_probreg.utils.memory import reuse_freed_memory

    torch.set_num_threads(threads)
    reuse_freed_memory(memory_reuse)  # on: as inference.yaml runs (reuse_cpu_memory: true) and the command
    # the bundle of the checkout the package comes from (this tree's, or the baseline's: its sidecars are its own)
    model = load_model(Path(monai_probreg.__file__).resolve().parents[1] / "bundle", quality=False)
    calibration = model.calibration
    times: dict[str, dict[str, float]] = {}
    for pair in PAIRS:
        moving, fixed, moving_label, _ = load_pair(dataset, pair)
        with torch.no_grad():
            output = register_pair(model.network, moving, fixed)
        refined = refine_registration(model.network, moving, fixed, output, model.refinement)

        def maps(label):
            with torch.inference_mode():
                residual = None
                if calibration.residual_weight > 0 and pair_term is None:
                    residual = residual_variance(refined.warped, fixed, refined.velocity_mean.shape[2:])
                elif calibration.residual_weight > 0:
                    pair = (
                        refined.warped,
                        fixed,
                        refined.velocity_mean,
                        refined.velocity_log_var,
                        refined.displacement,
                    )
                    residual = pair_term(calibration.error_model, *pair)
                return posterior_maps(
                    model.network,
                    refined.velocity_mean,
                    refined.velocity_log_var,
                    refined.displacement.shape[2:],
                    samples,
                    calibration.std_scale,
                    label,
                    0,
                    calibration.bias_fraction,
                    residual=residual,
                    residual_weight=calibration.residual_weight,
                    **gain,
                )

        # the samples' gain since bundle 0.34.0 (the std map first order), their Student-t since 0.35.0: as the writer
        # passes them (engines/handlers.py); an older checkout's maps take neither
        accepted = inspect.signature(posterior_maps).parameters
        gain = {k: getattr(calibration, k) for k in ("sample_gain", "interval_dof") if k in accepted}
        maps(moving_label)  # warm-up
        times[pair] = {}
        for kind, label in zip(KINDS, (None, moving_label)):
            start = time.perf_counter()
            maps(label)
            times[pair][kind] = time.perf_counter() - start
    return {"times": times, "package": str(Path(monai_probreg.__file__).parent), "version": monai_probreg.__version__}


def run_worker(source: Path | None, args: argparse.Namespace) -> dict:
    """:func:`time_maps` in a fresh process importing ``monai_probreg`` from ``source`` (None: as installed)."""
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(source)] + [p for p in [env.get("PYTHONPATH")] if p])
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "times.json"
        cmd = [sys.executable, __file__, "--worker", str(out), "--dataset-dir", str(args.dataset_dir)]
        cmd += ["--samples", str(args.samples), "--threads", str(args.threads)]
        cmd += ["--no-memory-reuse"] if args.no_memory_reuse else []
        subprocess.run(cmd, check=True, env=env)
        result = json.loads(out.read_text())
    if source is not None and not Path(result["package"]).resolve().is_relative_to(source.resolve()):
        raise SystemExit(f"--baseline-source {source}: monai_probreg was imported from {result['package']} instead")
    return result


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-dir", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--samples", type=int, default=POSTERIOR_SAMPLES)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-memory-reuse", action="store_true", help="glibc's defaults (reuse_cpu_memory: false)")
    ap.add_argument("--baseline-source", type=Path, default=None, help="a checkout whose monai_probreg to time too")
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)  # internal: one process's timings
    args = ap.parse_args(argv)
    if not (args.dataset_dir / "images").is_dir():
        print(f"skipped: dataset not found at {args.dataset_dir}")
        return 0
    if args.worker is not None:
        args.worker.write_text(
            json.dumps(time_maps(args.dataset_dir, args.samples, args.threads, not args.no_memory_reuse))
        )
        return 0
    if args.baseline_source is not None and not (args.baseline_source / "monai_probreg").is_dir():
        raise SystemExit(f"--baseline-source {args.baseline_source}: no monai_probreg package there")
    sources = {"this tree": None}
    if args.baseline_source is not None:
        sources["baseline"] = args.baseline_source
    runs: dict[str, list[dict]] = {name: [] for name in sources}
    for round_index in range(args.rounds):
        for name, source in sources.items():
            runs[name].append(run_worker(source, args))
            print(f"round {round_index + 1}/{args.rounds}: {name} done", flush=True)
    pairs = list(runs["this tree"][0]["times"])
    medians = {
        name: {
            pair: {kind: statistics.median(r["times"][pair][kind] for r in results) for kind in KINDS} for pair in pairs
        }
        for name, results in runs.items()
    }
    lines = ["| source (version) | " + " | ".join(f"{kind}, s per pair (median)" for kind in KINDS) + " |"]
    lines.append("|---|" + "---|" * len(KINDS))
    for name, per_pair in medians.items():
        cells = [statistics.median(per_pair[p][kind] for p in pairs) for kind in KINDS]
        version = runs[name][0]["version"]
        lines.append(f"| {name} ({version}) | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    if "baseline" in medians:
        ratios = [
            statistics.median(medians["baseline"][p][kind] / medians["this tree"][p][kind] for p in pairs)
            for kind in KINDS
        ]
        lines.append("| baseline / this tree | " + " | ".join(f"{r:.2f}x" for r in ratios) + " |")
    result = {
        "samples": args.samples,
        "rounds": args.rounds,
        "threads": args.threads,
        "memory_reuse": not args.no_memory_reuse,
        "pairs": pairs,
        "medians_s": medians,
        "runs": runs,
        "sources": {name: runs[name][0]["package"] for name in sources},
    }
    write_report(args.out_dir, "maps_speed", result, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
