"""monai_probreg.spatial.physical / resample: the voxel <-> mm convention against ITK itself, composition, inverse, files.

Grids here are deliberately awkward: axes permuted, one flipped, anisotropic spacing, an offset origin, so that an
axis-order, sign or spacing mistake cannot cancel out.
"""

from __future__ import annotations

import itk
import nibabel as nib
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from monai_probreg import compose_displacements, integrate_velocity, warp_image
from monai_probreg.registration.output_folder import write_field, write_transform
from monai_probreg.spatial import physical
from monai_probreg.spatial.physical import (
    affine_from_itk,
    affine_to_itk,
    apply_affine,
    compose_forward,
    compose_inverse,
    displacement_transform,
    field_to_itk,
    grid_points,
    index_map,
    mapped_index,
    mm_to_voxel,
    resample_with_itk,
    voxel_to_mm,
)
from monai_probreg.spatial.point_sampling import LinearSampler, sample_linear, sample_nearest
from monai_probreg.spatial.volume_io import Volume, volume_from_itk, volume_to_itk

SHAPE = (11, 9, 13)


def _grid() -> np.ndarray:
    affine = np.eye(4)
    affine[:3, :3] = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) * [0.8, 1.5, 1.1]
    affine[:3, 3] = [12.0, -7.0, 30.0]
    return affine


def _smooth(shape, channels, magnitude, seed) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(1, channels, 3, 3, 3, generator=g, dtype=torch.float64)
    field = F.interpolate(coarse, size=shape, mode="trilinear", align_corners=True)[0]
    return (field * magnitude / field.abs().max()).numpy()


def _affine() -> np.ndarray:
    from conftest import rigid_matrix

    matrix = rigid_matrix([8.0, -5.0, 11.0], [3.0, -2.0, 4.0], [5.0, 0.0, 20.0])
    matrix[:3, :3] = matrix[:3, :3] @ np.diag([1.05, 0.95, 1.02])
    return matrix


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_plus_one_voxel_is_the_itk_displacement_r_times_u(axis):
    """Pin: u = +1 voxel along array axis k  ==  d = R[:, k] mm in ITK, and both pull from index + 1 along k."""
    image = np.zeros(SHAPE, np.float32)
    bright = (5, 4, 6)
    image[bright] = 1.0
    u = np.zeros((3, *SHAPE))
    u[axis] = 1.0
    field = voxel_to_mm(u, _grid())
    np.testing.assert_allclose(field[0, 0, 0], _grid()[:3, axis])
    volume = Volume(image, _grid())
    warped = itk.array_from_image(
        resample_with_itk(
            volume_to_itk(volume), volume_to_itk(volume), displacement_transform(field_to_itk(field, _grid()))
        )
    )
    expected = list(bright)
    expected[axis] -= 1  # warped[i] = image[i + e_k]: content moves to the lower index
    ours = warp_image(torch.from_numpy(image)[None, None], torch.from_numpy(u).float()[None])[0, 0].numpy()
    assert np.unravel_index(ours.argmax(), SHAPE) == tuple(expected)
    assert np.unravel_index(warped.transpose(2, 1, 0).argmax(), SHAPE) == tuple(expected)


def test_itk_reproduces_the_model_warp_of_a_smooth_field():
    """The model's torch warp and ITK with R @ u agree wherever x + u stays inside the grid (ITK fills 0 outside,
    the model extends the border). Tolerance 1e-5: float32 grid_sample and float32 field storage."""
    image = _smooth(SHAPE, 1, 1.0, seed=0)[0].astype(np.float32)
    u = _smooth(SHAPE, 3, 2.0, seed=1)
    ours = warp_image(torch.from_numpy(image)[None, None], torch.from_numpy(u).float()[None])[0, 0].numpy()
    volume = Volume(image, _grid())
    transform = displacement_transform(field_to_itk(voxel_to_mm(u, _grid()), _grid()))
    theirs = itk.array_from_image(resample_with_itk(volume_to_itk(volume), volume_to_itk(volume), transform))
    target = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij")) + u
    inside = np.all((target >= 0) & (target <= np.array(SHAPE).reshape(3, 1, 1, 1) - 1), axis=0)
    assert inside.mean() > 0.5
    np.testing.assert_allclose(theirs.transpose(2, 1, 0)[inside], ours[inside], atol=1e-5)
    np.testing.assert_allclose(mm_to_voxel(voxel_to_mm(u, _grid()), _grid()), u, atol=1e-12)


