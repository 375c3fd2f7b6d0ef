"""The network's stages of one registration, on the model grid (the moving scan as :mod:`.affine_stage` made it):

- ``model``: the network's posterior mean velocity -> displacement and the warped scan (network, integration, warp;
  :func:`monai_probreg.engines.registration.register_pair`; :func:`register_network`);
- ``refine``: with the options' ``refinement`` enabled, that mean refined for the pair
  (:mod:`monai_probreg.engines.refinement`), its image term inside the cost-function masks when given
  (:func:`run_network`, as the stages below; the caller reads what it needs of the network's own registration before,
  :func:`~.quality_estimate.network_quality_features`, and does not keep it);
- ``maps``: the Jacobian and the velocity entropy; then, after the quality estimate, the inverse displacement
  (``exp(-v)``; unless ``inverse`` is off; :func:`add_inverse`), so that it is not held beside the quality estimate's
  working set and the network's own registration;
- ``samples``: with ``samples = K >= 2``, the displacement standard deviation, first order (no sampling:
  :func:`monai_probreg.uncertainty.posterior_maps.posterior_maps`, calibrated as the model is; the stage keeps its
  name from when the map was sampled).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field

import numpy as np
import torch
from monai.networks.utils import eval_mode

from monai_probreg.engines.refinement import RefinementMasks, refine_registration
from monai_probreg.engines.registration import register_pair
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.uncertainty.calibration import Calibration
from monai_probreg.uncertainty.error_model import error_features, pair_term
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.utils.tensors import float_numpy

__all__ = ["ModelMaps", "add_inverse", "posterior_entropy", "register_network", "run_network"]


@dataclass
class ModelMaps:
    """The network's results on the model grid: displacement and inverse (3, *S) voxels, maps (*S).

    A registration lets each volume go (None) once nothing left reads it (:func:`~.scan.register_scan`; the compose
    stage consumes the ones it reads, :func:`~.compose.compose_outputs`); ``deformed`` (whether the displacement
    moves any voxel) outlives them."""

    displacement: np.ndarray
    inverse: np.ndarray | None  # None: not asked for (RegistrationOptions.inverse), or not yet made (add_inverse)
    jacobian: np.ndarray
    entropy: np.ndarray | None  # velocity entropy, filled in by run_network (with the samples when there are any)
    warped: np.ndarray
    # the answer's velocity (mean, log-variance), kept for the quality estimate's entropy (None without a quality model)
    posterior: tuple[torch.Tensor, torch.Tensor] | None = None
    std: np.ndarray | None = None
    variance: np.ndarray | None = None  # (3, *S) mm^2 per model-grid axis, with the samples
    deformed: bool = field(init=False)  # any voxel moved (the summary's "deformation_given_up" reads it)
    velocity: torch.Tensor | None = None  # the answer's mean velocity, until add_inverse makes the inverse from it
    # (F, *S) the pair's error-model features (RegistrationOptions.error_features), or None
    error_features: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.deformed = bool(self.displacement.any())


def _image_tensor(image: np.ndarray, model: LoadedModel) -> torch.Tensor:
    """A model-grid image (*S) as the network reads it: (1, 1, *S) on the model's device (no copy on a CPU)."""
    return torch.from_numpy(image)[None, None].to(model.device)


def register_network(
    model: LoadedModel,
    moving_input: np.ndarray,
    fixed_input: np.ndarray,
    stage: Callable[[str], AbstractContextManager],
) -> RegistrationOutput:
    """The ``model`` stage, inside ``stage("model")`` (the caller's clock): the network's own registration."""
    with stage("model"):  # eval mode: the posterior mean velocity
        return register_pair(model.network, _image_tensor(moving_input, model), _image_tensor(fixed_input, model))


def run_network(
    model: LoadedModel,
    output: RegistrationOutput,
    moving_input: np.ndarray,
    fixed_input: np.ndarray,
    options: RegistrationOptions,
    spacing: np.ndarray,
    stage: Callable[[str], AbstractContextManager],
    masks: tuple[np.ndarray | None, np.ndarray | None] | None = None,
) -> ModelMaps:
    """The stages after ``model`` (module docstring) from the network's registration ``output``
    (:func:`register_network`), each run inside ``stage(name)`` (the caller's clock); ``masks``: the refinement's
    (fixed, moving) on the model grid (:class:`~.affine_stage.ModelInput`), or None."""
    shape, samples, seed = moving_input.shape, options.samples, options.seed
    moving_t, fixed_t = _image_tensor(moving_input, model), _image_tensor(fixed_input, model)
    if options.refinement.enabled:
        with stage("refine"), eval_mode(model.network):
            if masks is not None:
                masks = RefinementMasks(
                    *(None if m is None else torch.from_numpy(m)[None, None].to(model.device) for m in masks)
                )
            output = refine_registration(model.network, moving_t, fixed_t, output, options.refinement, masks)
    with stage("maps"):
        maps = ModelMaps(
            float_numpy(output.displacement[0]),
            None,  # add_inverse's, later
            float_numpy(jacobian_determinant(output.displacement)[0]),
            None,
            float_numpy(output.warped[0, 0]),
            posterior=None if model.quality is None else (output.velocity_mean, output.velocity_log_var),
            velocity=output.velocity_mean if options.inverse else None,
        )
        pair = (output.warped, fixed_t, output.velocity_mean, output.velocity_log_var, output.displacement)
        residual = None  # the map the calibration's term weighs (uncertainty.error_model.pair_term)
        if model.calibration.residual_weight > 0:
            residual = pair_term(model.calibration.error_model, *pair)
        if options.error_features:  # for a caller fitting the error model (fitting.error_cases)
            maps.error_features = float_numpy(error_features(*pair)[0])
        if not samples:  # with samples, the sampled call below gives the entropy too: computed once either way
            maps.entropy = posterior_entropy(
                model, output.velocity_mean, output.velocity_log_var, shape, model.calibration, residual
            )
    if samples:
        with stage("samples"):
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
                sample_gain=model.calibration.sample_gain,
                interval_dof=model.calibration.interval_dof,
            )
            maps.entropy, maps.std = float_numpy(sampled.velocity_entropy), float_numpy(sampled.displacement_std)
            maps.variance = float_numpy(sampled.displacement_variance)
    return maps


def add_inverse(model: LoadedModel, maps: ModelMaps) -> None:
    """The inverse displacement ``exp(-v)`` of ``maps.velocity`` (the answer's mean velocity; None: the inverse was
    not asked for, nothing to do) on the maps' grid into ``maps.inverse``; the velocity is let go."""
    if maps.velocity is None:
        return
    with eval_mode(model.network), torch.inference_mode():
        shape = tuple(maps.displacement.shape[1:])
        maps.inverse = float_numpy(model.network.velocity_to_displacement(-maps.velocity, shape)[0])
    maps.velocity = None


def posterior_entropy(
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
    return float_numpy(posterior.velocity_entropy)
