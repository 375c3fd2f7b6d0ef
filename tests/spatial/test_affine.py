"""monai_probreg.spatial.affine: the ITK backend's rigid + affine pre-alignment recovers a known transform across grids and orientations."""

from __future__ import annotations

import itk
import numpy as np
import pytest
from conftest import FAST_AFFINE_SETTINGS, FIXED_LPS, asymmetric_phantom, moved_scan, rigid_matrix

from monai_probreg.spatial.affine import AffineSettings, align, rotation_angle_deg
from monai_probreg.spatial.physical import apply_affine, grid_points
from monai_probreg.spatial.volume_io import Volume

# Small volumes: two levels at 1/2 and full resolution instead of the defaults' 1/4 and 1/2 of a 1 mm brain.
FAST = AffineSettings.itk_defaults(
    shrink_factors=(2, 1),
    smoothing_sigmas_mm=(1.0, 0.0),
    rigid_iterations=(100, 50),
    affine_iterations=(100, 50),
    sampling_percentage=0.25,
)
FAST_TORCH = FAST_AFFINE_SETTINGS
BACKENDS = {"itk": FAST, "torch": FAST_TORCH}
# a permuted, flipped, anisotropic scanner grid (axcodes of the moving scan differ from the fixed LPS)
DIRECTION = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


@pytest.fixture(scope="module")
def case():
    itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(1)
    image, labels = asymmetric_phantom()
    centre = grid_points(image.shape, FIXED_LPS).reshape(-1, 3).mean(0)
    truth = rigid_matrix([10.0, -8.0, 12.0], [4.0, -3.0, 2.5], centre)
    moved, _, grid = moved_scan(image, labels, truth, spacing=(1.4, 0.9, 1.1), direction=DIRECTION, shape=(34, 52, 40))
    fixed = Volume(image, FIXED_LPS)
    moving = Volume(moved * 300.0 + 50.0, grid)  # a raw scanner range: MI does not care
    brain = grid_points(image.shape, FIXED_LPS)[labels > 0]
    return fixed, moving, truth, brain


def _errors(matrix: np.ndarray, truth: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(apply_affine(matrix, points) - apply_affine(truth, points), axis=-1)


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_recovers_rotation_translation_across_grids(case, backend):
    """10-15 degrees and 5 mm off, moving on a 1.4 x 0.9 x 1.1 mm permuted/flipped grid: the fixed -> moving map is
    found to well under a voxel over the object (observed, ITK: mean 0.15 mm, max 0.25 mm; the 12-parameter stage
    fits a little scaling to interpolation noise, the rigid stage alone is at ~0.08 mm), by either backend."""
    fixed, moving, truth, brain = case
    result = align(fixed, moving, BACKENDS[backend])
    assert _errors(result.initial, truth, brain).mean() > 1.5  # the centre-of-mass start is far from the answer
    errors = _errors(result.matrix, truth, brain)
    assert errors.mean() < 0.4 and errors.max() < 0.8
    assert [s.name for s in result.stages] == ["rigid", "affine"]
    assert all(len(s.iterations) == 2 and s.iterations[0] > 0 for s in result.stages)
    assert abs(result.summary()["rotation_deg"] - rotation_angle_deg(truth)) < 1.0
    point = brain[0]
    np.testing.assert_allclose(
        np.asarray(result.transform.TransformPoint(point.tolist())), apply_affine(result.matrix, point), atol=1e-9
    )


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_rigid_only_is_a_rotation_and_is_deterministic(case, backend):
    fixed, moving, truth, brain = case
    settings = AffineSettings(**{**BACKENDS[backend].as_dict(), "rigid_only": True})
    first = align(fixed, moving, settings)
    second = align(fixed, moving, settings)
    np.testing.assert_array_equal(first.matrix, second.matrix)  # fixed sampling seed
    rotation = first.matrix[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
    assert _errors(first.matrix, truth, brain).mean() < 0.3


# an earlier registration's answer, a little off: the truth after 3 degrees and 2 mm more (fixed space first, as the
# stages compose it)
NEAR_TRUTH_ANGLES_DEG, NEAR_TRUTH_SHIFT_MM = [3.0, -2.0, 2.5], [2.0, -1.0, 1.5]


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_stages_start_from_an_initial_transform(case, backend):
    """``initial`` (``--initial-transform``'s start): the stages begin exactly at it (``result.initial``) and refine
    it to the truth, as from the initializer; the same result every run."""
    fixed, moving, truth, brain = case
    centre = brain.mean(0)
    initial = truth @ rigid_matrix(NEAR_TRUTH_ANGLES_DEG, NEAR_TRUTH_SHIFT_MM, centre)
    assert _errors(initial, truth, brain).mean() > 1.5  # far enough for the stages to have work to do
    result = align(fixed, moving, BACKENDS[backend], initial=initial)
    np.testing.assert_array_equal(result.initial, initial)
    errors = _errors(result.matrix, truth, brain)
    assert errors.mean() < 0.4 and errors.max() < 0.8
    assert [s.name for s in result.stages] == ["rigid", "affine"]
    np.testing.assert_allclose(
        np.asarray(result.transform.TransformPoint(brain[0].tolist())), apply_affine(result.matrix, brain[0]), atol=1e-9
    )
    np.testing.assert_array_equal(align(fixed, moving, BACKENDS[backend], initial=initial).matrix, result.matrix)


def test_torch_stages_without_iterations_return_the_initial_transform_exactly(case):
    """The stages' parameters are a map of the fixed space composed before the initial transform, the identity at 0:
    with no iterations the result is the initial transform itself, to the bit (a scaling and shear included)."""
    fixed, moving, truth, _ = case
    initial = truth.copy()
    initial[:3, :3] = initial[:3, :3] @ np.array([[1.05, 0.02, 0.0], [0.0, 0.97, 0.01], [0.0, 0.0, 1.02]])
    idle = AffineSettings(**{**FAST_TORCH.as_dict(), "rigid_iterations": (0, 0), "affine_iterations": (0, 0)})
    np.testing.assert_array_equal(align(fixed, moving, idle, initial=initial).matrix, initial)


def test_rotation_angle():
    assert rotation_angle_deg(rigid_matrix([0.0, 0.0, 30.0], [1.0, 2.0, 3.0], [0.0, 0.0, 0.0])) == pytest.approx(30.0)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"smoothing_sigmas_mm": (1.0,)}, "one value per level"),
        ({"shrink_factors": (2, 0), "smoothing_sigmas_mm": (1.0, 0.0)}, "shrink_factors"),
        ({"sampling_percentage": 0.0}, "sampling_percentage"),
        ({"initializer": "landmarks"}, "initializer"),
        ({"max_samples": 0}, "max_samples"),
        ({"backend": "ants"}, "backend"),
        ({"rigid_iterations": (10, -1, 0)}, "iterations must be >= 0"),
    ],
)
def test_settings_are_validated(kwargs, message):
    with pytest.raises(ValueError, match=message):
        AffineSettings(**kwargs)
