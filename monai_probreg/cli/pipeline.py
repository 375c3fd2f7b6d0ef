"""Register one raw scan to a fixed image, end to end: the functional core of ``monai-probreg register``.

Stages, timed under these names in ``summary.json["timings_s"]``:

- ``read``: read and validate the moving scan (and its labels) with their geometry (:mod:`monai_probreg.spatial.volume_io`);
- ``affine``: rigid + affine registration of the raw moving scan to the fixed image (:mod:`monai_probreg.spatial.affine`:
  torch by default, or ITK), started from an earlier registration's affine or replaced by it
  (:class:`InitialTransform`);
- ``resample``: the moving scan onto the fixed grid through the affine (one linear interpolation, the scan's
  minimum outside it and outside the fixed image's brain mask, :mod:`monai_probreg.spatial.brain_mask`: the fixed
  image's support or the ``--fixed-mask``, dilated by a margin), percentile
  intensity scaling to [0, 1] exactly as in training (:mod:`monai_probreg.spatial.intensity`), then onto the model grid
  (:class:`~monai_probreg.spatial.model_grid.ModelGrid`: RAS, padded to the bundle's divisor);
- ``model``: the network's posterior mean velocity -> displacement and the warped scan (network, integration, warp);
- ``refine``: with ``refinement`` enabled, that mean refined for the pair (:mod:`monai_probreg.engines.refinement`),
  its image term inside the cost-function masks when given (``--fixed-mask``, ``--moving-mask``:
  :mod:`monai_probreg.spatial.masks`, which the affine metric heeds too);
- ``maps``: the inverse displacement (``exp(-v)``; unless ``inverse`` is off), Jacobian, velocity entropy;
- ``samples``: with ``samples = K >= 2``, K posterior samples -> displacement standard deviation;
- ``compose``: affine + deformable -> one field fixed -> moving and its inverse (:mod:`monai_probreg.spatial.physical`);
  the original moving scan and labels resampled once through it; Dice;
- ``qc``, ``write``: the files, in a staging folder moved into place at the end (:mod:`monai_probreg.cli.output_dir`),
  compressed in parallel threads while the QC figure is drawn: ``qc`` times the drawing, ``write`` the wait for the
  files after it.

The model is loaded once (:func:`monai_probreg.cli.model.load_model`) and the fixed image prepared once
(:func:`prepare_fixed`), so a batch pays for them once; neither is counted in a scan's stages.
"""

from __future__ import annotations

import functools
import json
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import itk
import numpy as np
import torch
from monai.networks.utils import eval_mode

import monai_probreg
from monai_probreg.cli.compose import affine_resample, forward_outputs, inverse_outputs
from monai_probreg.cli.model import LoadedModel
from monai_probreg.cli.output_dir import (
    OUTPUTS_README,
    check_output_dir,
    label_dtype,
    staged_output_dir,
    write_field,
    write_transform,
    write_volume,
)
from monai_probreg.cli.qc import QCData, save_qc
from monai_probreg.engines.refinement import RefinementMasks, RefinementSettings, refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.metrics.calibration import interval_z
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.spatial.affine import AffineResult, AffineSettings, align
from monai_probreg.spatial.affine_torch import FixedSamples, fixed_samples
from monai_probreg.spatial.brain_mask import DEFAULT_MARGIN_MM, dilated_mask, fixed_brain_mask, hide_outside
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.masks import MASK_LEVEL, mask_record, read_mask
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.transform_files import read_initial_transform
from monai_probreg.spatial.volume_io import Volume, check_same_grid, read_image, read_label, volume_to_itk
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.uncertainty.quality import QualityEstimate, quality_path, quality_record
from monai_probreg.uncertainty.quality_features import QualityFeatures, quality_features
from monai_probreg.uncertainty.residual import residual_variance
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import parallel_writes, write_text
from monai_probreg.utils.provenance import library_versions

__all__ = [
    "INITIAL_TRANSFORM_USES",
    "FixedSpace",
    "InitialTransform",
    "Registered",
    "RegistrationOptions",
    "prepare_fixed",
    "register_scan",
]


