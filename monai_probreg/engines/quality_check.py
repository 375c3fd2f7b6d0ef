"""The quality estimate in the bundle's workflows: one :class:`QualityCheck` shared by the engine handlers.

``RegistrationWriter`` (inference.yaml) and ``RegistrationScorer`` (evaluate.yaml) call it per subject: it computes
the label-free features of the registration (:mod:`monai_probreg.uncertainty.quality_features`) from the batch
(``moving``/``fixed``: the network inputs) and the network's output, the entropy under the calibration recorded with
the quality model (``QualityModel.feature_calibration``; when the workflow
refines the mean, the features of the network's own registration, computed again here without refinement, and those
of the refined answer for the local-NCC drop rule: :mod:`monai_probreg.uncertainty.quality`, "Whose features"),
applies the
weights' quality model (``<weights stem>.quality.json``, :mod:`monai_probreg.uncertainty.quality`) and logs one
warning line for a registration that probably failed. The writer stores the estimate as ``<id>/quality.json``; the
scorer adds it to ``scores.csv`` and ``summary.json``. Weights without a quality model: no estimate, said once.
"""

from __future__ import annotations

import logging
import os

import numpy as np
import torch
from torch import nn

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.engines.registration import register_pair
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.uncertainty.posterior_maps import posterior_maps
from monai_probreg.uncertainty.quality import (
    QualityModel,
    load_quality_model,
    quality_model_for,
    quality_path,
    quality_record,
)
from monai_probreg.uncertainty.quality_features import QualityFeatures, quality_features
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["QualityCheck"]

_LOG = logging.getLogger(__name__)


class QualityCheck:
    """Per-subject quality estimate of a bundle workflow.

    Args:
        network: the registration network (its ``velocity_to_displacement`` is not needed: the entropy alone).
        model_file: the weights; their ``<stem>.quality.json`` is loaded (None: no estimate).
        std_scale, bias_fraction: the posterior calibration in use (the entropy feature takes the quality model's
            own when its sidecar records one: ``QualityModel.feature_calibration``).
        calibrate: False (raw posterior): an estimate only from a quality model that records its entropy's calibration
            (one that does not takes the calibration in use for it, and the raw posterior is not what it was fitted on).
        quality_model: a model to use instead of the sidecar (tests).
        refinement: the workflow's refinement of the mean; when enabled, the estimate reads the network's own
            registration (one more forward pass per subject) and the refined one for the local-NCC drop rule.
    """

    def __init__(
        self,
        network: nn.Module,
        model_file: str | os.PathLike,
        std_scale: float = 1.0,
        bias_fraction: float = 0.0,
        calibrate: bool = True,
        quality_model: QualityModel | None = None,
        refinement: RefinementSettings | None = None,
    ) -> None:
        self.network, self.std_scale, self.bias_fraction = network, float(std_scale), float(bias_fraction)
        self.refined = refinement is not None and refinement.enabled
        given = quality_model if quality_model is not None else load_quality_model(model_file)
        self.model = quality_model_for(given, calibrate)
        if self.model is None:
            why = f"no {quality_path(model_file).name}" if given is None else "raw posterior (calibrate: false)"
            _LOG.info(f"no quality estimate for {model_file}: {why}")

    @property
    def enabled(self) -> bool:
        return self.model is not None

    def __call__(self, sid: str, pair: RegistrationOutput, targets: dict) -> dict | None:
        """The estimate of the first registration of the batch (the workflows run one pair per batch)."""
        if self.model is None:
            return None
        moving, fixed = plain_tensor(targets["moving"])[0, 0], plain_tensor(targets["fixed"])[0, 0]
        affine = targets["fixed"].affine if hasattr(targets["fixed"], "affine") else None
        spacing = None
        if affine is not None:
            matrix = np.asarray(affine[0] if affine.ndim == 3 else affine, dtype=np.float64)
            spacing = np.linalg.norm(matrix[:3, :3], axis=0).tolist()
        # what the workflow gave the network (prepare_registration_batch: the *_input entries where the batch has them)
        moving_in, fixed_in = (targets.get(key + "_input", targets[key])[:1] for key in ("moving", "fixed"))
        answer = self._features(moving, fixed, pair, spacing)
        if not self.refined:
            estimate = self.model.estimate(answer)
            features, answer = answer, None
        else:  # the network's own registration (quality.py, "Whose features"); no gradients, eval mode
            network_pair = register_pair(self.network, plain_tensor(moving_in), plain_tensor(fixed_in))
            features = self._features(moving, fixed, network_pair, spacing)
            estimate = self.model.estimate(features, answer)
        if estimate.warning:  # a warning never stops the workflow
            _LOG.warning(f"{sid}: WARNING: {estimate.warning}")
        return quality_record(features, estimate, answer)  # strict JSON, the same record as the command line's

    def _features(self, moving, fixed, pair: RegistrationOutput, spacing) -> QualityFeatures:
        shape = pair.displacement.shape[2:]
        calibration = self.model.feature_calibration(self.std_scale, self.bias_fraction)
        entropy = posterior_maps(
            self.network,
            pair.velocity_mean[:1],
            pair.velocity_log_var[:1],
            shape,
            std_scale=calibration.std_scale,
            bias_fraction=calibration.bias_fraction,
        ).velocity_entropy
        with torch.inference_mode():
            return quality_features(
                moving, fixed, plain_tensor(pair.warped)[0, 0], plain_tensor(pair.displacement)[0], entropy, spacing
            )
