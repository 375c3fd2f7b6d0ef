"""monai_probreg.registration.compose: slab by slab, the same bits as the whole-grid computation it replaced
(oblique grids, a model grid in another orientation, slabs of several heights); the network's volumes consumed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monai_probreg.metrics.jacobian import jacobian_stats
from monai_probreg.registration.compose import affine_resample, compose_outputs, forward_outputs, inverse_outputs
from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.network import ModelMaps
from monai_probreg.spatial import physical
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.physical import compose_forward, compose_inverse, mapped_index, voxel_to_mm
from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
from monai_probreg.spatial.volume_io import Volume


def _grid(spacing, turn: float, origin) -> np.ndarray:
    c, s = np.cos(turn), np.sin(turn)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, -1.0]])  # oblique, and a flipped axis
    matrix = np.eye(4)
    matrix[:3, :3] = rotation @ np.diag(spacing)
    matrix[:3, 3] = origin
    return matrix


@pytest.fixture
def case():
    rng = np.random.default_rng(0)
    fixed = Volume(rng.random((9, 7, 6), dtype=np.float32), _grid([1.0, 1.2, 0.9], 0.3, [4.0, -3.0, 2.0]))
    moving = Volume(rng.random((8, 10, 7), dtype=np.float32) * 100, _grid([1.1, 0.8, 1.0], -0.2, [5.0, -4.0, 1.0]))
    moving_label = moving.with_array(rng.integers(0, 5, moving.shape).astype(np.int32))
    fixed_label = fixed.with_array(rng.integers(0, 5, fixed.shape).astype(np.int32))
    affine = np.eye(4)
    affine[:3, :3] += 0.05 * rng.standard_normal((3, 3))
    affine[:3, 3] = [0.7, -0.4, 0.3]
    grid = ModelGrid.for_volume(fixed, divisor=4)
    displacement = (rng.standard_normal((3, *grid.shape)) * 1.5).astype(np.float32)
    inverse = (rng.standard_normal((3, *grid.shape)) * 1.5).astype(np.float32)
    return fixed, moving, moving_label, fixed_label, affine, grid, displacement, inverse


@pytest.mark.parametrize("slab_voxels", [1, 100, 10**9])
def test_forward_outputs_are_the_whole_grid_computation_to_the_bit(case, monkeypatch, slab_voxels):
    fixed, moving, moving_label, _, affine, grid, displacement, _ = case
    monkeypatch.setattr(physical, "SLAB_VOXELS", slab_voxels)
    ours = forward_outputs(grid, fixed, moving, moving_label, affine, displacement)
    warp = compose_forward(grid.to_fixed(voxel_to_mm(displacement, grid.index_to_lps)), fixed.index_to_lps, affine)
    warp = warp.astype(np.float32)
    index = mapped_index(fixed.shape, fixed.index_to_lps, moving.index_to_lps, field=warp)
    affine_index = mapped_index(fixed.shape, fixed.index_to_lps, moving.index_to_lps, affine)
    assert np.array_equal(ours.warp, warp)
    assert np.array_equal(ours.warped, sample_linear(moving, None, index=index).astype(np.float32))
    assert np.array_equal(ours.labels["warped_label"], sample_nearest(moving_label, None, index=index))
    assert np.array_equal(ours.labels["affine_label"], sample_nearest(moving_label, None, index=affine_index))
    assert forward_outputs(grid, fixed, moving, None, affine, displacement).labels == {}


@pytest.mark.parametrize("slab_voxels", [1, 100, 10**9])
def test_inverse_outputs_are_the_whole_grid_computation_to_the_bit(case, monkeypatch, slab_voxels):
    fixed, moving, _, fixed_label, affine, grid, _, inverse = case
    monkeypatch.setattr(physical, "SLAB_VOXELS", slab_voxels)
    consumed = inverse.copy()
    ours = inverse_outputs(grid, consumed, affine, moving, fixed_label)
    field = Volume(voxel_to_mm(inverse, grid.index_to_lps), grid.index_to_lps)
    assert np.array_equal(consumed, field.array.astype(np.float32).transpose(3, 0, 1, 2))  # its mm, in place
    warp = compose_inverse(field, affine, moving.shape, moving.index_to_lps)
    index = mapped_index(moving.shape, moving.index_to_lps, fixed_label.index_to_lps, field=warp)
    assert np.array_equal(ours.warp, warp)
    assert np.array_equal(ours.fixed_label, sample_nearest(fixed_label, None, index=index))
    assert inverse_outputs(grid, inverse.copy(), affine, moving, None).fixed_label is None
    with pytest.raises(ValueError, match="expected the float32 displacement"):
        inverse_outputs(grid, inverse.astype(np.float64), affine, moving, None)


@pytest.mark.parametrize("slab_voxels", [1, 100, 10**9])
def test_affine_resample_is_sample_linear_rounded_to_float32(case, monkeypatch, slab_voxels):
    fixed, moving, _, _, affine, _, _, _ = case
    monkeypatch.setattr(physical, "SLAB_VOXELS", slab_voxels)
    index = mapped_index(fixed.shape, fixed.index_to_lps, moving.index_to_lps, affine)
    expected = sample_linear(moving, None, fill=-3.0, index=index).astype(np.float32)
    ours = affine_resample(moving, fixed, affine, -3.0)
    assert ours.dtype == np.float32
    assert np.array_equal(ours, expected)


def test_compose_outputs_consumes_the_network_volumes_and_keeps_the_bits(case):
    """Each of the network's volumes is let go once read, and the outputs are those of the steps done on their own:
    the forward and inverse outputs, the maps on the fixed grid, the Jacobian's statistics of the fixed-grid map."""
    fixed, moving, moving_label, fixed_label, affine, grid, displacement, inverse = case
    rng = np.random.default_rng(1)
    jacobian, entropy = (rng.random(grid.shape, dtype=np.float32) + 0.5 for _ in range(2))
    maps = ModelMaps(displacement.copy(), inverse.copy(), jacobian, entropy, rng.random(grid.shape, dtype=np.float32))
    space = FixedSpace(fixed, fixed_label, grid, grid.to_model(fixed.array), label_ids=[1, 2, 3, 4])
    composed = compose_outputs(space, moving, moving_label, affine, maps, inverse=True)
    assert maps.displacement is None and maps.inverse is None and maps.jacobian is None and maps.entropy is None
    assert maps.deformed  # what the summary reads, kept
    forward = forward_outputs(grid, fixed, moving, moving_label, affine, displacement)
    backward = inverse_outputs(grid, inverse.copy(), affine, moving, fixed_label)
    assert np.array_equal(composed.warp, forward.warp) and np.array_equal(composed.inverse_warp, backward.warp)
    assert np.array_equal(composed.maps["jacobian"], grid.to_fixed(jacobian))
    assert list(composed.maps) == ["warped", "jacobian", "entropy"]
    assert list(composed.labels) == ["warped_label", "affine_label", "fixed_label_in_moving"]
    assert composed.jacobian_stats == jacobian_stats(torch.from_numpy(grid.to_fixed(jacobian)))
    assert composed.dice is not None and 0.0 <= composed.dice["mean"] <= 1.0