def test_sampling_matches_itk_resampling_linear_and_nearest():
    """Our sampler has ITK's semantics (inside = within half a voxel of the grid, 0 outside, half-up rounding)."""
    rng = np.random.default_rng(0)
    moving = Volume(_smooth(SHAPE, 1, 100.0, seed=2)[0].astype(np.float32), _grid())
    labels = Volume(rng.integers(0, 5, SHAPE).astype(np.int16), _grid())
    reference = Volume(np.zeros((14, 12, 10), np.float32), np.diag([1.0, 1.2, 0.9, 1.0]) @ np.eye(4))
    reference.index_to_lps[:3, 3] = [-8.0, -12.0, 14.0]
    points = apply_affine(_affine(), grid_points(reference.shape, reference.index_to_lps))
    transform = affine_to_itk(_affine())
    theirs = itk.array_from_image(resample_with_itk(volume_to_itk(moving), volume_to_itk(reference), transform))
    ours = sample_linear(moving, points)
    assert (ours == 0).mean() > 0.1 and (ours != 0).mean() > 0.1  # both inside and outside points are tested
    np.testing.assert_allclose(ours, theirs.transpose(2, 1, 0), atol=1e-3)  # float32 output of values ~100
    theirs = itk.array_from_image(
        resample_with_itk(volume_to_itk(labels, np.int16), volume_to_itk(reference), transform, nearest=True)
    )
    np.testing.assert_array_equal(sample_nearest(labels, points), theirs.transpose(2, 1, 0))


def test_compose_forward_is_itk_composite_of_affine_after_deformable():
    d = voxel_to_mm(_smooth(SHAPE, 3, 2.0, seed=3), _grid())
    composed = compose_forward(d, _grid(), _affine())
    composite = itk.CompositeTransform[itk.D, 3].New()
    composite.AddTransform(affine_to_itk(_affine(), center=np.array([3.0, 1.0, -2.0])))
    composite.AddTransform(displacement_transform(field_to_itk(d, _grid())))  # the last added is applied first
    points = grid_points(SHAPE, _grid())
    for index in [(0, 0, 0), (5, 4, 6), (10, 8, 12), (3, 7, 1)]:
        expected = np.asarray(composite.TransformPoint([float(x) for x in points[index]]))
        np.testing.assert_allclose(points[index] + composed[index], expected, atol=1e-4)  # float32 field storage


# a rotated, permuted direction for the moving grid (columns: unit axes)
DIRECTION_OBLIQUE = np.array([[0.0, 0.8, 0.6], [0.0, -0.6, 0.8], [1.0, 0.0, 0.0]])


def test_compose_inverse_equals_its_definition_point_by_point():
    """The slab-wise, broadcast computation against D_inv(q) = a + d_inv(a) - q written out with explicit points
    (a = A^-1 q; d_inv linear, border-extended), on an oblique moving grid that reaches outside d_inv's grid, with
    slabs of 3 rows (the last one short)."""
    d_inv = voxel_to_mm(_smooth(SHAPE, 3, 2.0, seed=7), _grid())
    moving_grid = np.eye(4)
    moving_grid[:3, :3] = DIRECTION_OBLIQUE @ np.diag([1.3, 0.8, 1.1])
    moving_grid[:3, 3] = [-6.0, 4.0, -3.0]
    moving_shape = (17, 13, 15)
    ours = compose_inverse(Volume(d_inv, _grid()), _affine(), moving_shape, moving_grid, rows_per_chunk=3)
    q = grid_points(moving_shape, moving_grid)
    a = apply_affine(np.linalg.inv(_affine()), q)
    index = np.linalg.solve(_grid()[:3, :3], (a - _grid()[:3, 3]).reshape(-1, 3).T).T
    assert (index < -0.5).any() or (index > np.asarray(SHAPE) - 0.5).any()  # the border rule is exercised
    expected = a + sample_linear(Volume(d_inv, _grid()), a, outside="border") - q
    np.testing.assert_allclose(ours, expected, atol=1e-4)  # float32 coordinates and field values