@dataclass
class FixedSpace:
    """The fixed image prepared once: geometry, model grid, normalised model input; :attr:`itk_image` (for the ITK
    affine backend) and :attr:`points` (for a caller's ``check``) are computed on first use, once."""

    image: Volume
    label: Volume | None
    grid: ModelGrid
    model_input: np.ndarray
    label_ids: list[int] = field(default_factory=list)
    brain_mask: np.ndarray | None = None  # where the moving scan stays visible (monai_probreg.spatial.brain_mask)
    brain_mask_margin_mm: float | None = None  # its margin; None = no mask
    affine_samples: dict[AffineSettings, FixedSamples] = field(default_factory=dict, repr=False)  # samples_for's
    mask: Volume | None = None  # --fixed-mask (bool, the fixed grid): where the metrics look (spatial.masks)

    @functools.cached_property
    def itk_image(self) -> itk.Image:
        return volume_to_itk(self.image)  # loads ITK's core modules (slow): not on the torch backend's path

    def samples_for(self, settings: AffineSettings) -> FixedSamples | None:
        """The torch affine backend's fixed-image samples for ``settings``, made on first use and kept (the same
        for every scan of a batch, so made once); None for the ITK backend."""
        if settings.backend != "torch":
            return None
        if settings not in self.affine_samples:
            self.affine_samples[settings] = fixed_samples(
                self.image, settings, None if self.mask is None else self.mask.array
            )
        return self.affine_samples[settings]

    @functools.cached_property
    def points(self) -> np.ndarray:
        """The fixed grid's LPS voxel centres (*S, 3), float64: not used by the registration itself (every sampling
        goes through :func:`~monai_probreg.spatial.physical.mapped_index`), only by :class:`Registered`."""
        return grid_points(self.image.shape, self.image.index_to_lps)


def prepare_fixed(
    path: str | os.PathLike,
    label_path: str | os.PathLike | None = None,
    divisor: int = 16,
    brain_mask_margin_mm: float | None = DEFAULT_MARGIN_MM,
    mask_path: str | os.PathLike | None = None,
) -> FixedSpace:
    """``brain_mask_margin_mm``: hide the moving scan outside the fixed image's support dilated by this many mm
    (:mod:`monai_probreg.spatial.brain_mask`); None: show the network the whole moving scan. ``mask_path``: the
    fixed image's cost-function mask (``--fixed-mask``, :mod:`monai_probreg.spatial.masks`), which is also the
    support that margin dilates (in place of the voxels above the image's minimum)."""
    image = read_image(path, "--fixed")
    label = None
    if label_path is not None:
        label = read_label(label_path, "--fixed-label")
        check_same_grid(label, image, "--fixed-label", "--fixed")
    fixed_mask = None if mask_path is None else read_mask(mask_path, "--fixed-mask", image, "--fixed")
    grid = ModelGrid.for_volume(image, divisor)
    ids = [int(v) for v in np.unique(label.array) if v != 0] if label is not None else []
    if brain_mask_margin_mm is None:
        mask = None
    elif fixed_mask is None:
        mask = fixed_brain_mask(image.array, image.spacing, brain_mask_margin_mm)
    else:
        mask = dilated_mask(fixed_mask.array, image.spacing, brain_mask_margin_mm)
    return FixedSpace(
        image,
        label,
        grid,
        grid.to_model(normalise_intensity(image.array)),
        ids,
        mask,
        brain_mask_margin_mm,
        mask=fixed_mask,
    )


INITIAL_TRANSFORM_USES = ("start", "as-affine")  # the affine stage starts from it / it is the affine (no stage)


@dataclass(frozen=True, eq=False)
class InitialTransform:
    """An earlier registration's affine (``--initial-transform``, ANTs' ``--initial-moving-transform``): ``matrix``
    (4, 4), fixed LPS -> moving LPS, ITK's and ANTs' convention, as ``affine.tfm``; ``center``: its file's centre
    (LPS mm; kept so that ``as-affine`` writes the file's own parameters back); ``use``: ``"start"``, the affine
    stage starts from it (:func:`~monai_probreg.spatial.affine.align`'s ``initial``), or ``"as-affine"``, it is the
    affine and no stage runs. Compared by identity (it holds arrays)."""

    path: str
    matrix: np.ndarray
    center: np.ndarray
    use: str = INITIAL_TRANSFORM_USES[0]

    def __post_init__(self) -> None:
        if self.use not in INITIAL_TRANSFORM_USES:
            raise ValueError(f"use: expected one of {INITIAL_TRANSFORM_USES}, got {self.use!r}")

    @classmethod
    def read(
        cls, path: str | os.PathLike, use: str = INITIAL_TRANSFORM_USES[0], role: str = "--initial-transform"
    ) -> InitialTransform:
        """The transform of an ITK (``.tfm``, ``.txt``) or ANTs (``.mat``) affine file; InputError (one line) for a
        missing, unreadable, non-affine, not 3-D or singular one
        (:func:`~monai_probreg.spatial.transform_files.read_initial_transform`)."""
        affine = read_initial_transform(path, role)
        return cls(str(path), affine.matrix, affine.center, use)

    def summary(self) -> dict:
        return {
            "path": str(Path(self.path).resolve()),
            "use": self.use,
            "matrix_fixed_to_moving_lps": np.round(self.matrix, 6).tolist(),
        }


