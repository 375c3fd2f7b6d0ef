"""Register one raw scan to a fixed image, end to end: the functional core of ``monai-probreg register``.

Stages, timed under these names in ``summary.json["timings_s"]``, each in the module that runs it:

- ``read``: read and validate the moving scan (and its labels, its mask) with their geometry (:mod:`.inputs`);
- ``affine``, ``resample``: the affine pre-alignment, then the moving scan on the model grid as the network reads it
  (:mod:`.affine_stage`; with ``--match-contrast`` in the fixed image's contrast,
  :mod:`~monai_probreg.spatial.contrast`);
- ``model``, ``refine``, ``maps``, ``samples``: the network's registration, its test-time refinement, the
  Jacobian, entropy and inverse (the inverse after the quality estimate: ``maps`` is timed in two parts), the
  displacement std map (first order; the stage's name is from when it was sampled; :mod:`.network`);
- ``quality``: the label-free quality estimate, with a quality model next to the weights (:mod:`.quality_estimate`);
- ``compose``: affine + deformable -> one field fixed -> moving and its inverse; the original moving scan and labels
  resampled once through it; Dice (:mod:`.compose`);
- ``qc``, ``write``: the files, in a staging folder moved into place at the end (:mod:`.output_folder`), compressed
  in parallel threads while the QC figure is drawn (:mod:`.qc`): ``qc`` times the figure (its slices, cut before
  ``compose`` while the network's volumes are held, and the drawing), ``write`` the wait for the files after it;
  then ``summary.json`` (:mod:`.summary`) and ``README.txt``.

Memory: each large array goes once nothing left reads it, so that each stage runs beside as little as possible: the
network's own registration once refined (the quality estimate reads its features before the refinement: ``quality``
is timed in two parts), the network's volumes once the QC figure's slices are cut and as the compose stage reads
them (:func:`~.compose.compose_outputs`), each composed field once its file is written (its writer holds the only
reference); and the freed memory goes back between stages that allocate otherwise (:data:`_TRIM_AFTER`).

The model is loaded once (:func:`monai_probreg.registration.model.load_model`) and the fixed image prepared once
(:func:`monai_probreg.registration.inputs.prepare_fixed`), so a batch pays for them once; neither is counted in a
scan's stages.
"""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from monai_probreg.registration.affine_stage import affine_stage, matched_input, model_input
from monai_probreg.registration.compose import Composed, compose_outputs
from monai_probreg.registration.inputs import FixedSpace, read_moving
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.network import ModelMaps, add_inverse, register_network, run_network
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_files import OUTPUTS_README
from monai_probreg.registration.output_folder import (
    check_output_dir,
    finished_qc_planes,
    network_qc_planes,
    output_writers,
    qc_title,
    staged_output_dir,
)
from monai_probreg.registration.qc import save_qc
from monai_probreg.registration.quality_estimate import (
    estimate_quality,
    network_quality_features,
    why_no_quality,
)
from monai_probreg.registration.summary import scan_summary
from monai_probreg.spatial.affine import AffineResult
from monai_probreg.spatial.volume_io import Volume
from monai_probreg.utils.files import parallel_writes, write_text
from monai_probreg.utils.memory import trim_freed_memory

__all__ = ["Registered", "register_scan"]


class Registered(NamedTuple):
    """What :func:`register_scan` computed, for a caller's own check of the result (its ``check``).

    ``warp`` (*S, 3): the composed ``D(p) = phi(p) - p``, LPS mm on the fixed grid, float32 (``warp.nii.gz``'s
    values); ``affine`` (4, 4): the affine stage, fixed LPS -> moving LPS; ``points`` (*S, 3): the fixed grid's LPS
    points;
    ``displacement_variance`` (*S, 3): the calibrated posterior's variance of the deformable displacement, mm^2 on
    the fixed grid, one component per column of ``variance_axes`` (3, 3; unit LPS vectors: the model grid's axes),
    or None without samples; ``error_features`` (F, *S): the pair's error-model features on the model grid
    (``RegistrationOptions.error_features``), or None."""

    warp: np.ndarray
    affine: np.ndarray
    points: np.ndarray
    displacement_variance: np.ndarray | None
    variance_axes: np.ndarray
    error_features: np.ndarray | None = None


