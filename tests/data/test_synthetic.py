"""monai_probreg.data.synthetic: a subject made from a template by a known transform (the demo's ground truth)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIXED_LPS, asymmetric_phantom

from monai_probreg.data.synthetic import SyntheticSettings, brain_mask, synthesize_subject
from monai_probreg.spatial.physical import grid_points
from monai_probreg.spatial.point_sampling import sample_linear
from monai_probreg.spatial.volume_io import Volume

CLEAN = {"bias_coeff": 0.0, "noise_fraction": 0.0}  # no intensity change: the geometry alone


@pytest.fixture(scope="module")
def template() -> Volume:
    """The asymmetric phantom with an exact zero background, on an anisotropic RAS grid (1.2 x 1 x 1.5 mm)."""
    image, labels = asymmetric_phantom((40, 44, 36))
    index_to_lps = FIXED_LPS @ np.diag([1.2, 1.0, 1.5, 1.0])
    return Volume(np.where(labels > 0, np.clip(image, 0.05, None), 0.0).astype(np.float32), index_to_lps, "t.nii")


def _centre_of_mass(volume: Volume) -> np.ndarray:
    weights = np.asarray(volume.array, np.float64)
    points = grid_points(volume.shape, volume.index_to_lps)
    return (points * weights[..., None]).reshape(-1, 3).sum(0) / weights.sum()


def test_nothing_drawn_gives_the_template_and_a_zero_field(template):
    settings = SyntheticSettings(max_rotation_deg=0, max_shift_mm=0, deform_rms_mm=0, axcodes=None, **CLEAN)
    subject = synthesize_subject(template, settings, seed=1)
    np.testing.assert_allclose(subject.image.array, template.array, atol=1e-5)
    np.testing.assert_allclose(subject.true_warp, 0, atol=1e-6)
    np.testing.assert_array_equal(subject.image.index_to_lps, template.index_to_lps)


def test_the_subject_is_stored_in_another_orientation_with_a_true_header(template):
    settings = SyntheticSettings(max_rotation_deg=0, max_shift_mm=0, deform_rms_mm=0, axcodes="PIR", **CLEAN)
    subject = synthesize_subject(template, settings, seed=1)
    assert subject.image.axcodes == "PIR" and template.axcodes == "RAS"
    assert subject.image.shape == (template.shape[1], template.shape[2], template.shape[0])
    # the same anatomy at the same physical points: the permuted, flipped voxels sampled back onto the template grid
    points = grid_points(template.shape, template.index_to_lps)
    np.testing.assert_allclose(sample_linear(subject.image, points), template.array, atol=1e-5)


def test_a_shift_moves_the_anatomy_by_the_shift_and_the_field_says_so(template):
    subject = synthesize_subject(template, SyntheticSettings(max_rotation_deg=0, deform_rms_mm=0, **CLEAN), seed=2)
    shift = np.array(subject.shift_mm)
    assert np.abs(shift).max() > 1.0
    # D(p) = phi(p) - p = the shift everywhere: a template point p is found at p + shift in the subject
    np.testing.assert_allclose(subject.true_warp, np.broadcast_to(shift, subject.true_warp.shape), atol=1e-5)
    np.testing.assert_allclose(_centre_of_mass(subject.image), _centre_of_mass(template) + shift, atol=0.05)
    assert subject.image.axcodes == "PIR"  # the default: stored as a sagittal acquisition might be


def test_pulling_the_subject_back_through_the_true_field_gives_the_template(template):
    settings = SyntheticSettings(max_rotation_deg=8, max_shift_mm=3, deform_rms_mm=2.0, deform_spacing_mm=12, **CLEAN)
    subject = synthesize_subject(template, settings, seed=3)
    points = grid_points(template.shape, template.index_to_lps)
    back = sample_linear(subject.image, points + subject.true_warp)  # warped(p) = subject(phi(p))
    inner = brain_mask(template) & (sample_linear(subject.image, points + subject.true_warp) > 0)
    size = np.linalg.norm(subject.true_warp - subject.true_warp[inner].mean(0), axis=-1)[inner]
    assert np.median(size) > 0.5  # a real deformation besides the rigid part
    error = np.abs(back - template.array)[inner]
    moved = np.abs(sample_linear(subject.image, points) - template.array)[inner]  # unregistered, same points
    assert np.median(error) < 0.2 * np.median(moved)  # only two linear interpolations apart
    assert subject.inverse_error_mm < 0.05


def test_bias_and_noise_change_the_intensities_not_the_geometry(template):
    geometry = {"max_rotation_deg": 3, "max_shift_mm": 2, "deform_rms_mm": 1.0, "axcodes": None}
    clean = synthesize_subject(template, SyntheticSettings(**geometry, **CLEAN), seed=4)
    noisy = synthesize_subject(template, SyntheticSettings(**geometry, bias_coeff=0.3, noise_fraction=0.05), seed=4)
    np.testing.assert_array_equal(clean.true_warp, noisy.true_warp)
    assert not np.allclose(clean.image.array, noisy.image.array, atol=1e-3)
    assert (noisy.image.array[template.array == 0] > 0).mean() > 0.9  # Rician noise in the background too


def test_a_seed_repeats_the_draw_and_another_seed_differs(template):
    a, b, c = (synthesize_subject(template, seed=s) for s in (5, 5, 6))
    np.testing.assert_array_equal(a.image.array, b.image.array)
    np.testing.assert_array_equal(a.true_warp, b.true_warp)
    assert a.rotation_deg != c.rotation_deg and not np.allclose(a.true_warp, c.true_warp)


@pytest.mark.parametrize(
    "field, value",
    [
        ("max_rotation_deg", -1.0),
        ("noise_fraction", float("nan")),
        ("deform_spacing_mm", 0.0),
        ("num_steps", 0),
        ("axcodes", "PPR"),
        ("axcodes", "RA"),
    ],
)
def test_bad_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        SyntheticSettings(**{field: value})


def test_a_template_without_brain_is_refused(template):
    with pytest.raises(ValueError, match="no non-zero voxel"):
        synthesize_subject(template.with_array(np.zeros_like(template.array)))