@dataclass(frozen=True)
class RegistrationOptions:
    """``samples``: K posterior samples for the std map (0 = none, else >= 2); ``seed``: their RNG seed (the
    command line gives the same seed to ``affine.seed``);
    ``affine``: settings of the ITK pre-alignment, or None to skip it (the identity: scans already aligned to the
    fixed image, as the paper assumes); ``refinement``: test-time refinement of the posterior mean, or None for the
    model's own (its config's ``refinement``: the default path, as ``monai-probreg register`` runs it);
    ``inverse``: compute and write the inverse field and the fixed labels in moving space; ``maps``: write the
    Jacobian, entropy and std maps (their statistics stay in the summary either way); ``initial``: an earlier
    registration's affine that the affine stage starts from (``use="start"``, with ``affine`` settings) or that is
    the affine (``use="as-affine"``, with ``affine=None``), or None."""

    samples: int = 0
    seed: int = 0
    qc: bool = True
    inverse: bool = True
    maps: bool = True
    affine: AffineSettings | None = field(default_factory=AffineSettings)
    refinement: RefinementSettings | None = None
    initial: InitialTransform | None = None

    def __post_init__(self) -> None:
        if self.samples == 1 or self.samples < 0:
            raise InputError(
                f"--samples must be 0 (no sampling) or >= 2 (a standard deviation needs two); got {self.samples}"
            )
        if self.initial is not None and (self.initial.use == "start") != (self.affine is not None):
            # settings recorded for a stage that does not run, or a start for a stage that is not there
            raise ValueError(
                f"initial transform used as {self.initial.use!r}: expected affine settings "
                f"{'for the stage it starts' if self.initial.use == 'start' else 'None (no stage runs)'}, got "
                f"{self.affine}"
            )


@contextmanager
def _timed(timings: dict[str, float], name: str, report: Callable[[str, float], None] | None) -> Iterator[None]:
    start = time.perf_counter()
    yield
    timings[name] = round(time.perf_counter() - start, 3)
    if report is not None:
        report(name, timings[name])


def _describe(volume: Volume) -> dict:
    return {
        "path": str(Path(volume.path).resolve()),
        "shape": list(volume.shape),
        "spacing_mm": np.round(volume.spacing, 4).tolist(),
        "orientation": volume.axcodes,
        "value_range": [float(volume.array.min()), float(volume.array.max())],
    }


def _reproducibility(model: LoadedModel, options: RegistrationOptions) -> dict:
    """What the same outputs need besides the inputs (monai_probreg.utils.provenance): the seeds (the command gives
    ``--seed`` to both), whether the affine metric ran in one work unit, the weights' hash and the library versions.
    The other options are in the summary's ``affine.settings``, ``model`` and ``uncertainty``."""
    affine = options.affine
    return {
        "seed": options.seed,
        "affine_seed": affine.seed if affine else None,
        "deterministic_affine": affine.deterministic if affine else None,
        "weights_sha256": model.weights_sha256,
        "versions": library_versions(),
    }


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _dice(warped: np.ndarray, fixed: Volume, ids: list[int]) -> dict:
    per_label = label_dice(torch.from_numpy(warped), torch.from_numpy(fixed.array), ids)  # read in chunks, no copy
    mean = mean_dice(per_label)
    return {
        "mean": None if math.isnan(mean) else mean,  # JSON has no NaN: null
        "per_label": {str(k): (None if math.isnan(v) else round(v, 5)) for k, v in per_label.items()},
    }


class _QualityInputs(NamedTuple):
    """A registration on the model grid as the quality estimate reads it: the network's own before refinement (what
    its models read, :mod:`monai_probreg.uncertainty.quality`, "Whose features"), or the refined answer."""

    warped: np.ndarray
    displacement: np.ndarray
    jacobian: np.ndarray
    entropy: np.ndarray


