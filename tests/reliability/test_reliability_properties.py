"""Property-based tests (hypothesis) of the loading and resampling path over shapes, spacings, orientations and
intensity scalings. Small grids and a modest number of examples keep them to a few seconds; every property is
exact up to a stated floating-point tolerance, so any failing example hypothesis finds is a real bug.
"""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

import numpy as np
import torch
from conftest import save_lps
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from rel_helpers import rotation

from monai_probreg.data.transforms import registration_transforms
from monai_probreg.networks.velocity_unet import LOG_VAR_MAX, LOG_VAR_MIN, bound_log_var
from monai_probreg.spatial.intensity import normalise_intensity
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.point_sampling import sample_linear
from monai_probreg.spatial.volume_io import read_image

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SIGNED_PERMUTATIONS = [
    np.eye(3)[list(p)] * s for p in itertools.permutations(range(3)) for s in itertools.product([-1.0, 1.0], repeat=3)
]  # the 48 axis-aligned orientations

shapes = st.tuples(*[st.integers(2, 7)] * 3)
spacings = st.tuples(*[st.floats(0.05, 20.0)] * 3)
origins = st.tuples(*[st.floats(-200.0, 200.0)] * 3)
angles = st.tuples(*[st.floats(-180.0, 180.0)] * 3)
exponents = st.floats(-6.0, 9.0)  # intensity scale 1e-6 .. 1e9


def _index_to_lps(signed_permutation: int, angles_deg, spacing, origin, oblique: bool) -> np.ndarray:
    direction = SIGNED_PERMUTATIONS[signed_permutation]
    if oblique:
        direction = rotation(angles_deg) @ direction
    affine = np.eye(4)
    affine[:3, :3] = direction * np.asarray(spacing)
    affine[:3, 3] = origin
    return affine


@SETTINGS
@given(
    shape=shapes,
    perm=st.integers(0, 47),
    oblique=st.booleans(),
    angles_deg=angles,
    spacing=spacings,
    origin=origins,
    exponent=exponents,
    gradient=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_read_then_resample_reproduces_a_linear_field(
    shape, perm, oblique, angles_deg, spacing, origin, exponent, gradient, dtype
):
    """A file whose voxels are f(p) = s * (g . p + 1) at their physical centres p is read with the geometry of its
    header, and trilinear resampling at any physical point inside the grid gives f there (exact for a linear f).
    Tolerances: the header stores the affine in float32 (1e-6 relative of its entries, hence of p) and the voxels
    in float32 (1e-7 relative), so 1e-5 of max |f| covers both with room."""
    index_to_lps = _index_to_lps(perm, angles_deg, spacing, origin, oblique)
    scale, g = 10.0**exponent, np.asarray(gradient) / max(np.abs(spacing).max(), 1.0) / 100.0
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).astype(np.float64)
    points = index @ index_to_lps[:3, :3].T + index_to_lps[:3, 3]
    values = scale * (points @ g + 1.0)
    assume(np.ptp(values) > 1e-4 * np.abs(values).max())  # a (nearly) constant image is refused, as it should be
    with tempfile.TemporaryDirectory() as folder:
        volume = read_image(save_lps(Path(folder) / "f.nii.gz", values.astype(dtype), index_to_lps))
    np.testing.assert_allclose(volume.index_to_lps, index_to_lps, atol=2e-6 * max(1.0, np.abs(index_to_lps).max()))
    np.testing.assert_allclose(volume.array, values, rtol=2e-7, atol=2e-7 * np.abs(values).max())
    inside = np.random.default_rng(0).uniform(0.0, 1.0, (50, 3)) * (np.asarray(shape) - 1)
    query = inside @ index_to_lps[:3, :3].T + index_to_lps[:3, 3]
    np.testing.assert_allclose(
        sample_linear(volume, query), scale * (query @ g + 1.0), rtol=0, atol=1e-5 * np.abs(values).max()
    )


@SETTINGS
@given(
    shape=shapes,
    perm=st.integers(0, 47),
    spacing=spacings,
    origin=origins,
    exponent=exponents,
    offset=st.floats(-10.0, 10.0),
    seed=st.integers(0, 2**16),
)
def test_command_line_and_bundle_give_the_network_the_same_array(shape, perm, spacing, origin, exponent, offset, seed):
    """For any axis-aligned orientation, spacing and intensity units, the command line's model input (ModelGrid
    + normalise_intensity on the ITK read) equals the bundle's (LoadCheckedd, Orientation RAS, percentiles,
    DivisiblePad). Tolerance 1e-5: both rescale the same float32 values to [0, 1], in different operation order."""
    index_to_lps = _index_to_lps(perm, (0, 0, 0), spacing, origin, oblique=False)
    scale = 10.0**exponent
    data = (scale * (np.random.default_rng(seed).random(shape) + offset)).astype(np.float32)
    if data.min() == data.max():
        return  # a constant image is refused by both (tested in test_reliability_inputs)
    with tempfile.TemporaryDirectory() as folder:
        path = save_lps(Path(folder) / "f.nii.gz", data, index_to_lps)
        bundle = registration_transforms(with_labels=False, divisor=4)({"moving": str(path), "fixed": str(path)})
        volume = read_image(path)
    grid = ModelGrid.for_volume(volume, divisor=4)
    ours = grid.to_model(normalise_intensity(volume.array))
    assert ours.shape == tuple(bundle["fixed"].shape[1:])
    np.testing.assert_allclose(ours, bundle["fixed"][0].numpy(), atol=1e-5)
    # both affines come from the header's float32 sform: 1e-5 of its largest entry
    np.testing.assert_allclose(
        grid.ras_affine, bundle["fixed"].affine.numpy(), atol=1e-5 * max(1.0, np.abs(index_to_lps).max())
    )


@SETTINGS
@given(
    seed=st.integers(0, 2**16),
    exponent=exponents,
    offset=st.floats(-10.0, 10.0),
    dtype=st.sampled_from([np.float16, np.float32, np.float64]),
)
def test_intensity_normalisation_ignores_units(seed, exponent, offset, dtype):
    """normalise_intensity(s * x + t) = normalise_intensity(x) in [0, 1] for s > 0, for float16/32/64 storage.
    Tolerance: storing s * (x + offset) in the dtype rounds by eps * |x + offset| relative to the range s of x,
    so 50 * eps * (1 + |offset|) after rescaling, eps at least float32's (the computation's precision)."""
    scale = 10.0**exponent
    if dtype == np.float16:
        scale = min(scale, 1e3)  # float16 holds at most 65504
    x = np.random.default_rng(seed).random((6, 7, 5))
    y = (scale * (x + offset)).astype(dtype)
    ours, reference = normalise_intensity(y), normalise_intensity(x)
    assert np.isfinite(ours).all() and ours.min() >= 0.0 and ours.max() <= 1.0
    eps = max(float(np.finfo(dtype).eps), float(np.finfo(np.float32).eps))  # normalise_intensity works in float32
    np.testing.assert_allclose(ours, reference, atol=50 * eps * (1 + abs(offset)))


@SETTINGS
@given(values=st.lists(st.floats(allow_nan=False, allow_infinity=True, width=32), min_size=1, max_size=64))
def test_log_variance_bound_is_bounded_and_monotonic(values):
    raw = torch.tensor(sorted(values), dtype=torch.float32)
    bounded = bound_log_var(raw)
    assert bool(((bounded >= LOG_VAR_MIN) & (bounded <= LOG_VAR_MAX)).all())
    assert bool((bounded[1:] >= bounded[:-1]).all())
    assert torch.isfinite(torch.exp(bounded)).all()
