"""Another contrast: a T2-like scan onto a T1-like one, our refinement's image terms against ANTs SyN (Mattes MI), side
by side in one run.

Pairs are rendered from two whole-head label maps (SynthSeg's ``training_seg_11`` and ``_12`` by default: no
training run saw them): for each seed, each map deformed by a random smooth diffeomorphism
(``generalization.synthetic_head``), the moving one rendered T2-like
(:data:`~monai_probreg.data.label_synthesis.T2_LIKE`: fluid bright, white matter dark) and the fixed one T1-like, each
onto the other; as whole heads (skull and scalp kept, each at a random intensity per head) and as skull-stripped brains
(SynthSeg's labels from 500 on removed); ``--kinds head-onto-brain``: whole moving heads onto skull-stripped fixed
brains (a clinical scan onto a stripped template such as MNI152). ``--same-contrast`` adds the T1-like moving images of the same pairs (what
the cross-contrast path must not change). Rows, each through the code path a user runs (``register --fixed`` with
labels, the bundle's settings):

- "--contrast same": the shipped refinement as ``register`` runs it by default;
- "--contrast other": the refinement with the config's ``other_contrast`` fields, as ``register --contrast other``
  runs it (no pull towards the network's mean);
- "--contrast other --match-contrast": the same, the moving image first mapped onto the fixed one's contrast (the
  config's ``contrast_match_bins``, :mod:`monai_probreg.spatial.contrast`);
- ``--refined-variants NAME=FIELD:VALUE,...``: more rows, the shipped settings with fields replaced (e.g.
  ``image_loss:mind,image_weight:100``: MIND-SSC descriptors, :mod:`monai_probreg.losses.mind`;
  ``contrast_match_bins:N``: the moving image mapped onto the fixed one's contrast over N bins, default 0: not);
- "ANTs SyN": ``ants.registration(fixed, moving, type_of_transform="SyN")``, antspyx defaults (Mattes MI for the
  affine and the SyN stages), whole (read, register, resample, write).

Scores: mean Dice over FreeSurfer's aseg structures, folded voxels, the command's warnings (the quality estimate's,
in ``summary.json``; "–" where none is made: ``--contrast other``, and ANTs).

    python benchmarks/cross_contrast.py --label-maps SynthSeg/data/training_label_maps --threads 2

Prints one table and writes ``OUT_DIR/cross_contrast.json``; without the label maps it prints "skipped: ..." and exits
0. The ``other_contrast`` settings were chosen on maps 01-02 (``--maps training_seg_01 training_seg_02``), never 11-12.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from common import parse_variant
from generalization import ants_whole, command_options, dice, synthetic_head

from monai_probreg.data.label_synthesis import ASEG_LABELS, T1_LIKE, T2_LIKE
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.scan import register_scan
from monai_probreg.spatial.volume_io import read_label
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import library_versions

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "results"
MAPS = ("training_seg_11", "training_seg_12")  # never in a training run (train_synth.yaml uses 01-10)
SEEDS = (0,)
# a row's fields that are the registration's options, not RefinementSettings' (_options)
OPTION_FIELDS = ("contrast", "contrast_match_bins", "affine_local")
KINDS = (
    "head",
    "brain",
    "head-onto-brain",
)  # both whole heads; both skull-stripped; a whole head onto a stripped brain
DEFAULT_KINDS = ("head", "brain")
ANTS_CALL = 'ants.registration(fixed, moving, type_of_transform="SyN")'


def run(args: argparse.Namespace, rows_options: dict[str, dict]) -> dict:
    model = load_model()
    if not args.variants_only:
        other = {**model.other_contrast, "contrast": "other"}
        matched = {**other, "contrast_match_bins": model.contrast_match_bins}
        rows_options = {
            "--contrast same": {},
            "--contrast other": other,
            "--contrast other --match-contrast": matched,
            **rows_options,
        }
    paths = [args.label_maps / f"{m}.nii.gz" for m in args.maps]
    contrasts = {"T2->T1": T2_LIKE} | ({"T1->T1": T1_LIKE} if args.same_contrast else {})
    cases: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="cross_contrast_") as tmp:
        root = Path(tmp)
        for seed in args.seeds:
            for kind in args.kinds:
                folder = root / f"{kind}_{seed}"
                folder.mkdir()
                fixed_heads = [synthetic_head(p, seed, folder, T1_LIKE, kind != "head") for p in paths]
                for contrast, table in contrasts.items():
                    sub = folder / contrast.replace("->", "_")
                    sub.mkdir()
                    moving_heads = [synthetic_head(p, seed, sub, table, kind == "brain") for p in paths]
                    for i, j in ((0, 1), (1, 0)):
                        (moving, moving_label), (fixed_image, fixed_label) = moving_heads[i], fixed_heads[j]
                        case = {
                            "pair": f"{args.maps[i]}->{args.maps[j]}",
                            "seed": seed,
                            "kind": kind,
                            "contrast": contrast,
                            "rows": {},
                        }
                        target = read_label(fixed_label).array
                        fixed = prepare_fixed(fixed_image, fixed_label)
                        for row, fields in rows_options.items():
                            out = sub / f"{i}{j}_{row.replace(' ', '_')}"
                            start = time.perf_counter()
                            summary = register_scan(
                                model, fixed, moving, out, moving_label, _options(model, fields, seed)
                            )
                            case["rows"][row] = {
                                "dice": dice(read_label(out / "warped_label.nii.gz").array, target, ASEG_LABELS),
                                "num_folding": int(summary["jacobian"]["num_nonpositive"]),
                                "seconds": round(time.perf_counter() - start, 2),
                            }
                            if summary["quality_not_estimated"] is None:  # else no "warning": no estimate to warn
                                case["rows"][row]["warning"] = summary.get("warning") or ""
                        if args.ants:
                            out = sub / f"{i}{j}_ants"
                            out.mkdir()
                            record = ants_whole(fixed_image, moving, moving_label, out)
                            record["dice"] = dice(read_label(out / "warped_label.nii.gz").array, target, ASEG_LABELS)
                            case["rows"]["ANTs SyN"] = record
                        print(
                            f"[{kind} {contrast} seed {seed}] {case['pair']}: "
                            + ", ".join(f"{k} {v['dice']:.3f}" for k, v in case["rows"].items()),
                            flush=True,
                        )
                        cases.append(case)
    return {"cases": cases, "summary": summarise(cases), "rows": rows_options}


def _options(model, fields: dict, seed: int) -> RegistrationOptions:
    """The command's options for a row: its RefinementSettings fields replaced, and the fields of
    :data:`OPTION_FIELDS` that are not the refinement's when the row gives them: ``contrast_match_bins`` (the moving
    image mapped onto the fixed one's contrast, 0 = not), ``contrast`` ("other": no quality estimate and the affine
    stage's local step, as ``--contrast other`` runs; default "same") and ``affine_local`` (``--affine-local``:
    ``AffineSettings.local_stage``; default the settings')."""
    fields = dict(fields)
    bins = int(fields.pop("contrast_match_bins", 0))
    contrast = str(fields.pop("contrast", "same"))
    local = fields.pop("affine_local", None)
    options = dataclasses.replace(command_options(model, fields, seed), contrast_match_bins=bins, contrast=contrast)
    if local is None:
        return options
    return dataclasses.replace(options, affine=dataclasses.replace(options.affine, local_stage=str(local)))