def _registered(fixed: FixedSpace, affine: AffineResult, composed: Composed, model_maps: ModelMaps) -> Registered:
    grid = fixed.grid
    variance = None if model_maps.variance is None else grid.to_fixed(np.moveaxis(model_maps.variance, 0, -1))
    axes = grid.index_to_lps[:3, :3] / grid.spacing
    return Registered(composed.warp, affine.matrix, fixed.points, variance, axes, model_maps.error_features)


# the stages after which the freed memory goes back (monai_probreg.utils.memory: with memory reuse the heap keeps it
# and fragments): each leaves large temporaries freed behind it and is followed by stages that allocate otherwise
# (the quality estimate, the refinement, the maps, the inverse, the compose stage, the writing), which then start
# from the memory in use
_TRIM_AFTER = frozenset({"model", "quality", "refine", "maps", "compose"})


@contextmanager
def _timed(timings: dict[str, float], name: str, report: Callable[[str, float], None] | None) -> Iterator[None]:
    """Time a stage; a stage run in parts (``maps``, ``qc``) is timed as their sum, each part reported on its own.
    After the stages of :data:`_TRIM_AFTER`, the freed memory is given back (in the stage's time)."""
    start = time.perf_counter()
    yield
    if name in _TRIM_AFTER:
        trim_freed_memory()
    seconds = time.perf_counter() - start
    timings[name] = round(timings.get(name, 0.0) + seconds, 3)
    if report is not None:
        report(name, round(seconds, 3))


# summary.json's "timings_s" in the order of the stages (the module docstring), whatever order their parts ran in
_STAGE_ORDER = ("read", "affine", "resample", "model", "refine", "maps", "samples", "quality", "compose", "qc", "write")


def _in_stage_order(timings: dict[str, float]) -> dict[str, float]:
    """``timings`` in :data:`_STAGE_ORDER`, any other name after them in its own order ("total" last)."""
    rank = {name: n for n, name in enumerate(_STAGE_ORDER)}
    return dict(sorted(timings.items(), key=lambda item: rank.get(item[0], len(rank))))