@dataclass
class _ModelMaps:
    """The network's results on the model grid: displacement and inverse (3, *S) voxels, maps (*S)."""

    displacement: np.ndarray
    inverse: np.ndarray | None  # None: not asked for (RegistrationOptions.inverse)
    jacobian: np.ndarray
    entropy: np.ndarray | None  # velocity entropy, filled in by _run_model (with the samples when there are any)
    warped: np.ndarray
    network: RegistrationOutput | None = None  # the network's own registration when refined (the quality reads it)
    # the answer's velocity (mean, log-variance), kept for the quality estimate's entropy (None without a quality model)
    posterior: tuple[torch.Tensor, torch.Tensor] | None = None
    std: np.ndarray | None = None
    variance: np.ndarray | None = None  # (3, *S) mm^2 per model-grid axis, with the samples


def _run_model(
    model: LoadedModel,
    moving_input: np.ndarray,
    fixed_input: np.ndarray,
    options: RegistrationOptions,
    spacing: np.ndarray,
    timings: dict,
    report: Callable | None,
    masks: RefinementMasks | None = None,
) -> _ModelMaps:
    shape, samples, seed = moving_input.shape, options.samples, options.seed
    moving_t = torch.from_numpy(moving_input)[None, None].to(model.device)
    fixed_t = torch.from_numpy(fixed_input)[None, None].to(model.device)
    with _timed(timings, "model", report):
        output = register_pair(model.network, moving_t, fixed_t)  # eval mode: the posterior mean velocity
    network_output = None
    if options.refinement.enabled:
        with _timed(timings, "refine", report), eval_mode(model.network):
            network_output = output if model.quality is not None else None  # kept only for the quality estimate
            if masks is not None:
                masks = RefinementMasks(
                    *(None if m is None else torch.from_numpy(m)[None, None].to(model.device) for m in masks)
                )
            output = refine_registration(model.network, moving_t, fixed_t, output, options.refinement, masks)
    with _timed(timings, "maps", report):
        inverse = None
        if options.inverse:
            with eval_mode(model.network), torch.inference_mode():
                inverse = _numpy(model.network.velocity_to_displacement(-output.velocity_mean, shape)[0])  # exp(-v)
        maps = _ModelMaps(
            _numpy(output.displacement[0]),
            inverse,
            _numpy(jacobian_determinant(output.displacement)[0]),
            None,
            _numpy(output.warped[0, 0]),
            network=network_output,
            posterior=None if model.quality is None else (output.velocity_mean, output.velocity_log_var),
        )
        residual = None  # the pair's residual, for the calibration's residual term (uncertainty.residual)
        if model.calibration.residual_weight > 0:
            residual = residual_variance(output.warped, fixed_t, output.velocity_mean.shape[2:])
        if not samples:  # with samples, the sampled call below gives the entropy too: computed once either way
            maps.entropy = _entropy(
                model, output.velocity_mean, output.velocity_log_var, shape, model.calibration, residual
            )
    if samples:
        with _timed(timings, "samples", report):
            sampled = posterior_maps(
                model.network,
                output.velocity_mean,
                output.velocity_log_var,
                shape,
                samples,
                model.std_scale,
                seed=seed,
                bias_fraction=model.bias_fraction,
                spacing=spacing,
                residual=residual,
                residual_weight=model.calibration.residual_weight,
            )
            maps.entropy, maps.std = _numpy(sampled.velocity_entropy), _numpy(sampled.displacement_std)
            maps.variance = _numpy(sampled.displacement_variance)
    return maps


def _feature_entropy(model: LoadedModel, maps: _ModelMaps, posterior: tuple[torch.Tensor, torch.Tensor]) -> np.ndarray:
    """The velocity entropy of ``posterior`` (mean, log-variance) as the quality estimate reads it: under the quality
    model's own calibration (:meth:`~monai_probreg.uncertainty.quality.QualityModel.feature_calibration`); the maps'
    entropy itself when ``posterior`` is the answer's and that calibration is the one in use (computed once)."""
    calibration = model.quality.feature_calibration(model.std_scale, model.bias_fraction)
    if (
        posterior is maps.posterior
        and model.calibration.residual_weight == 0  # the maps' entropy has no residual term, the feature's never has
        and calibration == Calibration(model.std_scale, model.bias_fraction)
    ):
        return maps.entropy
    return _entropy(model, *posterior, tuple(maps.warped.shape), calibration)


def _network_quality_inputs(model: LoadedModel, output: RegistrationOutput, maps: _ModelMaps) -> _QualityInputs:
    """The network's registration ``output`` (before refinement) as the quality estimate reads it."""
    return _QualityInputs(
        _numpy(output.warped[0, 0]),
        _numpy(output.displacement[0]),
        _numpy(jacobian_determinant(output.displacement)[0]),
        _feature_entropy(model, maps, (output.velocity_mean, output.velocity_log_var)),
    )


