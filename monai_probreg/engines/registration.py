"""Register one pair with a trained model (posterior mean, eval mode), timed, and score it."""

from __future__ import annotations

import time
from collections.abc import Sequence

import torch
from monai.networks.utils import eval_mode
from torch import Tensor, nn

from monai_probreg.engines.refinement import RefinementSettings, refine_registration
from monai_probreg.metrics.scores import PairScores, score_pair
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["register_pair", "timed_register_pair", "evaluate_pair"]


def register_pair(
    network: nn.Module, moving: Tensor, fixed: Tensor, refinement: RefinementSettings | None = None
) -> RegistrationOutput:
    """Register ``moving`` onto ``fixed`` (both (B, C, *S)) in eval mode (posterior mean velocity), the network under
    ``torch.inference_mode()``, then, if ``refinement`` is enabled, its mean refined for this pair
    (:func:`~monai_probreg.engines.refinement.refine_registration`); the network's train/eval mode is restored."""
    moving, fixed = plain_tensor(moving), plain_tensor(fixed)
    with eval_mode(network):
        with torch.inference_mode():
            output = network(moving, fixed)
        if refinement is not None and refinement.enabled:
            output = refine_registration(network, moving, fixed, output, refinement)
    return output


def timed_register_pair(
    network: nn.Module, moving: Tensor, fixed: Tensor, refinement: RefinementSettings | None = None
) -> tuple[RegistrationOutput, float]:
    """:func:`register_pair` and its wall time in seconds (network + integration + warp, and the refinement if any;
    CUDA synchronised)."""
    sync = torch.cuda.synchronize if moving.is_cuda else (lambda: None)
    sync()
    start = time.perf_counter()
    output = register_pair(network, moving, fixed, refinement)
    sync()
    return output, time.perf_counter() - start


def evaluate_pair(
    network: nn.Module,
    moving: Tensor,
    fixed: Tensor,
    moving_label: Tensor,
    fixed_label: Tensor,
    labels: Sequence[int] | None = None,
    refinement: RefinementSettings | None = None,
) -> tuple[PairScores, PairScores]:
    """Register one pair (timed) and score it; returns (registered, no registration) scores."""
    output, runtime = timed_register_pair(network, moving, fixed, refinement)
    return (
        score_pair(output.displacement, moving_label, fixed_label, runtime, labels),
        score_pair(None, moving_label, fixed_label, 0.0, labels),
    )
