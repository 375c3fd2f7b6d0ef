"""``monai-probreg``: register raw 3-D scans to an atlas from the command line.

Subcommands ``register`` (one scan), ``register-batch`` (many scans, model and atlas loaded once) and ``demo`` (a
synthetic subject with a known answer, :mod:`monai_probreg.registration.demo`); the work is
:func:`monai_probreg.registration.scan.register_scan`. Exit status: 0 on success; 1 with one line
``monai-probreg: error: ...`` on stderr when an input or the registration fails (for a batch: when any scan
failed); 2 for command-line usage errors (argparse).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import textwrap
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from monai_probreg.registration.output_files import output_list

__all__ = ["build_parser", "main", "run", "run_bundle_demo"]

# the outputs by name; what each is, once, in monai_probreg.registration.output_files (DIR/README.txt)
_OUTPUTS = textwrap.fill(
    "Outputs, each described in DIR/README.txt: " + ", ".join(output_list()) + ".",
    width=118,
    break_long_words=False,
    break_on_hyphens=False,
)

DESCRIPTION = f"""\
Register 3-D brain MRI scans to an atlas with the trained VoxelMorph-diff model (Dalca et al. 2018): affine
pre-alignment (rigid then affine, Mattes mutual information; in torch, or ITK's with --affine-backend itk), then the
network's diffeomorphic deformation, composed into one transform. Scans may come in any orientation, voxel size,
field of view and intensity range; they should be skull-stripped T1-weighted brains, like the atlas.

  monai-probreg demo --out demo          # a synthetic subject with a known answer: is the install right?
  monai-probreg register --moving sub01.nii.gz --fixed atlas.nii.gz --out results/sub01
  monai-probreg register --moving sub01.nii.gz --moving-label sub01_seg.nii.gz \\
      --fixed atlas.nii.gz --fixed-label atlas_seg.nii.gz --samples 16 --out results/sub01
  monai-probreg register-batch --moving scans/ --fixed atlas.nii.gz --out results/
  monai-probreg register --moving sub01.nii.gz --fixed atlas.nii.gz --initial-transform sub01_0GenericAffine.mat \\
      --initial-transform-use as-affine --out results/sub01    # ANTs' affine (-r): as it is, or as a start

{_OUTPUTS}

The model (network settings and weights) comes from the MONAI bundle: BUNDLE/configs/inference.yaml and
the config's model_file (BUNDLE/models/...), BUNDLE being the repository's bundle/ folder unless --bundle-root, --config or --model-file
say otherwise. Without --fixed, scans are registered to the MNI ICBM152 2009a T1 template that nilearn ships inside
its package (skull-stripped, 1 mm; licence notice in monai_probreg/data/template.py).

Exit status: 0 on success; 1 with one line "monai-probreg: error: ..." when an input or the registration fails
(nothing is written to DIR; for register-batch, when any scan failed); 2 for a malformed command line.
"""


def _add_common(parser: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The options every registering subcommand has; returns the "registration" group, for options of some."""
    io = parser.add_argument_group("inputs and outputs")
    io.add_argument(
        "--fixed",
        metavar="F",
        help="the atlas / fixed image (default: the MNI ICBM152 2009a T1 template that nilearn ships)",
    )
    io.add_argument(
        "--fixed-label",
        metavar="L",
        help="its label map (integers, same grid): enables Dice and fixed_label_in_moving.nii.gz",
    )
    io.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output folder (created; must be empty or absent unless --overwrite)",
    )
    io.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier run in DIR")
    reg = parser.add_argument_group("registration")
    reg.add_argument(
        "--samples",
        type=int,
        default=0,
        metavar="K",
        help="write the displacement std map: K >= 2 (0 = none, default); the map is first order, no sample is "
        "drawn, so every K >= 2 gives the same map",
    )
    reg.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the affine stage's metric sampling (default 0); the same inputs, options and seed "
        "give the same outputs",
    )
    reg.add_argument(
        "--raw-uncertainty",
        action="store_true",
        help="entropy and std maps of the raw variational "
        "posterior (default: calibrated by the weights' <stem>.calibration.json)",
    )
    reg.add_argument(
        "--no-affine",
        action="store_true",
        help="skip the affine pre-alignment (scans already aligned to the fixed image)",
    )
    reg.add_argument("--rigid-only", action="store_true", help="pre-align with 6 parameters (no scaling/shear)")
    reg.add_argument(
        "--affine-backend",
        choices=("torch", "itk"),
        default="torch",
        help="who runs the pre-alignment: torch (default: 2-4 s, the same result every run) or ITK's "
        "v4 registration as antsRegistration (10-20 s, plus about 7 s to load its modules)",
    )
    reg.add_argument(
        "--affine-levels",
        type=int,
        nargs="+",
        default=None,
        metavar="S",
        help="shrink factor of each pre-alignment level, coarse to fine, smoothed by S/2 mm (default: "
        "torch 4 2 1, itk 4 2)",
    )
    reg.add_argument(
        "--affine-iterations",
        type=int,
        nargs="+",
        default=None,
        metavar="N",
        help="iterations per level, for each of the rigid and affine stages (default: torch at most 30 15 0 "
        "rigid and 30 15 10 affine, itk at most 100 50; with other --affine-levels: the first of these)",
    )
    reg.add_argument(
        "--affine-sampling",
        type=float,
        default=None,
        metavar="P",
        help="fraction of each level's voxels sampled by the mutual information metric (default: torch 0.05, itk 0.2)",
    )
    reg.add_argument(
        "--affine-max-samples",
        type=int,
        default=None,
        metavar="N",
        help="with the torch backend: at most N sample points per level (default 50000; 0 = no cap, "
        "5%% of the full-resolution level is about 245000 points for the same alignment)",
    )
    reg.add_argument(
        "--affine-local",
        choices=("never", "other-contrast", "always"),  # spatial.affine_settings.LOCAL_STAGE (--help stays light)
        default="other-contrast",  # AffineSettings.local_stage
        help="refine the pre-alignment by the squared local correlation (ANTs' CC) after mutual information: "
        "for a pair of two contrasts (--contrast other; default), always, or never (mutual information can prefer "
        "a shrunken head when a head of one contrast meets a skull-stripped brain of another)",
    )
    reg.add_argument(
        "--nondeterministic-affine",
        action="store_true",
        help="with --affine-backend itk: multi-threaded mutual information, faster on many cores, but "
        "ITK then sums in thread order and two runs differ slightly (default: one work unit, the "
        "same result every run; the torch backend is reproducible with any number of threads)",
    )
    reg.add_argument(
        "--brain-mask-margin",
        type=float,
        default=None,
        metavar="MM",
        help="after the affine, hide the moving scan outside the fixed image's non-background voxels "
        "dilated by MM (a skull-stripped template against a whole head); default 3",
    )
    reg.add_argument(
        "--no-brain-mask",
        action="store_true",
        help="show the network the whole moving scan (both images skull-stripped, or both not)",
    )
    reg.add_argument(
        "--refine",
        type=int,
        default=None,
        metavar="N",
        help="refine the posterior mean for this pair with N optimiser steps (test-time refinement: "
        "about 5 s for the demo on a 2-core CPU); default: the config's refine_iterations (20: on); 0 = the "
        "network alone",
    )
    reg.add_argument(
        "--smoothness",
        type=float,
        default=None,
        metavar="S",
        help="multiply the refinement's smoothness prior (the config's refine_prior_lambda) by S: above 1 a smoother "
        "warp, below 1 a sharper one that follows the images more closely (docs/cli.md, its effect on LPBA40); "
        "default 1; needs the refinement (not --refine 0)",
    )
    reg.add_argument(
        "--contrast",
        choices=("same", "other"),  # registration.options.CONTRASTS (not imported here: --help stays light)
        default="same",
        help="same (default): both scans of one contrast (or contrasts a local correlation relates, e.g. two "
        "T1-weighted scanners); other: a T2-weighted or FLAIR scan onto a T1-weighted atlas or template, the "
        "refinement then follows the images without the pull towards the network's estimate, which was trained on "
        "pairs of one contrast (the config's other_contrast settings; docs/cli.md), and no quality estimate is made "
        "(its models were fitted on pairs of one contrast); needs the refinement (not --refine 0)",
    )
    reg.add_argument(
        "--match-contrast",
        action="store_true",
        help="with --contrast other, for skull-stripped brains: map the moving scan's intensities onto the fixed "
        "image's contrast (each to the mean fixed intensity of the voxels that have it, after the affine stage; the "
        "config's contrast_match_bins) before the network, the refinement and the quality estimate read it. On "
        "whole heads, whose skin, fat and bone share the brain's intensities, it lowered Dice (docs/cli.md)",
    )
    reg.add_argument("--no-qc", action="store_true", help="do not draw qc.png")
    reg.add_argument(
        "--no-inverse",
        action="store_true",
        help="do not compute or write inverse_warp.nii.gz and "
        "fixed_label_in_moving.nii.gz (the moving grid's field: about a third of the writing time)",
    )
    reg.add_argument(
        "--no-maps",
        action="store_true",
        help="do not write jacobian.nii.gz, entropy.nii.gz and "
        "displacement_std.nii.gz (summary.json keeps their statistics)",
    )
    model = parser.add_argument_group("model and machine")
    model.add_argument("--bundle-root", metavar="B", help="MONAI bundle folder (default: bundle/ of the repository)")
    model.add_argument(
        "--model-file",
        metavar="P",
        help="weights (default: the model_file of the config, the bundle's shipped default)",
    )
    model.add_argument("--config", metavar="Y", help="network settings (default: B/configs/inference.yaml)")
    model.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    model.add_argument(
        "--threads", type=int, default=None, metavar="N", help="CPU threads for torch and ITK (default: all)"
    )
    model.add_argument(
        "--unet-precision",
        choices=["auto", "bf16", "fp32"],
        default=None,
        help="the UNet's arithmetic (default: the config's unet_precision, 'auto': bf16 on CPUs with "
        "native bf16, else float32; integration and warps are always float32)",
    )
    model.add_argument(
        "--no-memory-reuse",
        action="store_true",
        help="give freed memory back to the system (glibc's default); by default the process keeps it "
        "and reuses it, which saves about a fifth of a registration's time on a CPU (monai_probreg.utils.memory)",
    )
    model.add_argument(
        "--max-voxels",
        type=int,
        default=None,
        metavar="N",
        help="refuse an image of more than N voxels before reading it, instead of running out of memory "
        "(default: $MONAI_PROBREG_MAX_VOXELS, else 512^3 = 134217728)",
    )
    model.add_argument("--quiet", action="store_true", help="print nothing but errors and the final summary")
    model.add_argument("--debug", action="store_true", help="show the full traceback of an unexpected error")
    return reg