def summarise(cases: list[dict]) -> dict:
    """Per (kind, contrast) and row: mean Dice, folded voxels, warned pairs (None for a row without a quality
    estimate: ANTs, --contrast other), pairs."""
    out: dict[str, dict] = {}
    for case in cases:
        group = out.setdefault(f"{case['kind']} {case['contrast']}", {})
        for row, record in case["rows"].items():
            entry = group.setdefault(row, {"dice": [], "num_folding": 0, "warned": 0 if "warning" in record else None})
            entry["dice"].append(record["dice"])
            entry["num_folding"] += int(record.get("num_folding", 0))
            if entry["warned"] is not None:  # ANTs and --contrast other have no quality estimate: None
                entry["warned"] += int(bool(record.get("warning")))
    for group in out.values():
        for entry in group.values():
            entry["pairs"] = len(entry["dice"])
            entry["dice"] = float(np.mean(entry["dice"]))
    return out


def markdown(result: dict) -> str:
    lines = ["| images | method | mean Dice | folded voxels | warned pairs |", "|---|---|---|---|---|"]
    for group, rows in result["summary"].items():
        for row, entry in rows.items():
            lines.append(
                f"| {group} | {row} | {entry['dice']:.4f} | {entry['num_folding']} | "
                + ("– |" if entry["warned"] is None else f"{entry['warned']} of {entry['pairs']} |")
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label-maps", type=Path, default=None, help="folder with SynthSeg's training_seg_*.nii.gz")
    ap.add_argument("--maps", nargs=2, default=list(MAPS), help="the two label maps' stems (default: %(default)s)")
    ap.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    ap.add_argument(
        "--kinds",
        nargs="+",
        choices=KINDS,
        default=list(DEFAULT_KINDS),
        help="whole heads, skull-stripped brains, or whole moving heads onto stripped fixed brains (default: %(default)s)",
    )
    ap.add_argument("--same-contrast", action="store_true", help="also the T1-like moving images of the same pairs")
    ap.add_argument(
        "--refined-variants",
        nargs="+",
        default=[],
        metavar="NAME=FIELD:VALUE,...",
        help="more rows, the shipped refinement with RefinementSettings fields replaced, and the options' "
        "contrast:same|other, contrast_match_bins:N, affine_local:never|other-contrast|always",
    )
    ap.add_argument(
        "--variants-only", action="store_true", help="only the --refined-variants rows (and ANTs): no --contrast rows"
    )
    ap.add_argument("--no-ants", dest="ants", action="store_false", help="leave ANTs SyN out")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    paths = [args.label_maps / f"{m}.nii.gz" for m in args.maps] if args.label_maps else []
    if not paths or not all(p.is_file() for p in paths):
        print(f"skipped: no {args.maps} in {args.label_maps} (git clone https://github.com/BBillot/SynthSeg)")
        return 0
    rows_options: dict[str, dict] = {}
    for name, fields in (parse_variant(v) for v in args.refined_variants):
        try:
            RefinementSettings(**{k: v for k, v in fields.items() if k not in OPTION_FIELDS})
            _options(SimpleNamespace(refinement=RefinementSettings()), fields, 0)  # the other fields' values
        except (TypeError, ValueError) as err:
            raise SystemExit(f"--refined-variants {name!r}: {err}") from None
        rows_options[name] = fields
    torch.set_num_threads(args.threads)
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)
    if args.ants:
        try:
            import ants  # noqa: F401
        except ImportError as err:
            print(f"ANTs SyN skipped: antspyx not importable ({err}); pip install -e '.[bench]'", flush=True)
            args.ants = False
    start = time.perf_counter()
    result = run(args, rows_options)
    result["config"] = {
        "maps": list(args.maps),
        "seeds": list(args.seeds),
        "kinds": list(args.kinds),
        "rows": result.pop("rows"),
        "ants": ANTS_CALL if args.ants else None,
        "threads": args.threads,
        "seconds": round(time.perf_counter() - start, 1),
        "versions": library_versions(),
        "command": " ".join(["python", "benchmarks/cross_contrast.py", *sys.argv[1:]]),
    }
    table = markdown(result)
    print(table)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_text(args.out_dir / "cross_contrast.json", json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