def test_grid_points_are_index_to_lps_of_every_index():
    matrix = _grid()
    points = grid_points((4, 3, 5), matrix)
    for index in [(0, 0, 0), (3, 2, 4), (1, 2, 3)]:
        np.testing.assert_allclose(
            points[index], matrix[:3, :3] @ np.asarray(index, float) + matrix[:3, 3], rtol=0, atol=1e-12
        )


def test_index_map_is_the_matrix_applied_to_every_index_plus_the_offset():
    matrix = _affine() @ _grid()
    offset = np.random.default_rng(4).normal(size=(4, 3, 5, 3))
    ours = index_map((4, 3, 5), matrix, offset)
    for index in [(0, 0, 0), (3, 2, 4), (1, 2, 3)]:
        expected = matrix[:3, :3] @ np.asarray(index, float) + matrix[:3, 3] + offset[index]
        np.testing.assert_allclose(ours[index], expected, rtol=0, atol=1e-12)


def test_mapped_index_is_the_continuous_index_of_the_moved_points():
    """mapped_index(...) = T^-1 (A p + field(p)) against explicit points, and sampling at it (index only, no points)
    gives what sampling at those points gives: the same voxels, bit for bit."""
    field = voxel_to_mm(_smooth(SHAPE, 3, 2.0, seed=5), _grid()).astype(np.float32)
    target = np.eye(4)
    target[:3, :3] = DIRECTION_OBLIQUE @ np.diag([1.3, 0.8, 1.1])
    target[:3, 3] = [-6.0, 4.0, -3.0]
    moved = apply_affine(_affine(), grid_points(SHAPE, _grid())) + field
    expected = np.linalg.solve(target[:3, :3], (moved - target[:3, 3]).reshape(-1, 3).T).T.reshape(*SHAPE, 3)
    ours = mapped_index(SHAPE, _grid(), target, _affine(), field)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        mapped_index(SHAPE, _grid(), _grid()),
        np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), axis=-1),
        atol=1e-9,
    )  # a grid onto itself: its own index
    volume = Volume(_smooth((17, 13, 15), 1, 50.0, seed=6)[0], target)
    labels = Volume(np.random.default_rng(1).integers(0, 6, (17, 13, 15)).astype(np.int16), target)
    np.testing.assert_array_equal(sample_linear(volume, None, index=ours), sample_linear(volume, moved, index=ours))
    np.testing.assert_allclose(sample_linear(volume, None, index=ours), sample_linear(volume, moved), atol=1e-9)
    np.testing.assert_array_equal(sample_nearest(labels, None, index=ours), sample_nearest(labels, moved))


def test_sampling_needs_points_or_their_index():
    volume = Volume(np.zeros(SHAPE, np.float32), _grid())
    with pytest.raises(ValueError, match="expected points or their index"):
        sample_linear(volume, None)
    with pytest.raises(ValueError, match="expected points or their index"):
        sample_nearest(volume, None)


def test_compose_inverse_undoes_compose_forward():
    """q = p + D(p), then q + D_inv(q) comes back to p as far as exp(-v) inverts exp(v) on the model grid: the
    residual must equal the model's own voxel-space residual u + u_inv(x + u) (in mm; up to ~0.3 mm for this rough
    2 mm field on an 11-voxel grid). Tolerance 0.1 mm: D_inv is stored on the (rotated) moving grid, and
    re-interpolating the piecewise-trilinear d_inv there errs by ~ spacing x the jumps of its gradient (0.08 mm
    observed with 1 mm voxels, 0.06 mm with 0.5 mm ones); a convention error would be millimetres."""
    velocity = torch.from_numpy(_smooth(SHAPE, 3, 1.5, seed=4)).float()[None]
    u, u_inv = integrate_velocity(velocity), integrate_velocity(-velocity)
    residual = voxel_to_mm(compose_displacements(u_inv, u)[0].double().numpy(), _grid())
    u, u_inv = u[0].double().numpy(), u_inv[0].double().numpy()
    forward = compose_forward(voxel_to_mm(u, _grid()), _grid(), _affine())
    mapped_all = (grid_points(SHAPE, _grid()) + forward).reshape(-1, 3)
    spacing = np.array([1.1, 0.9, 1.3])
    moving_grid = np.diag([*spacing, 1.0])
    moving_grid[:3, 3] = mapped_all.min(0) - 2.0  # a moving grid covering the mapped points, 2 mm margin
    moving_shape = tuple(int(n) for n in np.ceil((np.ptp(mapped_all, axis=0) + 4.0) / spacing) + 1)
    inverse = compose_inverse(Volume(voxel_to_mm(u_inv, _grid()), _grid()), _affine(), moving_shape, moving_grid)
    interior = (slice(2, -2),) * 3
    points = grid_points(SHAPE, _grid())[interior].reshape(-1, 3)
    mapped = points + forward[interior].reshape(-1, 3)
    back = mapped + sample_linear(Volume(inverse, moving_grid), mapped)
    np.testing.assert_allclose(back - points, residual[interior].reshape(-1, 3), atol=0.1)


