"""The validation metric: mean Dice of the moving labels warped (nearest neighbour) onto the fixed
labels at the labels' resolution, the |J| <= 0 count per pair, and the folding-aware selection score."""

from __future__ import annotations

import math
from collections.abc import Sequence

from ignite.engine import Engine
from ignite.metrics import Metric

from monai_probreg.blocks.integration import resize_displacement
from monai_probreg.blocks.warp import warp_labels
from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
from monai_probreg.networks.probreg_net import RegistrationOutput

__all__ = ["RegistrationMetrics"]


class RegistrationMetrics(Metric):
    """Mean Dice over ``label_values`` (default: non-zero labels of the fixed map) and mean |J| <= 0 count per pair.

    ``compute()`` returns ``{"dice": float, "folding": float}``. Attached as ``name`` (the evaluator's key metric),
    it writes ``state.metrics[name]`` (Dice), ``state.metrics[name + "_folding"]`` and, when ``max_folding`` is set,
    ``state.metrics[name + "_selection"]``: the Dice if fewer than ``max_folding`` voxels fold per pair on average,
    else Dice - 1, so that an epoch which folds ranks below every epoch which does not (and folding epochs still
    rank by Dice among themselves). Point a ``CheckpointSaver``'s ``key_metric_name`` at it to keep the best Dice
    among the epochs that do not fold.
    """

    def __init__(
        self,
        label_values: Sequence[int] | None = None,
        max_folding: float | None = None,
        output_transform=lambda out: (out["pred"], out["label"]),
    ) -> None:
        if max_folding is not None and not (isinstance(max_folding, (int, float)) and max_folding > 0):
            raise ValueError(f"max_folding must be a positive number of voxels per pair or None; got {max_folding!r}")
        self.label_values = list(label_values) if label_values is not None else None
        self.max_folding = None if max_folding is None else float(max_folding)
        super().__init__(output_transform=output_transform)

    def reset(self) -> None:
        self._dice: list[float] = []
        self._folding: list[int] = []

    def update(self, output: tuple[RegistrationOutput, dict]) -> None:
        pred, targets = output
        moving_label, fixed_label = targets["moving_label"], targets["fixed_label"]
        ddf = resize_displacement(pred.displacement.float(), moving_label.shape[2:])
        warped = warp_labels(moving_label, ddf)
        for b in range(ddf.shape[0]):
            self._dice.append(mean_dice(label_dice(warped[b], fixed_label[b], self.label_values)))
            self._folding.append(jacobian_stats(jacobian_determinant(ddf[b : b + 1])).num_folding)

    def compute(self) -> dict[str, float]:
        scored = [d for d in self._dice if not math.isnan(d)]  # a pair with no label to score has no Dice
        if not scored:
            raise RuntimeError("RegistrationMetrics has no scored pair; was the evaluator run on labelled pairs?")
        return {"dice": sum(scored) / len(scored), "folding": sum(self._folding) / len(self._folding)}

    def completed(self, engine: Engine, name: str) -> None:
        result = self.compute()
        engine.state.metrics[name] = result["dice"]
        engine.state.metrics[f"{name}_folding"] = result["folding"]
        if self.max_folding is not None:
            eligible = result["folding"] < self.max_folding
            engine.state.metrics[f"{name}_selection"] = result["dice"] - (0.0 if eligible else 1.0)