def _entropy(
    model: LoadedModel,
    mean: torch.Tensor,
    log_var: torch.Tensor,
    shape: tuple[int, ...],
    calibration: Calibration,
    residual: torch.Tensor | None = None,
) -> np.ndarray:
    """The velocity entropy of the posterior (``mean``, ``log_var``) on ``shape`` under ``calibration`` (std_scale 1,
    bias 0 = raw; its residual term with ``residual``, which it then needs)."""
    posterior = posterior_maps(
        model.network,
        mean,
        log_var,
        shape,
        std_scale=calibration.std_scale,
        bias_fraction=calibration.bias_fraction,
        residual=residual,
        residual_weight=calibration.residual_weight,
    )
    return _numpy(posterior.velocity_entropy)


def _quality(
    model: LoadedModel, moving_input: np.ndarray, fixed: FixedSpace, maps: _ModelMaps
) -> tuple[QualityFeatures, QualityEstimate, QualityFeatures | None] | None:
    """The label-free quality estimate on the model grid (:mod:`monai_probreg.uncertainty.quality`): the features of
    the network's registration, the estimate, and the features of the refined answer (None: not refined); None when
    the weights have no quality model."""
    if model.quality is None:
        return None
    t = torch.from_numpy

    def features_of(m: _QualityInputs) -> QualityFeatures:
        return quality_features(
            t(moving_input),
            t(fixed.model_input),
            t(m.warped),
            t(m.displacement),
            t(m.entropy),
            fixed.grid.spacing,
            jacobian=t(m.jacobian),
        )

    # the answer the user gets; its entropy as the estimate reads it (the same rule for both feature sets)
    answer = features_of(
        _QualityInputs(maps.warped, maps.displacement, maps.jacobian, _feature_entropy(model, maps, maps.posterior))
    )
    if maps.network is None:  # not refined: the answer is the network's own registration
        return answer, model.quality.estimate(answer), None
    features = features_of(_network_quality_inputs(model, maps.network, maps))
    return features, model.quality.estimate(features, answer), answer


def _quality_summary(
    model: LoadedModel,
    quality: tuple[QualityFeatures, QualityEstimate, QualityFeatures | None] | None,
    refinement: RefinementSettings,
) -> dict | None:
    if quality is None:
        return None
    record = quality_record(*quality)  # strict JSON, the same record as the bundle's
    del record["warning"]  # summary.json has it at the top level
    return {
        **record,
        "warning_threshold": model.quality.threshold,
        "definition": model.quality.definition,
        "model": quality_path(model.model_file).name,
        "refinement_differs_from_fit": refinement.differences(model.quality.refinement),
    }


@dataclass
class _Composed:
    """Everything on the fixed grid (and the inverse on the moving grid) that is written."""

    warp: np.ndarray
    inverse_warp: np.ndarray | None  # None: not asked for (RegistrationOptions.inverse)
    maps: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    dice: dict | None


def _compose(
    fixed: FixedSpace,
    moving: Volume,
    moving_label: Volume | None,
    affine: np.ndarray,
    model_maps: _ModelMaps,
    inverse: bool,
) -> _Composed:
    """Affine + deformable -> one field each way; the original scan and labels resampled once; Dice
    (:mod:`monai_probreg.cli.compose`, slab by slab). ``model_maps.inverse`` is consumed: set to None once read, so
    that the model grid's inverse (200 MB at 256^3) is not held beside the composed one."""
    grid = fixed.grid
    forward = forward_outputs(grid, fixed.image, moving, moving_label, affine, model_maps.displacement)
    maps = {
        "warped": forward.warped,
        "jacobian": grid.to_fixed(model_maps.jacobian),
        "entropy": grid.to_fixed(model_maps.entropy),
    }
    if model_maps.std is not None:
        maps["displacement_std"] = grid.to_fixed(model_maps.std)
    labels = dict(forward.labels)
    inverse_warp = None
    if inverse:
        backward = inverse_outputs(grid, model_maps.inverse, affine, moving, fixed.label)
        model_maps.inverse = None
        inverse_warp = backward.warp
        if backward.fixed_label is not None:
            labels["fixed_label_in_moving"] = backward.fixed_label
    dice = None
    if moving_label is not None and fixed.label is not None:
        # the structures both label maps have (a moving map of another protocol, e.g. LPBA40's 48 cortical labels
        # against the atlas' 56, is not charged for the labels it never had)
        ids = sorted(set(fixed.label_ids) & {int(v) for v in np.unique(moving_label.array) if v != 0})
        if ids:  # else no Dice (summary "dice": null): the two maps share no structure
            dice = _dice(labels["warped_label"], fixed.label, ids)
            affine_only = _dice(labels["affine_label"], fixed.label, ids)
            dice.update(
                mean_affine_only=affine_only["mean"],
                per_label_affine_only=affine_only["per_label"],
                labels="the non-zero labels of both label maps",
                num_fixed_only_labels=len(fixed.label_ids) - len(ids),
            )
    return _Composed(forward.warp, inverse_warp, maps, labels, dice)