def test_affine_itk_round_trip_with_centre(tmp_path):
    transform = affine_to_itk(_affine(), center=np.array([10.0, -4.0, 2.0]))
    np.testing.assert_allclose(affine_from_itk(transform), _affine(), atol=1e-12)
    point = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.asarray(transform.TransformPoint(point.tolist())), apply_affine(_affine(), point))
    write_transform(tmp_path / "a.tfm", _affine(), np.array([10.0, -4.0, 2.0]))
    read = itk.transformread(str(tmp_path / "a.tfm"))[0]
    np.testing.assert_allclose(affine_from_itk(read), _affine(), atol=1e-9)
    assert "AffineTransform_double_3_3" in (tmp_path / "a.tfm").read_text()


def test_ants_reads_the_transform_file(tmp_path):
    """ANTs (antspyx, in the bench extra) reads our text affine.tfm and maps a point as we do."""
    ants = pytest.importorskip("ants")
    write_transform(tmp_path / "a.tfm", _affine(), np.array([10.0, -4.0, 2.0]))
    point = np.array([1.0, 2.0, 3.0])
    mapped = ants.read_transform(str(tmp_path / "a.tfm")).apply_to_point(point.tolist())
    np.testing.assert_allclose(mapped, apply_affine(_affine(), point), atol=1e-6)


def test_bad_transform_file_suffix(tmp_path):
    with pytest.raises(ValueError, match=r"expected a \.tfm or \.txt path"):
        write_transform(tmp_path / "a.h5", _affine())


