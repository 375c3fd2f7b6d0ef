"""The ``quality`` stage of one registration: the label-free quality estimate on the model grid
(:mod:`monai_probreg.uncertainty.quality`), read from the network's own registration before refinement (what its
models were fitted on: docs/uncertainty.md, "Whose features"; read as soon as the network has run,
:func:`network_quality_features`), with the refined answer's features beside it (:func:`estimate_quality`); and its
record in ``summary.json``. Weights without a quality model have no stage (``"quality": null``), and neither has a
pair of two contrasts (``--contrast other``; :func:`why_no_quality` says why, in ``summary.json``): the models were
fitted on pairs of one contrast, with scans of an inverted contrast among their failures, so they call every pair of
two contrasts failed, whatever its alignment (docs/accuracy.md, "Another contrast")."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.network import ModelMaps, posterior_entropy
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.uncertainty.quality import QualityEstimate, quality_path, quality_record
from monai_probreg.uncertainty.quality_features import QualityFeatures, quality_features
from monai_probreg.utils.tensors import float_numpy

__all__ = [
    "NO_QUALITY_MODEL",
    "NO_QUALITY_OTHER_CONTRAST",
    "ScanQuality",
    "estimate_quality",
    "network_quality_features",
    "quality_summary",
    "why_no_quality",
]

# each reason reads "<short label>: <the whole reason>"; the command prints the label (cli.messages.summary_line)
NO_QUALITY_MODEL = "no quality model"  # ": no <weights stem>.quality.json beside <weights>" follows
NO_QUALITY_OTHER_CONTRAST = (
    "--contrast other: the quality models were fitted on pairs of one contrast, with another contrast among their "
    "failures; they would call this pair failed whatever its alignment (check qc.png)"
)


def why_no_quality(model: LoadedModel, options: RegistrationOptions) -> str | None:
    """Why no quality estimate is made for a registration with ``options`` (module docstring), or None when it is:
    the one rule for whether the ``quality`` stage runs."""
    if model.quality is None:
        return f"{NO_QUALITY_MODEL}: no {quality_path(model.model_file).name} beside {model.model_file}"
    if options.contrast != "same":
        return NO_QUALITY_OTHER_CONTRAST
    return None


class ScanQuality(NamedTuple):
    """``features`` of the network's registration (what the estimate reads), the ``estimate``, and the
    ``answer_features`` of the refined answer (None: not refined, the answer is the network's own)."""

    features: QualityFeatures
    estimate: QualityEstimate
    answer_features: QualityFeatures | None


class _QualityInputs(NamedTuple):
    """A registration on the model grid as the quality estimate reads it: the network's own before refinement (what
    its models read, :mod:`monai_probreg.uncertainty.quality`, "Whose features"), or the refined answer."""

    warped: np.ndarray
    displacement: np.ndarray
    jacobian: np.ndarray
    entropy: np.ndarray


def _feature_entropy(
    model: LoadedModel, posterior: tuple[torch.Tensor, torch.Tensor], shape: tuple[int, ...], maps: ModelMaps | None
) -> np.ndarray:
    """The velocity entropy of ``posterior`` (mean, log-variance) on ``shape`` as the quality estimate reads it: under
    the quality model's own calibration (:meth:`~monai_probreg.uncertainty.quality.QualityModel.feature_calibration`);
    the ``maps``' entropy itself when ``posterior`` is their answer's and that calibration is the one in use (computed
    once)."""
    calibration = model.quality.feature_calibration(model.std_scale, model.bias_fraction)
    # an entropy depends on every number of the calibration but the intervals' dof and the samples' gain (the
    # feature's has no residual term)
    if (
        maps is not None
        and posterior is maps.posterior
        and calibration._replace(interval_dof=None, sample_gain=1.0)
        == model.calibration._replace(interval_dof=None, sample_gain=1.0)
    ):
        return maps.entropy
    return posterior_entropy(model, *posterior, shape, calibration)


def _features(model: LoadedModel, moving_input: np.ndarray, fixed: FixedSpace, inputs: _QualityInputs):
    t = torch.from_numpy
    return quality_features(
        t(moving_input),
        t(fixed.model_input),
        t(inputs.warped),
        t(inputs.displacement),
        t(inputs.entropy),
        fixed.grid.spacing,
        jacobian=t(inputs.jacobian),
    )


def network_quality_features(
    model: LoadedModel, moving_input: np.ndarray, fixed: FixedSpace, output: RegistrationOutput
) -> QualityFeatures:
    """The features of the network's own registration ``output`` (before refinement: what the quality models read),
    for :func:`estimate_quality` once the answer is made; read as soon as the network has run, so that the
    caller need not keep ``output`` (its displacement and warped image) beside the refinement's answer."""
    shape = tuple(moving_input.shape)
    inputs = _QualityInputs(
        float_numpy(output.warped[0, 0]),
        float_numpy(output.displacement[0]),
        float_numpy(jacobian_determinant(output.displacement)[0]),
        _feature_entropy(model, (output.velocity_mean, output.velocity_log_var), shape, None),
    )
    return _features(model, moving_input, fixed, inputs)


def estimate_quality(
    model: LoadedModel,
    moving_input: np.ndarray,
    fixed: FixedSpace,
    maps: ModelMaps,
    network_features: QualityFeatures | None = None,
) -> ScanQuality | None:
    """The label-free quality estimate on the model grid (module docstring) of the answer ``maps``, with the
    network's own registration's ``network_features`` when the answer was refined (:func:`network_quality_features`;
    None: not refined, the answer is the network's own); None when the weights have no quality model."""
    if model.quality is None:
        return None
    # the answer the user gets; its entropy as the estimate reads it (the same rule for both feature sets)
    entropy = _feature_entropy(model, maps.posterior, tuple(maps.warped.shape), maps)
    answer = _features(
        model, moving_input, fixed, _QualityInputs(maps.warped, maps.displacement, maps.jacobian, entropy)
    )
    if network_features is None:
        return ScanQuality(answer, model.quality.estimate(answer), None)
    return ScanQuality(network_features, model.quality.estimate(network_features, answer), answer)


def quality_summary(model: LoadedModel, quality: ScanQuality | None, refinement: RefinementSettings) -> dict | None:
    """``summary.json["quality"]``: the estimate's record (the bundle's, without its warning, which the summary has
    at its top level), the model's threshold and definition, and how the run's refinement differs from the fit's."""
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
