"""experiments/roughness_term.py: the roughness maps in closed form, the mixing, the skip without a dataset."""

from __future__ import annotations

import pytest
import torch
from conftest import load_script

study = load_script("experiments", "roughness_term")


def _parabola(shape=(8, 9, 10), axis=0) -> torch.Tensor:
    """(1, 3, *shape): x^2 along ``axis`` in the first component, zero in the others."""
    field = torch.zeros(1, 3, *shape)
    coord = torch.arange(shape[axis], dtype=torch.float32)
    view = [1, 1, 1]
    view[axis] = shape[axis]
    field[0, 0] = coord.view(view).square().expand(shape)
    return field


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_squared_laplacian_of_a_parabola_is_four_inside(axis):
    rough = study.roughness(_parabola(axis=axis), "laplacian", 1)
    assert rough.shape == (1, 1, 8, 9, 10)
    inside = rough[0, 0, 1:-1, 1:-1, 1:-1]
    assert torch.allclose(inside, torch.full_like(inside, 4.0))


def test_the_gradient_energy_of_a_parabola_is_its_squared_slope():
    rough = study.roughness(_parabola(), "gradient", 1)
    assert torch.isclose(rough[0, 0, 3, 4, 5], torch.tensor(36.0))  # d(x^2)/dx = 6 at x = 3


def test_a_straight_field_has_no_roughness_and_the_box_averages():
    ramp = torch.arange(10, dtype=torch.float32).view(1, 1, 10, 1, 1).expand(1, 3, 10, 6, 6)
    assert torch.allclose(study.roughness(ramp, "laplacian", 1)[0, 0, 1:-1, 1:-1, 1:-1], torch.zeros(8, 4, 4))
    point = torch.zeros(1, 3, 7, 7, 7)
    point[0, 0, 3, 3, 3] = 1.0
    boxed = study.roughness(point, "laplacian", 3)
    plain = study.roughness(point, "laplacian", 1)
    assert torch.isclose(boxed.sum(), plain.sum(), rtol=1e-5)  # a box mean moves energy, it does not make any


def test_mixed_keeps_the_residual_mean_and_weighs_the_roughness():
    residual = torch.full((1, 1, 8, 9, 10), 0.5)
    field = _parabola()
    assert torch.equal(study.mixed(residual, field, (None, 1, 0.0)), residual)
    alone = study.mixed(residual, field, ("laplacian", 1, 1.0))
    assert torch.isclose(alone.mean(), residual.mean())
    half = study.mixed(residual, field, ("laplacian", 1, 0.5))
    assert torch.allclose(half, 0.5 * residual + 0.5 * alone)


def test_no_dataset_is_a_clean_skip(tmp_path, capsys):
    assert study.main(["--dataset-dir", str(tmp_path / "missing"), "--out-dir", str(tmp_path)]) == 0
    assert "skipped" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.json"))