def test_bad_non_finite_transform_is_not_written(tmp_path):
    matrix = _affine().copy()
    matrix[0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_transform(tmp_path / "a.tfm", matrix)
    assert not list(tmp_path.iterdir())


def test_rigid_transform_is_written_as_an_equivalent_affine(tmp_path):
    """A rigid ITK transform (its matrix and centre) reads back as the same map."""
    rigid = itk.VersorRigid3DTransform[itk.D].New()
    rigid.SetCenter([1.0, -2.0, 3.0])
    versor = itk.Versor[itk.D]()
    versor.Set([0.0, 0.0, 1.0], 0.3)  # 0.3 rad about S
    rigid.SetRotation(versor)
    rigid.SetTranslation([4.0, 5.0, -6.0])
    write_transform(tmp_path / "r.tfm", affine_from_itk(rigid), np.asarray(rigid.GetCenter()))
    read = itk.transformread(str(tmp_path / "r.tfm"))[0]
    np.testing.assert_allclose(affine_from_itk(read), affine_from_itk(rigid), atol=1e-12)


def test_field_file_stores_lps_millimetres_as_an_itk_vector_image(tmp_path):
    """What ANTs expects: NIfTI intent vector, (X, Y, Z, 1, 3), values = the LPS vectors (no RAS sign flip)."""
    field = voxel_to_mm(_smooth(SHAPE, 3, 2.0, seed=5), _grid())
    write_field(tmp_path / "warp.nii.gz", field, _grid())
    stored = nib.load(tmp_path / "warp.nii.gz")
    assert stored.shape == (*SHAPE, 1, 3) and stored.header.get_intent()[0] == "vector"
    np.testing.assert_allclose(np.asarray(stored.dataobj)[:, :, :, 0, :], field, atol=1e-5)
    read = itk.imread(str(tmp_path / "warp.nii.gz"))
    volume = volume_from_itk(read) if read.GetNumberOfComponentsPerPixel() == 1 else None
    assert volume is None  # a vector image
    np.testing.assert_allclose(itk.array_from_image(read).transpose(2, 1, 0, 3), field, atol=1e-5)
    np.testing.assert_allclose(np.asarray(read.GetOrigin()), _grid()[:3, 3], atol=1e-5)


def test_row_slabs_cover_the_rows_in_order():
    assert physical.row_slabs((5, 3, 4), voxels=24) == [slice(0, 2), slice(2, 4), slice(4, 5)]
    assert physical.row_slabs((3, 3, 4), voxels=1) == [slice(0, 1), slice(1, 2), slice(2, 3)]  # at least one row
    assert physical.row_slabs((3, 3, 4), voxels=10**9) == [slice(0, 3)]


def test_maps_of_a_slab_are_that_slab_of_the_whole_grids_to_the_bit():
    """index_map, mapped_index and compose_forward with first_row: each value from its own index, as on the whole grid
    (not the slab's start folded into the matrix, which rounds differently)."""
    rng = np.random.default_rng(1)
    target = _grid() @ np.diag([1.3, 0.7, 1.1, 1.0])
    field = (rng.standard_normal((*SHAPE, 3)) * 2).astype(np.float32)
    d = rng.standard_normal((*SHAPE, 3))
    whole = {
        "index": index_map(SHAPE, _affine() @ _grid()),
        "mapped": mapped_index(SHAPE, _grid(), target, _affine(), field),
        "composed": compose_forward(d, _grid(), _affine()),
    }
    for rows in physical.row_slabs(SHAPE, voxels=2 * SHAPE[1] * SHAPE[2]):
        slab = (rows.stop - rows.start, *SHAPE[1:])
        assert np.array_equal(index_map(slab, _affine() @ _grid(), first_row=rows.start), whole["index"][rows])
        mapped = mapped_index(slab, _grid(), target, _affine(), field[rows], first_row=rows.start)
        assert np.array_equal(mapped, whole["mapped"][rows])
        assert np.array_equal(compose_forward(d[rows], _grid(), _affine(), rows.start), whole["composed"][rows])


def test_a_linear_sampler_gives_sample_linears_values_per_call():
    rng = np.random.default_rng(2)
    volume = Volume(rng.random((5, 6, 4, 2)), _grid())
    index = rng.uniform(-1, 6, (3, 4, 5, 3))
    sampler = LinearSampler(volume, fill=-1.0)
    assert np.array_equal(sampler(None, index=index), sample_linear(volume, None, fill=-1.0, index=index))
    assert np.array_equal(sampler(None, index=index[1:]), sample_linear(volume, None, fill=-1.0, index=index[1:]))
    with pytest.raises(ValueError, match="outside"):
        LinearSampler(volume, outside="wrap")


@pytest.mark.parametrize("layout", ["C", "F", "flipped"])
def test_nearest_samples_do_not_depend_on_the_arrays_memory_layout(layout):
    """sample_nearest reads a C- or Fortran-ordered label map (nibabel's order) in place, any other layout from one
    copy, and picks the same voxels for every layout, against a brute-force reading of each index."""
    from monai_probreg.spatial.point_sampling import _flat_view

    rng = np.random.default_rng(3)
    labels = rng.integers(0, 200, (7, 5, 6)).astype(np.uint8)
    if layout == "flipped":  # the same values through a view with a negative stride: neither C- nor Fortran-ordered
        array = np.flip(np.flip(labels, 0).copy(), 0)
        assert not (array.flags.c_contiguous or array.flags.f_contiguous)
    else:
        array = labels if layout == "C" else np.asfortranarray(labels)
    index = rng.uniform(-1.0, 7.5, (4, 3, 2, 3))
    ours = sample_nearest(Volume(array, _grid()), None, fill=255, index=index)
    nearest = np.floor(index + 0.5).astype(int)
    inside = ((index >= -0.5) & (index < np.array(labels.shape) - 0.5)).all(-1)
    expected = np.full(index.shape[:-1], 255, np.uint8)
    expected[inside] = labels[tuple(nearest[inside].T)]
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(ours, expected)
    flat, _ = _flat_view(array)
    assert np.shares_memory(flat.numpy(), array) == (layout != "flipped")  # read in place unless it cannot be
