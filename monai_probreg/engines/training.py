"""Glue between the registration model and MONAI's ``SupervisedTrainer``/``SupervisedEvaluator``.

- :func:`prepare_registration_batch` turns a batch dict into ``(moving, targets, (fixed,), {})`` so the engine
  calls ``network(moving, fixed)``; ``targets`` is the batch dict (images and, if present, labels). Where the
  batch holds intensity-augmented inputs (``moving_input``/``fixed_input``, :func:`~monai_probreg.data.augmentation.
  intensity_augmentation`), the network sees those instead.
- :class:`RegistrationLoss` adapts :class:`~monai_probreg.losses.elbo.ProbRegLoss` to the engine's
  ``loss_function(pred, targets)`` and keeps the last terms for :class:`LossTermsLogger`. With augmented inputs it
  scores the *clean* moving image warped by the predicted displacement against the clean fixed image.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import torch
from ignite.engine import Engine, Events
from torch import Tensor, nn

from monai_probreg.blocks.warp import warp_image
from monai_probreg.losses.elbo import LossTerms, ProbRegLoss
from monai_probreg.networks.probreg_net import RegistrationOutput

__all__ = ["prepare_registration_batch", "one_hot_labels", "RegistrationLoss", "LossTermsLogger"]


_LOG = logging.getLogger("monai_probreg.train")


_KEYS = ("moving", "fixed", "moving_label", "fixed_label", "moving_input", "fixed_input")


def prepare_registration_batch(
    batchdata: dict, device: str | torch.device | None = None, non_blocking: bool = False, **kwargs: Any
) -> tuple:
    """Engine ``prepare_batch``: ``(moving, targets, (fixed,), {})`` with every tensor on ``device``; ``moving`` and
    ``fixed`` are ``moving_input``/``fixed_input`` where the batch has them (intensity augmentation)."""
    for key in ("moving", "fixed"):
        if key not in batchdata:
            raise KeyError(f"batch has no {key!r} entry; got keys {sorted(batchdata)}")
    targets = {
        k: batchdata[k].to(device=device, non_blocking=non_blocking, **kwargs)
        for k in _KEYS
        if isinstance(batchdata.get(k), Tensor)
    }  # label paths not loaded stay behind
    moving, fixed = (targets.get(key + "_input", targets[key]) for key in ("moving", "fixed"))
    return moving, targets, (fixed,), {}


def one_hot_labels(labels: Tensor, label_values: Sequence[int]) -> Tensor:
    """(B, 1, *S) integer map -> (B, 1 + len(label_values), *S) float one-hot; channel 0 = everything else."""
    lut = torch.zeros(int(max(int(labels.max()), max(label_values))) + 1, dtype=torch.long, device=labels.device)
    lut[torch.as_tensor(list(label_values), device=labels.device)] = torch.arange(
        1, len(label_values) + 1, device=labels.device
    )
    idx = lut[labels.long().clamp(min=0)[:, 0]]
    return torch.nn.functional.one_hot(idx, len(label_values) + 1).movedim(-1, 1).float()


class RegistrationLoss(nn.Module):
    """``loss_function(pred, targets)`` for the engines.

    Args:
        loss: the objective (image likelihood + KL [+ Dice]).
        label_values: label ids one-hot encoded for the Dice term (needed only when ``loss.label_weight > 0``;
            the label maps must then be on the network grid).
        padding_mode: the network's ``padding_mode``, used to warp the clean images when the batch holds
            intensity-augmented inputs (``moving_input``/``fixed_input``).
    """

    def __init__(
        self, loss: ProbRegLoss, label_values: Sequence[int] | None = None, padding_mode: str = "border"
    ) -> None:
        super().__init__()
        self.padding_mode = padding_mode
        self.loss = loss
        self.label_values = list(label_values) if label_values is not None else None
        self.last_terms: LossTerms | None = None

    def forward(self, pred: RegistrationOutput, targets: dict) -> Tensor:
        moving_oh = fixed_oh = None
        if self.loss.label_weight > 0:
            if self.label_values is None or "moving_label" not in targets:
                raise ValueError("a label term needs label_values and moving_label/fixed_label in the batch")
            moving_oh = one_hot_labels(targets["moving_label"], self.label_values)
            fixed_oh = one_hot_labels(targets["fixed_label"], self.label_values)
        if "moving_input" in targets or "fixed_input" in targets:
            # the network saw augmented intensities: the likelihood compares the clean images (same padding as
            # the network's own warp), so image_sigma keeps its meaning
            pred = pred._replace(
                warped=warp_image(targets["moving"], pred.displacement, padding_mode=self.padding_mode)
            )
            if pred.inverse_displacement is not None:
                pred = pred._replace(
                    warped_fixed=warp_image(targets["fixed"], pred.inverse_displacement, padding_mode=self.padding_mode)
                )
        terms = self.loss(pred, targets["moving"], targets["fixed"], moving_oh, fixed_oh)
        self.last_terms = LossTerms(*(t.detach() for t in terms))
        if not torch.isfinite(terms.total):
            raise FloatingPointError(f"non-finite training loss ({terms}); stopping before weights become NaN")
        return terms.total


class LossTermsLogger:
    """Logs the parts of the loss (image, KL, label) every ``interval`` iterations."""

    def __init__(self, loss: RegistrationLoss, interval: int = 10, name: str = "monai_probreg.train") -> None:
        self.loss, self.interval, self.logger = loss, interval, logging.getLogger(name)

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.ITERATION_COMPLETED(every=self.interval), self)

    def __call__(self, engine: Engine) -> None:
        t = self.loss.last_terms
        if t is not None:
            self.logger.info(
                f"epoch {engine.state.epoch} iter {engine.state.iteration}: total {float(t.total):.4f} "
                f"image {float(t.image):.4f} kl {float(t.kl):.4f} label {float(t.label):.4f}"
            )