def _add_initial_transform(reg: argparse._ArgumentGroup, batch: bool = False) -> None:
    """``--initial-transform``: an earlier registration's affine (ANTs' ``-r``) in the "registration" group ``reg``;
    register and register-batch only (the demo makes its own subject)."""
    from monai_probreg.registration.options import INITIAL_TRANSFORM_USES

    reg.add_argument(
        "--initial-transform",
        metavar="T",
        help="an earlier registration's affine, fixed -> moving as ITK and ANTs write it: an ITK transform file "
        "(.tfm, .txt; e.g. our affine.tfm) or ANTs' .mat (*0GenericAffine.mat; antsRegistration's -r)"
        + (
            "; one file for every scan, or a folder holding one per scan, named like it (NAME.tfm, NAME.txt, "
            "NAME.mat or NAME/affine.tfm: an earlier register-batch's --out)"
            if batch
            else ""
        ),
    )
    reg.add_argument(
        "--initial-transform-use",
        choices=INITIAL_TRANSFORM_USES,
        default=None,
        help="start: the affine stage starts from it and refines it (default); as-affine: it is the affine, "
        "the affine stage is skipped",
    )


def _add_masks(reg: argparse._ArgumentGroup, batch: bool = False) -> None:
    """``--fixed-mask`` and the moving scan's mask (``--moving-mask``; a folder of them in a batch): cost-function
    masks, ANTs' ``antsRegistration -x [fixedMask,movingMask]`` (:mod:`monai_probreg.spatial.masks`); register and
    register-batch only (the demo makes its own subject); in the "registration" group ``reg``."""
    reg.add_argument(
        "--fixed-mask",
        metavar="FM",
        help="cost-function mask of the fixed image (same grid; nonzero = inside, as ANTs): the affine metric and "
        "the refinement compare the images only inside it, and it replaces the fixed image's support as the brain "
        "mask (dilated by --brain-mask-margin)",
    )
    if batch:
        reg.add_argument(
            "--moving-mask-dir",
            metavar="D",
            help="folder of moving masks named like their scans (same grid; nonzero = inside; a scan without one "
            "is registered without): points mapped outside a scan's mask are left out of the affine metric and the "
            "refinement",
        )
    else:
        reg.add_argument(
            "--moving-mask",
            metavar="MM",
            help="cost-function mask of the moving scan (same grid; nonzero = inside, as ANTs): points mapped "
            "outside it (a lesion, an artefact) are left out of the affine metric and the refinement",
        )


