"""Scores of one registration: Dice per label and their mean (the one rule of :func:`~monai_probreg.
metrics.dice.mean_dice`), folding and smoothness of the displacement, runtime."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from torch import Tensor

from monai_probreg.blocks.warp import warp_labels
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.metrics.jacobian import JacobianStats, jacobian_determinant, jacobian_stats
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["PairScores", "score_pair"]


class PairScores(NamedTuple):
    """Scores of one registration: Dice per fixed label and their mean; |J| <= 0 count and percentage and std of
    log|J| over the whole fixed grid (padding included); runtime in seconds (0 for no registration)."""

    dice: dict[int, float]
    mean_dice: float
    num_folding: int
    percent_folding: float
    std_log_jacobian: float
    runtime_s: float


def score_pair(
    displacement: Tensor | None,
    moving_label: Tensor,
    fixed_label: Tensor,
    runtime_s: float = 0.0,
    labels: Sequence[int] | None = None,
) -> PairScores:
    """Score a displacement (1, 3, *S) (None = no registration, the identity) with labels (1, 1, *S) on the
    same grid: Dice of the nearest-neighbour warped moving labels against the fixed labels for ``labels``
    (default: the non-zero labels of ``fixed_label``) and folding statistics of the displacement."""
    moving_label, fixed_label = plain_tensor(moving_label), plain_tensor(fixed_label)
    if displacement is None:
        warped, stats = moving_label, JacobianStats(0, 0.0, 0.0)
    else:
        displacement = plain_tensor(displacement).float()
        warped = warp_labels(moving_label.to(displacement.device), displacement)
        stats = jacobian_stats(jacobian_determinant(displacement))
    dice = label_dice(warped.cpu(), fixed_label.cpu(), labels)
    return PairScores(
        dice, mean_dice(dice), stats.num_folding, stats.percent_folding, stats.std_log_jacobian, runtime_s
    )