_MAP_FILES = ("jacobian", "entropy", "displacement_std")  # left out by RegistrationOptions.maps = False


class Registered(NamedTuple):
    """What :func:`register_scan` computed, for a caller's own check of the result (its ``check``).

    ``warp`` (*S, 3): the composed ``D(p) = phi(p) - p``, LPS mm on the fixed grid, float32 (``warp.nii.gz``'s
    values); ``affine`` (4, 4): the affine stage, fixed LPS -> moving LPS; ``points`` (*S, 3): the fixed grid's LPS
    points;
    ``displacement_variance`` (*S, 3): the calibrated posterior's variance of the deformable displacement, mm^2 on
    the fixed grid, one component per column of ``variance_axes`` (3, 3; unit LPS vectors: the model grid's axes),
    or None without samples."""

    warp: np.ndarray
    affine: np.ndarray
    points: np.ndarray
    displacement_variance: np.ndarray | None
    variance_axes: np.ndarray


def _model_grid_masks(
    fixed: FixedSpace, moving_mask: Volume | None, affine: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None] | None:
    """The refinement's masks on the model grid, float32 0/1 (:class:`~monai_probreg.engines.refinement.RefinementMasks`
    as arrays), or None without any: the fixed mask re-indexed (exact; the padding outside), the moving mask carried
    onto the fixed grid through the affine as the scan is (linear, 0 beyond its grid, inside from
    :data:`~monai_probreg.spatial.masks.MASK_LEVEL`)."""
    if fixed.mask is None and moving_mask is None:
        return None
    grid = fixed.grid
    fixed_part = None if fixed.mask is None else grid.to_model(fixed.mask.array.astype(np.float32))
    moving_part = None
    if moving_mask is not None:
        on_fixed = affine_resample(
            moving_mask.with_array(moving_mask.array.astype(np.float32)), fixed.image, affine, 0.0
        )
        moving_part = grid.to_model((on_fixed >= MASK_LEVEL).astype(np.float32))
    return fixed_part, moving_part


def _registered(fixed: FixedSpace, affine: AffineResult, composed: _Composed, model_maps: _ModelMaps) -> Registered:
    grid = fixed.grid
    variance = None if model_maps.variance is None else grid.to_fixed(np.moveaxis(model_maps.variance, 0, -1))
    return Registered(composed.warp, affine.matrix, fixed.points, variance, grid.index_to_lps[:3, :3] / grid.spacing)


def _writers(
    stage: Path,
    fixed: FixedSpace,
    moving: Volume,
    affine: AffineResult,
    composed: _Composed,
    options: RegistrationOptions,
) -> list[Callable[[], object]]:
    """One call per output file (run in parallel by :func:`~monai_probreg.utils.files.parallel_writes`), largest
    first so that the pool's last file is a small one."""
    writers: list[tuple[int, Callable[[], object]]] = []
    if composed.inverse_warp is not None:
        writers.append(
            (
                composed.inverse_warp.size,
                functools.partial(
                    write_field, stage / "inverse_warp.nii.gz", composed.inverse_warp, moving.index_to_lps
                ),
            )
        )
    writers.append(
        (
            composed.warp.size,
            functools.partial(write_field, stage / "warp.nii.gz", composed.warp, fixed.image.index_to_lps),
        )
    )
    for name, array in composed.maps.items():
        if options.maps or name not in _MAP_FILES:
            writers.append(
                (
                    array.size,
                    functools.partial(
                        write_volume,
                        stage / f"{name}.nii.gz",
                        fixed.image.with_array(array.astype(np.float32, copy=False)),
                    ),
                )
            )
    for name, grid in (("warped_label", fixed.image), ("fixed_label_in_moving", moving)):
        if name in composed.labels:
            array = composed.labels[name]
            writers.append(
                (
                    array.size // 4,
                    functools.partial(  # bytes, roughly: 1-2 per label voxel, 4 per float
                        write_volume, stage / f"{name}.nii.gz", grid.with_array(array), label_dtype(array)
                    ),
                )
            )
    writers.append((0, functools.partial(write_transform, stage / "affine.tfm", affine.matrix, affine.center)))
    return [write for _, write in sorted(writers, key=lambda item: -item[0])]


