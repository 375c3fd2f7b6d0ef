"""monai_probreg.spatial.model_grid.ModelGrid: the model grid is exactly the bundle's preprocessing, and the way back is exact."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import save_lps

from monai_probreg.data.transforms import registration_transforms
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.volume_io import read_image


def _oblique_lps() -> np.ndarray:
    affine = np.eye(4)
    affine[:3, :3] = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]) * [1.2, 0.9, 1.5]
    affine[:3, 3] = [5.0, -3.0, 12.0]
    return affine


@pytest.mark.parametrize("lps", [np.diag([-1.0, -1.0, 1.0, 1.0]), "oblique"])
def test_model_grid_is_the_bundle_preprocessing(tmp_path, lps):
    """Same array and affine as registration_transforms (LoadImage, RAS, DivisiblePad) gives the network."""
    lps = _oblique_lps() if isinstance(lps, str) else lps
    data = np.random.default_rng(0).random((20, 13, 18)).astype(np.float32)
    path = save_lps(tmp_path / "fixed.nii.gz", data, lps)
    bundle = registration_transforms(with_labels=False, divisor=16)({"moving": str(path), "fixed": str(path)})["fixed"]
    volume = read_image(path)
    grid = ModelGrid.for_volume(volume, divisor=16)
    ours = grid.to_model(normalise_intensity(volume.array))
    assert grid.shape == tuple(bundle.shape[1:]) == ours.shape
    np.testing.assert_allclose(ours, bundle[0].numpy(), atol=1e-6)  # float32 rounding of the rescaling
    np.testing.assert_allclose(grid.ras_affine, bundle.affine.numpy(), atol=1e-4)


def test_to_fixed_inverts_to_model_with_channels():
    grid = ModelGrid((20, 13, 18), _oblique_lps(), divisor=8)
    field = np.random.default_rng(1).random((20, 13, 18, 3))
    np.testing.assert_array_equal(grid.to_fixed(grid.to_model(field)), field)
    assert grid.to_model(field).shape == (*grid.shape, 3)


def test_voxel_centres_coincide():
    """The model grid's voxel centres are the fixed grid's, so a field in mm moves between them by re-indexing."""
    grid = ModelGrid((20, 13, 18), _oblique_lps(), divisor=16)
    fixed_points = grid_points((20, 13, 18), _oblique_lps())
    model_points = grid_points(grid.shape, grid.index_to_lps)
    np.testing.assert_allclose(grid.to_fixed(model_points), fixed_points, atol=1e-9)


def test_padding_is_symmetric_like_monai():
    grid = ModelGrid((20, 13, 18), np.diag([-1.0, -1.0, 1.0, 1.0]), divisor=16)
    assert grid.shape == (32, 16, 32) and grid.pad_before == (6, 1, 7)


def test_rejects_arrays_on_other_grids():
    grid = ModelGrid((20, 13, 18), np.eye(4), divisor=16)
    with pytest.raises(ValueError, match="fixed grid"):
        grid.to_model(np.zeros((20, 13, 17)))
    with pytest.raises(ValueError, match="model grid"):
        grid.to_fixed(np.zeros((20, 13, 18)))


@pytest.mark.parametrize("axcodes", ["RAS", "LPS", "AIL", "SRP"])
def test_a_block_of_rows_is_those_rows_of_to_fixed(axcodes):
    """block_of_rows + block_to_fixed: the fixed grid's rows, cut from the model grid (any orientation, padded)."""
    from nibabel.orientations import axcodes2ornt, inv_ornt_aff

    from monai_probreg.spatial.volume_io import LPS_TO_RAS

    shape = (7, 5, 6)
    ras = inv_ornt_aff(axcodes2ornt(axcodes), shape)  # a grid of that orientation
    grid = ModelGrid(shape, LPS_TO_RAS @ ras @ np.diag([1.0, 1.5, 0.8, 1.0]), divisor=4)
    model = np.random.default_rng(0).random((*grid.shape, 2))
    whole = grid.to_fixed(model)
    for rows in [slice(0, 7), slice(0, 1), slice(2, 5), slice(6, 7)]:
        assert np.array_equal(grid.block_to_fixed(model[grid.block_of_rows(rows)]), whole[rows])
    with pytest.raises(ValueError, match="consecutive"):
        grid.block_of_rows(slice(0, 7, 2))
