"""monai_probreg.spatial.affine_local: the local-correlation step recovers a known affine between two contrasts (the
fixed -> moving convention), keeps a right answer, picks the right start, honours a moving mask; its settings refuse
bad values one by one."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIXED_LPS, asymmetric_phantom, moved_scan, rigid_matrix

from monai_probreg.spatial.affine_local import refine_by_local_correlation
from monai_probreg.spatial.affine_settings import AffineSettings
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.volume_io import Volume

SETTINGS = AffineSettings(local_levels_mm=(2.0, 1.0), local_kernels=(3, 5), local_iterations=(30, 30))


def _max_distance_mm(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """The largest distance between the two maps' images of ``points`` (N, 3)."""
    return float(np.abs(points @ (a[:3, :3] - b[:3, :3]).T + (a[:3, 3] - b[:3, 3])).max())


@pytest.fixture(scope="module")
def pair():
    """The phantom (fixed) and a moved copy in the *inverted* contrast on another grid, and the truth (fixed ->
    moving): a rotation, a shift and a 6% scaling along one axis."""
    image, labels = asymmetric_phantom()
    centre = grid_points(image.shape, FIXED_LPS).reshape(-1, 3).mean(0)
    truth = rigid_matrix([6.0, -4.0, 8.0], [3.0, -2.0, 1.5], centre)
    scale = np.diag([1.06, 1.0, 1.0, 1.0])
    scale[:3, 3] = centre - scale[:3, :3] @ centre
    truth = truth @ scale
    moved, _, grid = moved_scan(image, labels, truth, spacing=(1.1, 1.0, 1.2), direction=np.eye(3), shape=(44, 48, 36))
    inverted = ((1.2 - moved) * 200.0).astype(np.float32)  # dark where the fixed is bright, and the other way round
    points = grid_points(image.shape, FIXED_LPS).reshape(-1, 3)[labels.reshape(-1) > 0]
    return Volume(image, FIXED_LPS), Volume(inverted, grid), truth, points


def test_recovers_a_known_affine_across_inverted_contrast(pair):
    fixed, moving, truth, points = pair
    start = np.eye(4)
    before = _max_distance_mm(start, truth, points)
    result = refine_by_local_correlation(fixed, moving, [start], SETTINGS)
    after = _max_distance_mm(result.matrix, truth, points)
    assert before > 4.0, before  # the start is far off: the test can fail
    assert after < 0.2, (before, after)
    assert result.start == 0 and result.report.name == "local correlation"
    assert result.report.metric < -0.2  # minus the mean squared local correlation


def test_keeps_the_right_answer(pair):
    fixed, moving, truth, points = pair
    result = refine_by_local_correlation(fixed, moving, [truth], SETTINGS)
    assert _max_distance_mm(result.matrix, truth, points) < 0.2


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_starts_from_the_candidate_it_scores_best(pair, order):
    fixed, moving, truth, _ = pair
    wrong = truth.copy()
    wrong[:3, 3] += [12.0, -10.0, 8.0]
    candidates = [(truth, wrong)[i] for i in order]
    settings = AffineSettings(local_levels_mm=(2.0,), local_kernels=(3,), local_iterations=(0,))  # choice only
    result = refine_by_local_correlation(fixed, moving, candidates, settings)
    assert result.start == order.index(0)
    np.testing.assert_array_equal(result.matrix, truth)  # no iterations: the chosen start as it was
    assert f"start {order.index(0)} of 2" in result.report.stop_condition


def test_a_moving_mask_away_from_the_object_leaves_the_start(pair):
    """No point of the fixed support maps inside the moving mask: nothing to compare, nothing moves."""
    fixed, moving, truth, _ = pair
    start = truth.copy()
    start[:3, 3] += 3.0
    corner = np.zeros(moving.shape, bool)
    corner[:3, :3, :3] = True  # a corner of the grid, far from the object
    result = refine_by_local_correlation(fixed, moving, [start], SETTINGS, moving_mask=corner)
    np.testing.assert_allclose(result.matrix, start, atol=1e-12)


def test_a_moving_mask_over_the_whole_scan_changes_almost_nothing(pair):
    """Only the points mapped beyond the moving grid leave (the mask is 0 there, the image only dark)."""
    fixed, moving, truth, points = pair
    start = truth.copy()
    start[:3, 3] += 3.0
    everywhere = np.ones(moving.shape, bool)
    masked = refine_by_local_correlation(fixed, moving, [start], SETTINGS, moving_mask=everywhere)
    plain = refine_by_local_correlation(fixed, moving, [start], SETTINGS)
    assert _max_distance_mm(masked.matrix, plain.matrix, points) < 0.05


def test_expects_a_candidate(pair):
    fixed, moving, _, _ = pair
    with pytest.raises(ValueError, match="expected at least one affine"):
        refine_by_local_correlation(fixed, moving, [], SETTINGS)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"local_stage": "sometimes"}, "local_stage must be one of"),
        ({"local_starts": ()}, "local_starts must be one or more of"),
        ({"local_starts": ("moments", "corners")}, "local_starts must be one or more of"),
        ({"local_levels_mm": (4.0,)}, "one value per level each"),
        ({"local_levels_mm": (), "local_kernels": (), "local_iterations": ()}, "at least one level"),
        ({"local_levels_mm": (4.0, 0.0)}, "local_levels_mm must be > 0"),
        ({"local_kernels": (3, 4)}, "local_kernels must be odd integers >= 3"),
        ({"local_kernels": (1, 5)}, "local_kernels must be odd integers >= 3"),
        ({"local_iterations": (20, -1)}, "local_iterations must be >= 0"),
    ],
)
def test_settings_refuse_each_bad_value(changes, message):
    with pytest.raises(ValueError, match=message):
        AffineSettings(**changes)