def _qc_data(
    fixed: FixedSpace,
    moving_input: np.ndarray,
    model_maps: _ModelMaps,
    composed: _Composed,
    title: str,
    warning: str | None = None,
) -> QCData:
    to_model, labels = fixed.grid.to_model, composed.labels
    sampled = model_maps.std is not None
    return QCData(
        fixed=fixed.model_input,
        moving=moving_input,
        warped=model_maps.warped,
        displacement=model_maps.displacement,
        jacobian=model_maps.jacobian,
        uncertainty=model_maps.std if sampled else model_maps.entropy,
        uncertainty_name="displacement std (mm)" if sampled else "velocity entropy",
        spacing=tuple(fixed.grid.spacing),
        title=title,
        warning=warning,
        fixed_label=to_model(fixed.label.array) if fixed.label is not None else None,
        moving_label=to_model(labels["affine_label"]) if "affine_label" in labels else None,
        warped_label=to_model(labels["warped_label"]) if "warped_label" in labels else None,
    )


def _qc_title(
    moving: Volume,
    dice: dict | None,
    num_folding: int,
    quality: tuple[QualityFeatures, QualityEstimate, QualityFeatures | None] | None,
) -> str:
    title = Path(moving.path).name + (
        f"   mean Dice {dice['mean']:.3f} (affine only {dice['mean_affine_only']:.3f})" if dice else ""
    )
    title += f"   |J| <= 0: {num_folding} voxels"
    if quality is not None:
        title += f"   predicted Dice {quality[1].predicted_dice:.2f}"
    return title


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
    start = time.perf_counter()
    with _timed(timings, "read", report):
        moving = moving_path if isinstance(moving_path, Volume) else read_image(moving_path, "--moving")
        moving_label = read_label(moving_label_path, "--moving-label") if moving_label_path is not None else None
        if moving_label is not None:
            check_same_grid(moving_label, moving, "--moving-label", "--moving")
        moving_mask = None
        if moving_mask_path is not None:
            moving_mask = read_mask(moving_mask_path, "--moving-mask", moving, "--moving")
    initial = options.initial
    with _timed(timings, "affine", report):
        if initial is not None and initial.use == "as-affine":
            affine = AffineResult(initial.matrix, initial.center, initial.matrix, [])
        elif options.affine is None:
            affine = AffineResult(np.eye(4), np.zeros(3), np.eye(4), [])
        else:
            affine = align(
                fixed.image,
                moving,
                options.affine,
                fixed.itk_image if options.affine.backend == "itk" else None,
                fixed.samples_for(options.affine),
                None if initial is None else initial.matrix,
                fixed.mask,
                moving_mask,
            )
    with _timed(timings, "resample", report):
        background = float(moving.array.min())
        moving_on_fixed = affine_resample(moving, fixed.image, affine.matrix, background)
        moving_input = fixed.grid.to_model(
            normalise_intensity(hide_outside(moving_on_fixed, fixed.brain_mask, background))
        )
        del moving_on_fixed
        masks = _model_grid_masks(fixed, moving_mask, affine.matrix)
    model_maps = _run_model(model, moving_input, fixed.model_input, options, fixed.grid.spacing, timings, report, masks)
    quality = None
    if model.quality is not None:  # weights without a quality model: no stage, "quality": null
        with _timed(timings, "quality", report):
            quality = _quality(model, moving_input, fixed, model_maps)
    model_maps.network = None  # read by the quality estimate only: its fields (about 300 MB at 256^3) go now
    warning = quality[1].warning if quality is not None else None
    with _timed(timings, "compose", report):
        composed = _compose(fixed, moving, moving_label, affine.matrix, model_maps, options.inverse)
        stats = jacobian_stats(torch.from_numpy(composed.maps["jacobian"]))
    checked = check(_registered(fixed, affine, composed, model_maps)) if check is not None else {}
    with staged_output_dir(out, overwrite) as stage:
        # the files compress in a pool of threads while this thread draws the QC figure: "qc" is the drawing,
        # "write" the wait for the files after it (so the stages still add up to the wall time)
        write_start = time.perf_counter()
        with parallel_writes(torch.get_num_threads()) as submit:
            for writer in _writers(stage, fixed, moving, affine, composed, options):
                submit(writer)
            for name, write in (extra_outputs or {}).items():
                submit(functools.partial(write, stage / name))
            if options.qc:
                with _timed(timings, "qc", report):
                    save_qc(
                        stage / "qc.png",
                        _qc_data(
                            fixed,
                            moving_input,
                            model_maps,
                            composed,
                            _qc_title(moving, composed.dice, stats.num_folding, quality),
                            warning,
                        ),
                    )
        timings["write"] = round(time.perf_counter() - write_start - timings.get("qc", 0.0), 3)
        if report is not None:
            report("write", timings["write"])
        timings["total"] = round(time.perf_counter() - start, 3)
        jacobian, std = composed.maps["jacobian"], model_maps.std
        summary = {
            "moving": _describe(moving),
            "fixed": _describe(fixed.image),
            "moving_label": moving_label.path if moving_label is not None else None,
            "fixed_label": fixed.label.path if fixed.label is not None else None,
            "model": {
                "model_file": str(model.model_file),
                "config": str(model.config_file),
                "device": str(model.device),
                "model_grid_shape": list(fixed.grid.shape),
                "divisor": model.divisor,
                "posterior_std_scale": model.std_scale,
                "posterior_bias_fraction": model.bias_fraction,
                # the posterior the maps are drawn from: the network's spread around the answer's mean, widened where
                # the registered pair stays unlike by this weight (uncertainty.residual; 0: the network's alone)
                "posterior_residual_weight": model.calibration.residual_weight,
                "posterior_interval_dof": model.interval_dof,  # Student-t dof of the intervals; None: Gaussian
                # the calibrated 95% interval of one displacement component is +- this many times that component's
                # std (displacement_std.nii.gz is the root-sum-square of the 3 components' stds)
                "posterior_interval_95_half_width_std": round(interval_z(0.95, model.interval_dof), 4),
                # this run's refinement settings where they differ from those the calibration was fitted around
                # (the maps are calibrated for that mean); None: the raw posterior, or a sidecar that does not say
                "calibration_refinement_differs_from_fit": None
                if model.calibration_refinement is None
                else options.refinement.differences(model.calibration_refinement),
                "refinement": options.refinement.as_dict(),
                "brain_mask": None
                if fixed.brain_mask is None
                else {
                    "margin_mm": fixed.brain_mask_margin_mm,
                    "fraction_of_fixed_grid": round(float(fixed.brain_mask.mean()), 4),
                    "support": "the fixed image above its minimum" if fixed.mask is None else "--fixed-mask",
                },
            },
            "timings_s": timings,
            # the cost-function masks (--fixed-mask, --moving-mask): where the affine metric and the refinement's
            # image term looked; null each without one
            "masks": {"fixed": mask_record(fixed.mask), "moving": mask_record(moving_mask)},
            "affine": {
                **affine.summary(),
                "settings": options.affine.as_dict() if options.affine else None,
                "initial_transform": None if initial is None else initial.summary(),
            },
            "jacobian": {
                "num_nonpositive": stats.num_folding,
                "percent_nonpositive": stats.percent_folding,
                "std_log_jacobian": stats.std_log_jacobian,
                "min": float(jacobian.min()),
                "max": float(jacobian.max()),
            },
            "dice": composed.dice,
            # the refinement's similarity guard gave the deformation up (it left the images less alike than the
            # affine alone): warp.nii.gz is the affine alone
            "deformation_given_up": bool(
                options.refinement.enabled and options.refinement.similarity_guard and not model_maps.displacement.any()
            ),
            "quality": _quality_summary(model, quality, options.refinement),
            "warning": warning,
            "uncertainty": {
                "samples": options.samples,
                "seed": options.seed,
                "mean_displacement_std_mm": None if std is None else float(std.mean()),
            },
            "outputs": sorted(p.name for p in stage.iterdir()) + ["summary.json", "README.txt"],
            "version": monai_probreg.__version__,
            "reproducibility": _reproducibility(model, options),
        }
        clash = set(checked) & set(summary)
        if clash:
            raise ValueError(f"check() returned keys the summary has already: {sorted(clash)}")
        summary.update(checked)
        write_text(stage / "summary.json", json.dumps(summary, indent=2) + "\n")
        write_text(stage / "README.txt", OUTPUTS_README)
    return summary
