"""Training guards: stop at the first non-finite loss or weight, before the epoch's checkpoints."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from ignite.engine import Engine, Events
from torch import Tensor

__all__ = ["NonFiniteGuard"]


class NonFiniteGuard:
    """Stops training at the first non-finite loss or weight with a ``FloatingPointError`` naming the epoch, the
    iteration and the first bad parameter.

    It runs at ``ITERATION_COMPLETED``, after the optimizer step and before ``EPOCH_COMPLETED`` (validation and the
    checkpoints), so no checkpoint ever holds NaN weights: the newest on disk is the last good epoch's. Checking the
    weights costs one ``isfinite().all()`` per parameter tensor and a single host sync per iteration.

    Args:
        check_weights: also check the trainer's ``network`` parameters (a finite loss can still give Inf gradients).
        output_transform: engine output -> loss tensor (MONAI trainers: ``output["loss"]``).
    """

    def __init__(
        self, check_weights: bool = True, output_transform: Callable[[Any], Tensor] = lambda output: output["loss"]
    ) -> None:
        self.check_weights, self.output_transform = check_weights, output_transform

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.ITERATION_COMPLETED, self)

    def __call__(self, engine: Engine) -> None:
        where = f"training stopped at epoch {engine.state.epoch}, iteration {engine.state.iteration}"
        advice = (
            "no checkpoint of this epoch was written; resume from the last one with a lower learning_rate or "
            "check the data"
        )
        loss = torch.as_tensor(self.output_transform(engine.state.output)).detach()
        if not bool(torch.isfinite(loss).all()):
            raise FloatingPointError(f"{where}: expected a finite loss, got {loss.flatten()[:4].tolist()}; {advice}")
        network = getattr(engine, "network", None)
        if not self.check_weights or network is None:
            return
        params = [(name, p.detach()) for name, p in network.named_parameters()]
        finite = torch.stack([torch.isfinite(p).all() for _, p in params]) if params else torch.ones(1, dtype=bool)
        if not bool(finite.all()):  # one host sync
            name, p = params[int((~finite).nonzero()[0])]
            bad = int((~torch.isfinite(p)).sum())
            raise FloatingPointError(
                f"{where}: expected finite weights, got {bad} NaN/Inf values in {name!r} after "
                f"the optimizer step; {advice}"
            )
