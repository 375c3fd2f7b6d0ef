"""monai_probreg.spatial.affine_torch: the mutual information against a brute-force histogram and finite differences,
the rotation parameterisation, and a result that does not depend on the number of threads."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import FIXED_LPS, asymmetric_phantom, moved_scan, rigid_matrix

from monai_probreg.spatial.affine import AffineSettings, align
from monai_probreg.spatial.affine_torch import (
    _cubic_bspline,
    fixed_samples,
    mutual_information,
    register_affine_torch,
    rotation_matrix,
    scaled_intensities,
)
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.volume_io import Volume

BINS = 12


def _brute_force_mi(moving: np.ndarray, fixed_bins: np.ndarray, bins: int) -> float:
    """The joint histogram sample by sample and bin by bin (every bin, not just the 4 a window covers)."""
    joint = np.zeros((bins, bins))
    for value, a in zip(moving, fixed_bins):
        position = 1 + min(max(value, 0.0), 1.0) * (bins - 4)
        for b in range(bins):
            joint[a, b] += float(_cubic_bspline(torch.tensor(position - b, dtype=torch.float64)))
    joint /= len(moving)
    marginal = joint.sum(1, keepdims=True) * joint.sum(0, keepdims=True)
    inside = joint > 0
    return float((joint[inside] * np.log(joint[inside] / marginal[inside])).sum())


@pytest.fixture
def samples():
    generator = torch.Generator().manual_seed(3)
    fixed_bins = torch.randint(0, BINS, (300,), generator=generator)
    moving = fixed_bins.double() / BINS + 0.15 * torch.rand(300, generator=generator, dtype=torch.float64)
    return moving.clamp(0, 1), fixed_bins


def test_mutual_information_matches_a_brute_force_histogram(samples):
    moving, fixed_bins = samples
    expected = _brute_force_mi(moving.numpy(), fixed_bins.numpy(), BINS)
    assert float(mutual_information(moving, fixed_bins, BINS)) == pytest.approx(expected, rel=1e-10)


def test_mutual_information_gradient_matches_finite_differences(samples):
    moving, fixed_bins = samples
    moving = moving.clone().requires_grad_()
    mutual_information(moving, fixed_bins, BINS).backward()
    step = 1e-6
    for i in range(0, 300, 37):
        up, down = moving.detach().clone(), moving.detach().clone()
        up[i] += step
        down[i] -= step
        numeric = (mutual_information(up, fixed_bins, BINS) - mutual_information(down, fixed_bins, BINS)) / (2 * step)
        assert float(moving.grad[i]) == pytest.approx(float(numeric), rel=1e-5, abs=1e-9), i


def test_mutual_information_is_highest_for_the_matching_image(samples):
    moving, fixed_bins = samples
    shuffled = moving[torch.randperm(300, generator=torch.Generator().manual_seed(0))]
    assert float(mutual_information(moving, fixed_bins, BINS)) > 2 * float(
        mutual_information(shuffled, fixed_bins, BINS)
    )


def test_rotation_matrix_closed_forms():
    np.testing.assert_allclose(rotation_matrix(torch.zeros(3, dtype=torch.float64)).numpy(), np.eye(3), atol=0)
    quarter = rotation_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(quarter, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)  # x -> y about z
    some = rotation_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(some @ some.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(some) == pytest.approx(1.0)


@pytest.mark.parametrize("rotation", [[0.0, 0.0, 0.0], [0.3, -0.2, 0.5]])
def test_rotation_matrix_gradcheck(rotation):
    """Differentiable at 0 (the rigid stage starts there) and away from it."""
    point = torch.tensor(rotation, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotation_matrix, (point,))


def test_same_transform_with_one_or_two_threads():
    """No thread-order reduction: the torch backend gives the same matrix whatever the thread count."""
    image, labels = asymmetric_phantom()
    centre = grid_points(image.shape, FIXED_LPS).reshape(-1, 3).mean(0)
    truth = rigid_matrix([6.0, -4.0, 8.0], [3.0, -2.0, 1.5], centre)
    moved, _, grid = moved_scan(image, labels, truth, spacing=(1.2, 1.0, 1.1), direction=np.eye(3), shape=(40, 48, 40))
    fixed, moving = Volume(image, FIXED_LPS), Volume(moved * 300.0 + 50.0, grid)
    settings = AffineSettings(
        shrink_factors=(2, 1),
        smoothing_sigmas_mm=(1.0, 0.0),
        rigid_iterations=(40, 20),
        affine_iterations=(40, 20),
        sampling_percentage=0.5,
    )
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = align(fixed, moving, settings).matrix
        torch.set_num_threads(2)
        two = align(fixed, moving, settings).matrix
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_allclose(one, two, atol=1e-5)


@pytest.mark.parametrize("max_samples, expected", [(None, 16 * 16 * 16 // 2), (300, 300), (10_000, 16 * 16 * 16 // 2)])
def test_max_samples_caps_a_levels_sample_points(max_samples, expected):
    volume = Volume(np.random.default_rng(0).random((16, 16, 16)).astype(np.float32), np.eye(4))
    settings = AffineSettings(
        shrink_factors=(1,),
        smoothing_sigmas_mm=(0.0,),
        rigid_iterations=(1,),
        affine_iterations=(1,),
        sampling_percentage=0.5,
        max_samples=max_samples,
        histogram_bins=BINS,
    )
    samples = fixed_samples(volume, settings)
    assert samples.points[0].shape == (expected, 3) and samples.bins[0].shape == (expected,)


def test_fixed_samples_are_voxel_centres_of_the_fixed_level_with_their_bins():
    """The sample points are the LPS centres of the (pooled) fixed level's voxels, each with the bin of its value,
    on an oblique, anisotropic grid; and a caller's prepared samples give the matrix the call would make itself."""
    grid = np.eye(4)
    grid[:3, :3] = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) * [0.8, 1.5, 1.1]
    grid[:3, 3] = [12.0, -7.0, 30.0]
    volume = Volume(np.random.default_rng(1).random((12, 10, 14)).astype(np.float32), grid)
    settings = AffineSettings(
        shrink_factors=(1,),
        smoothing_sigmas_mm=(0.0,),
        rigid_iterations=(2,),
        affine_iterations=(2,),
        sampling_percentage=0.3,
        histogram_bins=BINS,
    )
    samples = fixed_samples(volume, settings)
    index = np.linalg.solve(grid[:3, :3], (samples.points[0].numpy() - grid[:3, 3]).T).T
    np.testing.assert_allclose(index, np.round(index), atol=1e-9)  # voxel centres
    scaled = scaled_intensities(volume).numpy()
    values = scaled[tuple(np.round(index).astype(int).T)]
    np.testing.assert_array_equal(samples.bins[0].numpy(), np.clip(np.round(values * (BINS - 1)), 0, BINS - 1))
    moving = Volume(np.roll(volume.array, 1, axis=0), grid)
    np.testing.assert_array_equal(
        register_affine_torch(volume, moving, settings, samples).matrix,
        register_affine_torch(volume, moving, settings).matrix,
    )
