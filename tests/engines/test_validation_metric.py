"""monai_probreg.engines.validation_metric.RegistrationMetrics: Dice, folding and the folding-aware selection score."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from monai_probreg.engines.validation_metric import RegistrationMetrics
from monai_probreg.networks.probreg_net import RegistrationOutput

SIZE = (8, 8, 8)


def _labels() -> torch.Tensor:
    label = torch.zeros((1, 1, *SIZE), dtype=torch.int16)
    label[..., 2:6, 2:6, 2:6] = 1
    return label


def _output(displacement: torch.Tensor) -> RegistrationOutput:
    zero = torch.zeros_like(displacement)
    return RegistrationOutput(
        warped=torch.zeros((1, 1, *SIZE)),
        displacement=displacement,
        velocity=zero,
        velocity_mean=zero,
        velocity_log_var=zero,
        inverse_displacement=None,
        warped_fixed=None,
    )


def _folding_displacement() -> torch.Tensor:
    """u = -2 (x - 3.5) along axis 0 on the slab 2..5: central differences give d(x + u)/dx = -1, det J < 0, on its
    two inner planes (2 x 8 x 8 voxels)."""
    displacement = torch.zeros((1, 3, *SIZE))
    x = torch.arange(SIZE[0], dtype=torch.float32)[:, None, None].expand(SIZE)
    slab = torch.zeros(SIZE, dtype=torch.bool)
    slab[2:6] = True
    displacement[0, 0] = torch.where(slab, -2.0 * (x - 3.5), torch.zeros(SIZE))
    return displacement


def _run(metric: RegistrationMetrics, displacement: torch.Tensor) -> dict[str, float]:
    metric.reset()
    metric.update((_output(displacement), {"moving_label": _labels(), "fixed_label": _labels()}))
    engine = SimpleNamespace(state=SimpleNamespace(metrics={}))
    metric.completed(engine, "val_dice")
    return engine.state.metrics


def test_identity_registration_has_dice_one_and_no_folding():
    metrics = _run(RegistrationMetrics(), torch.zeros((1, 3, *SIZE)))
    assert metrics["val_dice"] == pytest.approx(1.0)
    assert metrics["val_dice_folding"] == 0
    assert "val_dice_selection" not in metrics  # max_folding unset: Dice alone selects


def test_selection_score_is_dice_when_below_max_folding():
    metrics = _run(RegistrationMetrics(max_folding=1.0), torch.zeros((1, 3, *SIZE)))
    assert metrics["val_dice_selection"] == pytest.approx(metrics["val_dice"])


def test_selection_score_drops_by_one_when_the_field_folds():
    metrics = _run(RegistrationMetrics(max_folding=1.0), _folding_displacement())
    assert metrics["val_dice_folding"] >= 1.0
    assert metrics["val_dice_selection"] == pytest.approx(metrics["val_dice"] - 1.0)
    # Dice <= 1, so a folding epoch never ranks above one that does not fold (Dice >= 0)
    assert metrics["val_dice_selection"] <= 0.0


def test_max_folding_is_a_strict_threshold():
    folded = _run(RegistrationMetrics(), _folding_displacement())["val_dice_folding"]
    at = _run(RegistrationMetrics(max_folding=folded), _folding_displacement())
    above = _run(RegistrationMetrics(max_folding=folded + 0.5), _folding_displacement())
    assert at["val_dice_selection"] == pytest.approx(at["val_dice"] - 1.0)
    assert above["val_dice_selection"] == pytest.approx(above["val_dice"])


@pytest.mark.parametrize("bad", [0, -1.0, "1"])
def test_bad_max_folding_is_refused(bad):
    with pytest.raises(ValueError, match="max_folding"):
        RegistrationMetrics(max_folding=bad)