def register_scan(
    model: LoadedModel,
    fixed: FixedSpace,
    moving_path: str | os.PathLike | Volume,
    out_dir: str | os.PathLike,
    moving_label_path: str | os.PathLike | None = None,
    options: RegistrationOptions | None = None,
    overwrite: bool = False,
    report: Callable[[str, float], None] | None = None,
    check: Callable[[Registered], dict] | None = None,
    extra_outputs: Mapping[str, Callable[[Path], object]] | None = None,
    moving_mask_path: str | os.PathLike | None = None,
) -> dict:
    """Register ``moving_path`` to ``fixed`` and write every output into ``out_dir`` (all or nothing).

    ``moving_path`` may be a :class:`~monai_probreg.spatial.volume_io.Volume` already in memory (``monai-probreg
    demo``'s synthetic subject): the "read" stage then only takes it. ``report(stage, seconds)`` is called after each
    stage. ``check(registered)``: a caller's check of the result (:class:`Registered`), whose keys are added to the
    summary; ``extra_outputs``: file name -> writer of that file (given its path in the staging folder), written
    with the others. ``moving_mask_path``: the moving scan's cost-function mask (``--moving-mask``, on its grid;
    :mod:`monai_probreg.spatial.masks`), or None. Returns the summary written to ``summary.json``.
    Raises :class:`~monai_probreg.utils.errors.InputError` (one line) for unusable inputs, before anything is written.
    """
    options = options or RegistrationOptions()
    if options.refinement is None:  # the model's (config's) refinement: what the command line runs by default
        options = replace(options, refinement=model.refinement)
    out = check_output_dir(out_dir, overwrite)
    timings: dict[str, float] = {}
    stage = functools.partial(_timed, timings, report=report)
    start = time.perf_counter()
    with stage("read"):
        moving = read_moving(moving_path, moving_label_path, moving_mask_path)
    with stage("affine"):
        affine = affine_stage(fixed, moving, options)
    with stage("resample"):
        moving_input, masks = model_input(fixed, moving, affine.matrix)
        if options.contrast_match_bins:  # --match-contrast: what the network reads in the fixed image's contrast
            moving_input = matched_input(moving_input, fixed.model_input, masks, options.contrast_match_bins)
    output = register_network(model, moving_input, fixed.model_input, stage)
    network_features = None
    estimates_quality = why_no_quality(model, options) is None  # else no stage, "quality": null
    if estimates_quality and options.refinement.enabled:  # the quality stage's first part
        with stage("quality"):
            network_features = network_quality_features(model, moving_input, fixed, output)
    model_maps = run_network(model, output, moving_input, fixed.model_input, options, fixed.grid.spacing, stage, masks)
    del output  # the network's own registration: read by the refinement and the quality estimate only
    quality = None
    if estimates_quality:
        with stage("quality"):
            quality = estimate_quality(model, moving_input, fixed, model_maps, network_features)
    with stage("maps"):  # the maps stage's last part, now that the quality estimate's memory is free
        add_inverse(model, model_maps)
    warning = quality.estimate.warning if quality is not None else None
    planes = None
    if options.qc:  # the figure's slices, cut while the network's volumes are here; drawn with the files below
        with stage("qc"):
            planes = network_qc_planes(fixed, moving_input, model_maps)
    del moving_input, masks  # read by the network, the quality estimate and the QC figure's slices only
    model_maps.warped = None  # likewise; compose_outputs consumes the other volumes
    with stage("compose"):
        composed = compose_outputs(fixed, moving.image, moving.label, affine.matrix, model_maps, options.inverse)
    stats = composed.jacobian_stats
    checked = check(_registered(fixed, affine, composed, model_maps)) if check is not None else {}
    with staged_output_dir(out, overwrite) as folder:
        # the files compress in a pool of threads while this thread draws the QC figure: "write" is the wait for the
        # files after the drawing (so the stages still add up to the wall time)
        write_start, qc_before = time.perf_counter(), timings.get("qc", 0.0)
        with parallel_writes(torch.get_num_threads()) as submit:
            for writer in output_writers(folder, fixed, moving.image, affine, composed, options):
                submit(writer)
            composed.warp = composed.inverse_warp = None  # their writers hold them now: each goes once written
            for name, write in (extra_outputs or {}).items():
                submit(functools.partial(write, folder / name))
            if planes is not None:
                with stage("qc"):
                    title = qc_title(moving.image, composed.dice, stats.num_folding, quality)
                    save_qc(folder / "qc.png", finished_qc_planes(planes, fixed, composed, title, warning))
        drawing = timings.get("qc", 0.0) - qc_before
        timings["write"] = round(time.perf_counter() - write_start - drawing, 3)
        if report is not None:
            report("write", timings["write"])
        timings["total"] = round(time.perf_counter() - start, 3)
        timings = _in_stage_order(timings)
        outputs = sorted(p.name for p in folder.iterdir()) + ["summary.json", "README.txt"]
        summary = scan_summary(
            model, fixed, moving, options, affine, model_maps, composed, stats, quality, timings, outputs
        )
        clash = set(checked) & set(summary)
        if clash:
            raise ValueError(f"check() returned keys the summary has already: {sorted(clash)}")
        summary.update(checked)
        write_text(folder / "summary.json", json.dumps(summary, indent=2) + "\n")
        write_text(folder / "README.txt", OUTPUTS_README)
    return summary
