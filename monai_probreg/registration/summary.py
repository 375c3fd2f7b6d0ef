"""``summary.json`` of one registration: the inputs and the model, the stages' times, the affine, the Jacobian's
statistics, Dice, the quality estimate and its warning, the uncertainty settings, the files written and what the same
outputs need besides the inputs (the reproducibility record)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import monai_probreg
from monai_probreg.metrics.calibration import interval_z
from monai_probreg.metrics.jacobian import JacobianStats
from monai_probreg.registration.compose import Composed
from monai_probreg.registration.inputs import FixedSpace, MovingScan
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.network import ModelMaps
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.quality_estimate import ScanQuality, quality_summary, why_no_quality
from monai_probreg.spatial.affine import AffineResult
from monai_probreg.spatial.masks import mask_record
from monai_probreg.spatial.volume_io import Volume
from monai_probreg.uncertainty.residual import residual_form
from monai_probreg.utils.provenance import library_versions

__all__ = ["scan_summary"]


def scan_summary(
    model: LoadedModel,
    fixed: FixedSpace,
    moving: MovingScan,
    options: RegistrationOptions,
    affine: AffineResult,
    model_maps: ModelMaps,
    composed: Composed,
    stats: JacobianStats,
    quality: ScanQuality | None,
    timings: dict[str, float],
    outputs: list[str],
) -> dict:
    """The summary (strict JSON) of a registration run with ``options`` (their ``refinement`` set), ``outputs``
    being the names of the files written."""
    jacobian, std = composed.maps["jacobian"], model_maps.std
    return {
        "moving": _describe(moving.image),
        "fixed": _describe(fixed.image),
        "moving_label": moving.label.path if moving.label is not None else None,
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
            # ... per unit of this residual: its boxes in voxels (uncertainty.residual.residual_form; None: no term)
            "posterior_residual_form": residual_form() if model.calibration.residual_weight > 0 else None,
            # what the term reads: "error model" (the predicted squared error from the pair's features,
            # uncertainty.error_model), "residual" (the pair's residual itself) or None (no term)
            "posterior_term": None
            if model.calibration.residual_weight == 0
            else "residual"
            if model.calibration.error_model is None
            else "error model",
            # how displacement_std.nii.gz is made: "first order", the calibrated velocity std resized onto the grid
            # (uncertainty.spread; no sampling; older bundles wrote the std of K samples)
            "displacement_std": "first order",
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
            # --match-contrast: the moving scan mapped onto the fixed image's contrast over this many bins before the
            # network read it (monai_probreg.spatial.contrast); 0: as it is
            "contrast_match_bins": options.contrast_match_bins,
            "contrast": options.contrast,  # --contrast: "same" or "other" (the refinement's settings for it above)
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
        "masks": {"fixed": mask_record(fixed.mask), "moving": mask_record(moving.mask)},
        "affine": {
            **affine.summary(),
            "settings": options.affine.as_dict() if options.affine else None,
            "initial_transform": None if options.initial is None else options.initial.summary(),
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
            options.refinement.enabled and options.refinement.similarity_guard and not model_maps.deformed
        ),
        "quality": quality_summary(model, quality, options.refinement),
        "quality_not_estimated": why_no_quality(model, options),  # why "quality" is null (None: it is not)
        "warning": None if quality is None else quality.estimate.warning,
        "uncertainty": {
            "samples": options.samples,
            "seed": options.seed,
            "mean_displacement_std_mm": None if std is None else float(std.mean()),
        },
        "outputs": outputs,
        "version": monai_probreg.__version__,
        "reproducibility": _reproducibility(model, options),
    }


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