def build_parser() -> argparse.ArgumentParser:
    from monai_probreg.cli.apply import add_apply_parser
    from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES

    parser = argparse.ArgumentParser(
        prog="monai-probreg", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="{register,register-batch,demo,apply}")
    one = commands.add_parser(
        "register",
        help="register one scan to the fixed image",
        description="Register one scan to the fixed image; outputs in DIR.\n\n" + DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    one.add_argument("--moving", required=True, metavar="M", help="the scan to register (NIfTI, NRRD, MHA...)")
    one.add_argument("--moving-label", metavar="L", help="its label map (same grid): warped_label.nii.gz and Dice")
    reg = _add_common(one)
    _add_initial_transform(reg)
    _add_masks(reg)
    many = commands.add_parser(
        "register-batch",
        help="register many scans to one fixed image",
        description="Register many scans to one fixed image, the model loaded once; outputs "
        "in DIR/<scan name>/ plus DIR/batch_summary.csv.\n\n" + DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    many.add_argument(
        "--moving",
        required=True,
        nargs="+",
        metavar="M",
        help="scans, or one folder of scans (*.nii.gz, *.nii, *.nrrd, *.mha)",
    )
    many.add_argument(
        "--moving-label-dir",
        metavar="D",
        help="folder of label maps named like their scans (a scan without one is registered without labels)",
    )
    reg = _add_common(many)
    _add_initial_transform(reg, batch=True)
    _add_masks(reg, batch=True)
    demo = commands.add_parser(
        "demo",
        help="register a synthetic subject with a known answer and score it",
        description="Make a subject from the template (--fixed; default: the MNI152 template "
        "nilearn ships) with a known random rigid turn and shift, smooth deformation, bias "
        "field and noise (drawn from --seed), register it back with the options of register, "
        "and print how well the known transform was recovered: the displacement error in mm "
        "inside the brain before and after, and the coverage of the calibrated 95% interval. "
        "Outputs in DIR as register's, plus subject.nii.gz and true_warp.nii.gz; the scores in "
        f'DIR/summary.json["demo"]. --samples defaults to {POSTERIOR_SAMPLES} here (as many as the calibration is '
        "fitted with).\n\n" + DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_common(demo)
    demo.set_defaults(samples=None)  # None: monai_probreg.registration.demo.DEMO_SAMPLES (imported when the demo runs)
    add_apply_parser(commands)
    return parser


def _named_like(folder: str | None, sid: str) -> Path | None:
    """The file of ``folder`` named like scan ``sid`` (an image suffix), or None (no folder, or no such file)."""
    from monai_probreg.utils.files import IMAGE_SUFFIXES

    if not folder:
        return None
    return next((m for m in (Path(folder) / (sid + ext) for ext in IMAGE_SUFFIXES) if m.is_file()), None)


def _batch_items(args: argparse.Namespace) -> list[tuple[str, Path, Path | None, Path | None]]:
    from monai_probreg.utils.errors import InputError
    from monai_probreg.utils.files import IMAGE_SUFFIXES, file_stem

    paths = [Path(p) for p in args.moving]
    if len(paths) == 1 and paths[0].is_dir():
        paths = sorted(p for p in paths[0].iterdir() if p.is_file() and p.name.endswith(IMAGE_SUFFIXES))
        if not paths:
            raise InputError(f"--moving {args.moving[0]!r}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
    items, seen = [], {}
    for path in paths:
        sid = file_stem(path)
        if sid in seen:
            raise InputError(
                f"--moving: {str(seen[sid])!r} and {str(path)!r} have the same name {sid!r}; their "
                "outputs would collide"
            )
        seen[sid] = path
        items.append((sid, path, _named_like(args.moving_label_dir, sid), _named_like(args.moving_mask_dir, sid)))
    return items


def _per_level(values: tuple[int, ...], levels: int) -> tuple[int, ...]:
    return tuple(values[:levels]) + (values[-1],) * max(0, levels - len(values))


def _initial_use(args: argparse.Namespace) -> str | None:
    """How ``--initial-transform`` is used (``start`` unless ``--initial-transform-use`` says otherwise), or None
    without one (and on ``demo``, which has no such option)."""
    from monai_probreg.registration.options import INITIAL_TRANSFORM_USES

    if getattr(args, "initial_transform", None) is None:
        return None
    return args.initial_transform_use or INITIAL_TRANSFORM_USES[0]


def _affine_stage_runs(args: argparse.Namespace) -> bool:
    return not args.no_affine and _initial_use(args) != "as-affine"


def _initial_transform(args: argparse.Namespace):
    """``--initial-transform`` read now, before the model loads (a batch's folder: per scan, by the batch), or None."""
    from monai_probreg.registration.options import InitialTransform
    from monai_probreg.utils.errors import InputError

    path = getattr(args, "initial_transform", None)
    if path is None:
        if getattr(args, "initial_transform_use", None) is not None:
            raise InputError(
                f"--initial-transform-use {args.initial_transform_use}: expected --initial-transform too (the use "
                "of which transform?)"
            )
        return None
    if args.no_affine:
        raise InputError(
            f"--initial-transform {path!r}: expected it or --no-affine, got both (--initial-transform-use as-affine "
            "takes it as the affine without running the stage)"
        )
    if args.command == "register-batch" and Path(path).is_dir():
        return None
    return InitialTransform.read(path, _initial_use(args))


def _options(args: argparse.Namespace):
    from monai_probreg.registration.options import RegistrationOptions
    from monai_probreg.spatial.affine import AffineSettings
    from monai_probreg.utils.errors import InputError

    if args.brain_mask_margin is not None and not args.brain_mask_margin >= 0:
        raise InputError(f"--brain-mask-margin must be >= 0 mm; got {args.brain_mask_margin}")
    if args.refine is not None and args.refine < 0:
        raise InputError(f"--refine must be >= 0 optimiser steps (0 = off); got {args.refine}")
    if args.smoothness is not None and not (math.isfinite(args.smoothness) and args.smoothness > 0):
        raise InputError(f"--smoothness must be a number > 0 (1: the shipped prior); got {args.smoothness}")
    if args.smoothness is not None and args.refine == 0:
        raise InputError("--smoothness scales the refinement's prior: expected refinement on, got --refine 0")
    if args.match_contrast and args.contrast != "other":
        raise InputError("--match-contrast maps a second contrast onto the first: expected --contrast other too")
    if args.contrast == "other" and args.refine == 0:
        raise InputError("--contrast other sets the refinement's image term: expected refinement on, got --refine 0")
    initial = _initial_transform(args)
    affine = None
    if _affine_stage_runs(args):
        if args.nondeterministic_affine and args.affine_backend != "itk":
            raise InputError(
                "--nondeterministic-affine applies to --affine-backend itk only (the torch backend is "
                "reproducible with any number of threads)"
            )
        base = AffineSettings() if args.affine_backend == "torch" else AffineSettings.itk_defaults()
        changes: dict = {
            "rigid_only": args.rigid_only,
            "seed": args.seed,
            "deterministic": not args.nondeterministic_affine,
            "local_stage": args.affine_local,
        }
        levels = tuple(args.affine_levels) if args.affine_levels is not None else base.shrink_factors
        if args.affine_levels is not None:
            changes.update(shrink_factors=levels, smoothing_sigmas_mm=tuple(s / 2.0 for s in levels))
        if args.affine_iterations is not None:
            if len(args.affine_iterations) != len(levels):
                raise InputError(
                    f"--affine-iterations needs one value per --affine-levels level ({len(levels)}); "
                    f"got {len(args.affine_iterations)}"
                )
            changes.update(
                rigid_iterations=tuple(args.affine_iterations), affine_iterations=tuple(args.affine_iterations)
            )
        elif args.affine_levels is not None:  # the defaults' first levels, the last one repeated if more
            changes.update(
                rigid_iterations=_per_level(base.rigid_iterations, len(levels)),
                affine_iterations=_per_level(base.affine_iterations, len(levels)),
            )
        if args.affine_sampling is not None:
            changes["sampling_percentage"] = args.affine_sampling
        if args.affine_max_samples is not None:
            if args.affine_backend != "torch":
                raise InputError(
                    "--affine-max-samples applies to --affine-backend torch only (ITK samples a "
                    "percentage: --affine-sampling)"
                )
            if args.affine_max_samples < 0:
                raise InputError(f"--affine-max-samples must be >= 1, or 0 for no cap; got {args.affine_max_samples}")
            changes["max_samples"] = args.affine_max_samples or None
        try:
            affine = AffineSettings(**{**base.as_dict(), **changes})
        except ValueError as err:
            raise InputError(f"affine settings: {err}") from None
    return RegistrationOptions(
        samples=args.samples,
        seed=args.seed,
        qc=not args.no_qc,
        affine=affine,
        inverse=not args.no_inverse,
        maps=not args.no_maps,
        initial=initial,
    )


def _setup(args: argparse.Namespace):
    """Threads, model, fixed image: the parts a batch pays for once."""
    import itk
    import torch

    from monai_probreg.registration.inputs import prepare_fixed
    from monai_probreg.registration.model import load_model
    from monai_probreg.spatial.affine import load_itk_modules
    from monai_probreg.spatial.brain_mask import DEFAULT_MARGIN_MM
    from monai_probreg.utils.memory import reuse_freed_memory

    if args.threads is not None:
        if args.threads < 1:
            from monai_probreg.utils.errors import InputError

            raise InputError(f"--threads must be >= 1; got {args.threads}")
        torch.set_num_threads(args.threads)
        # ITK reads this when its core first loads (the torch path never loads it, which saves its load time); the ITK
        # backend, where ITK's threads matter, is told directly (ITK may be loaded already in this process)
        os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)
        if args.affine_backend == "itk":
            itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(args.threads)
    if not args.no_memory_reuse:
        reuse_freed_memory()
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    model = load_model(args.bundle_root, args.model_file, args.config, device, calibrate=not args.raw_uncertainty)
    if args.unet_precision is not None:
        model.network.unet_precision = args.unet_precision
    if args.fixed is None:
        from monai_probreg.data.template import mni152_template_path

        args.fixed = str(mni152_template_path())
    margin = DEFAULT_MARGIN_MM if args.brain_mask_margin is None else args.brain_mask_margin
    fixed = prepare_fixed(
        args.fixed,
        args.fixed_label,
        model.divisor,
        None if args.no_brain_mask else margin,
        getattr(args, "fixed_mask", None),  # the demo has no --fixed-mask
    )
    if args.affine_backend == "itk" and _affine_stage_runs(args):
        load_itk_modules()  # several seconds, paid once per batch, outside the timed stages
    return model, fixed


def _with_refinement(
    options,
    model,
    iterations: int | None,
    smoothness: float | None = None,
    contrast: str = "same",
    match_contrast: bool = False,
):
    """The config's refinement settings (``model.refinement``), with the config's ``other_contrast`` fields for
    ``--contrast other`` (and with ``--match-contrast`` the moving image mapped onto the fixed one's contrast over the
    config's ``contrast_match_bins``), ``--refine N`` steps and ``--smoothness S`` (the prior's ``prior_lambda`` times
    S) when given; without any the options keep ``refinement=None``, which ``register_scan`` reads as the config's."""
    import dataclasses

    from monai_probreg.utils.errors import InputError

    if match_contrast:  # with --contrast other (checked with the other arguments, before the model loads)
        if not model.contrast_match_bins:
            raise InputError(
                f"--match-contrast: expected the config's 'contrast_match_bins' (>= 2), got none in "
                f"{str(model.config_file)!r}"
            )
        options = dataclasses.replace(options, contrast_match_bins=model.contrast_match_bins)
    if iterations is None and smoothness is None and contrast == "same":
        return options
    refinement = model.refinement
    if contrast == "other":
        options = dataclasses.replace(options, contrast="other")
        if not model.other_contrast:
            raise InputError(
                f"--contrast other: expected the config's 'other_contrast' settings, got none in "
                f"{str(model.config_file)!r}"
            )
        refinement = refinement.with_fields(**model.other_contrast)
    if iterations is not None:
        try:
            refinement = refinement.with_fields(num_iterations=iterations)
        except ValueError as err:
            raise InputError(f"--refine: {err}") from None
    if smoothness is not None:
        if not refinement.enabled:  # the config's refinement is off and --refine did not turn it on
            raise InputError(
                "--smoothness scales the refinement's prior: expected refinement on (the config's "
                "refine_iterations or --refine N), got 0 steps"
            )
        refinement = refinement.with_fields(prior_lambda=refinement.prior_lambda * smoothness)
    return dataclasses.replace(options, refinement=refinement)


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text, file=sys.stderr, flush=True)


def _require_files(args: argparse.Namespace, options: Sequence[str]) -> None:
    """Fail fast, before the model and ITK load (seconds), on input paths that do not exist."""
    from monai_probreg.utils.errors import InputError

    if getattr(args, "fixed_label", None) is not None and args.fixed is None:
        raise InputError(f"--fixed-label {args.fixed_label!r}: expected --fixed too (the label map of which image?)")
    for option in options:
        value = getattr(args, option.lstrip("-").replace("-", "_"), None)
        if value is not None and not Path(value).is_file():
            what = "is a folder, not an image file" if Path(value).is_dir() else "no such file"
            raise InputError(f"{option} {value!r}: {what}")


def _print_result(args: argparse.Namespace, summary: dict) -> int:
    """The summary line on stdout and the warning, if any, on stderr; 0: a warning never changes the exit status."""
    from monai_probreg.cli.messages import summary_line

    print(f"{args.out}: {summary_line(summary)}")
    if summary.get("warning"):
        print(f"monai-probreg: warning: {args.out}: {summary['warning']}", file=sys.stderr, flush=True)
    return 0


def _register_one(args: argparse.Namespace, files: Sequence[str], ready: str, register: Callable[..., dict]) -> int:
    """``register`` and ``demo``: the options and the ``files`` options checked, the model and the fixed image loaded
    (``ready`` names them in the message), then ``register(model, fixed, options, report)``'s summary printed."""
    from monai_probreg.registration.output_folder import check_output_dir

    options = _options(args)
    _require_files(args, files)
    check_output_dir(args.out, args.overwrite)  # fail before loading anything
    start = time.perf_counter()
    model, fixed = _setup(args)
    options = _with_refinement(options, model, args.refine, args.smoothness, args.contrast, args.match_contrast)
    _say(args, f"{ready} ready in {time.perf_counter() - start:.1f} s")
    summary = register(model, fixed, options, lambda stage, s: _say(args, f"  {stage:<9}{s:7.1f} s"))
    return _print_result(args, summary)


def _register(args: argparse.Namespace) -> int:
    from monai_probreg.registration.scan import register_scan

    def register(model, fixed, options, report) -> dict:
        return register_scan(
            model,
            fixed,
            args.moving,
            args.out,
            args.moving_label,
            options,
            args.overwrite,
            report=report,
            moving_mask_path=args.moving_mask,
        )

    files = ["--moving", "--moving-label", "--fixed", "--fixed-label", "--fixed-mask", "--moving-mask"]
    return _register_one(args, files, "model and fixed image", register)


def _demo(args: argparse.Namespace) -> int:
    from monai_probreg.cli.messages import demo_report
    from monai_probreg.registration.demo import DEMO_SAMPLES, run_demo

    def register(model, fixed, options, report) -> dict:
        summary = run_demo(model, fixed, args.out, args.seed, options=options, overwrite=args.overwrite, report=report)
        print(demo_report(summary))
        return summary

    if args.samples is None:
        args.samples = DEMO_SAMPLES
    return _register_one(args, ["--fixed", "--fixed-label"], "model and template", register)


def _register_batch(args: argparse.Namespace) -> int:
    from monai_probreg.cli.messages import print_batch_table
    from monai_probreg.registration.batch import BatchItem, register_batch
    from monai_probreg.registration.output_folder import check_output_dir

    options = _options(args)
    _require_files(args, ["--fixed", "--fixed-label", "--fixed-mask"])
    if args.moving_mask_dir is not None and not Path(args.moving_mask_dir).is_dir():
        from monai_probreg.utils.errors import InputError

        raise InputError(f"--moving-mask-dir {args.moving_mask_dir!r}: expected a folder, got no such folder")
    items = [BatchItem(*item) for item in _batch_items(args)]
    out = Path(args.out)
    for item in items:  # fail fast on what is cheap to check and would hit every scan
        check_output_dir(out / item.name, args.overwrite)
    model, fixed = _setup(args)
    options = _with_refinement(options, model, args.refine, args.smoothness, args.contrast, args.match_contrast)
    per_scan = args.initial_transform is not None and Path(args.initial_transform).is_dir()
    rows = register_batch(
        model,
        fixed,
        items,
        out,
        options,
        args.overwrite,
        quiet=args.quiet,
        debug=args.debug,
        initial_transforms=Path(args.initial_transform) if per_scan else None,
        initial_use=_initial_use(args),
    )
    print_batch_table(rows)
    failed = sum(row.status != "ok" for row in rows)
    if failed:
        print(
            f"monai-probreg: error: {failed} of {len(rows)} scans failed (see above and {out}/batch_summary.csv)",
            file=sys.stderr,
        )
    return 1 if failed else 0


def _apply(args: argparse.Namespace) -> int:
    from monai_probreg.cli.apply import run_apply

    return run_apply(args)


@contextlib.contextmanager
def _voxel_limit(limit: int | None) -> Iterator[None]:
    """``--max-voxels``: the limit of :mod:`monai_probreg.spatial.checks` for this call only (restored afterwards)."""
    from monai_probreg.spatial.checks import MAX_VOXELS_ENV
    from monai_probreg.utils.errors import InputError

    if limit is None:
        yield
        return
    if limit < 1:
        raise InputError(f"--max-voxels: expected a positive number of voxels, got {limit}")
    previous = os.environ.get(MAX_VOXELS_ENV)
    os.environ[MAX_VOXELS_ENV] = str(limit)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(MAX_VOXELS_ENV, None)
        else:
            os.environ[MAX_VOXELS_ENV] = previous


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``monai-probreg`` command; returns the exit status."""
    args = build_parser().parse_args(argv)
    os.environ.setdefault("KMP_WARNINGS", "0")
    try:
        with _voxel_limit(args.max_voxels):
            command = {"register": _register, "register-batch": _register_batch, "demo": _demo, "apply": _apply}[
                args.command
            ]
            return command(args)
    except KeyboardInterrupt:
        print(
            "monai-probreg: interrupted; the scan in progress left nothing in its output folder (a batch lists "
            "the scans not run in batch_summary.csv)",
            file=sys.stderr,
        )
        return 130
    except Exception as err:  # noqa: BLE001 - one line for users; --debug for the traceback
        from monai_probreg.utils.errors import InputError, first_line

        if args.debug:
            traceback.print_exc()
        if isinstance(err, InputError):
            print(f"monai-probreg: error: {err}", file=sys.stderr)
        else:
            print(
                f"monai-probreg: error: unexpected {type(err).__name__}: {first_line(err)} (rerun with --debug for the "
                "traceback)",
                file=sys.stderr,
            )
        return 1


def run_bundle_demo(
    out_dir: str,
    seed: int = 0,
    bundle_root: str | None = None,
    model_file: str | None = None,
    template: str | None = None,
    samples: int | None = None,
    overwrite: bool = False,
) -> dict:
    """The bundle's ``configs/demo.yaml``: ``monai-probreg demo`` with these options (None: the command's default);
    prints what the command prints and returns the summary. Raises RuntimeError when the demo fails."""
    import json

    argv = ["demo", "--out", str(out_dir), "--seed", str(seed)]
    for flag, value in (
        ("--bundle-root", bundle_root),
        ("--model-file", model_file),
        ("--fixed", template),
        ("--samples", samples),
    ):
        if value is not None:
            argv += [flag, str(value)]
    status = main(argv + (["--overwrite"] if overwrite else []))
    if status != 0:
        raise RuntimeError(f"monai-probreg demo failed with exit status {status} (see the error above)")
    return json.loads((Path(out_dir) / "summary.json").read_text())


def run() -> None:
    """The console entry point (``monai-probreg``, ``python -m monai_probreg.cli``): :func:`main`, then leave
    without tearing the interpreter down.

    Python's normal exit spends seconds here, after every output is written, destroying the half a million objects
    that importing monai, torch and ITK creates (``experiments/command_levers.py``'s ``exit`` row times both). Once
    :func:`main` has returned, every file of ours is closed and moved into place, so the only work left is flushing
    the standard streams and logging, done here before ``os._exit`` skips the teardown; the exit status is
    :func:`main`'s. Library callers of :func:`main` (tests, scripts) are unaffected."""
    status = main()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(status)


if __name__ == "__main__":
    run()
