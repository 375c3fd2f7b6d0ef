"""``monai-probreg apply`` against ANTs itself: ``ants.apply_transforms`` (antspyx, antsApplyTransforms' code) on the
same files gives the same images and labels (issue #53).

``test_apply.py`` pins the conventions with ITK's ResampleImageFilter + DisplacementFieldTransform as the stand-in for
antsApplyTransforms; here the real ANTs (the ``.[bench]`` extra; the module is skipped without it) resamples what
``apply`` resamples, so a convention ANTs adds on top of ITK (how it reads a field's header, its transform files, its
interpolators, its output header) would show. Geometry, none of it trivial: the asymmetric phantom and its labels on
an oblique (permuted, flipped) anisotropic grid with an offset origin; a reference grid of another shape, rotated off
the axes, left-handed and anisotropic. Transforms: a smooth field on the reference grid written as ``register``
writes ``warp.nii.gz`` (:func:`~monai_probreg.registration.output_folder.write_field`: LPS mm, NIfTI intent
"vector"), a field on a coarser third oblique grid covering part of the reference (interpolated, identity outside),
our ``.tfm`` affine (:func:`~monai_probreg.registration.output_folder.write_transform`) and an affine ``.mat`` written
by ANTs (``ants.write_transform``, centre not at the origin). Interpolation: ``linear`` of the image against ANTs'
``linear``, ``nearest`` of the labels against ANTs' ``nearestNeighbor``.

Acceptance (issue #53): labels identical in at least 99.9% of the voxels; images within 1% of the moving image's
intensity range, as the largest absolute difference over all voxels. Observed with antspyx 0.6.3: every label equal
and the images equal to the bit in all eight cases. Each case also checks that the transform matters (it changes
far more labels and intensities than the tolerances allow: 3-13% of the labels, 40-59% of the range), so a wrong
sign, axis or RAS/LPS reading fails. Measured by reading the file wrongly inside ``apply``: the field negated, or its
L and P components taken as R and A, leaves 87-95% of the labels equal and the image 55-66% of its range off ANTs';
the affine inverted, 78% and 92%.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import PHANTOM_LABELS, asymmetric_phantom, rigid_matrix, save_lps
from scipy.spatial.transform import Rotation
from test_apply import _apply, _array, _oblique_grid, _smooth_field

from monai_probreg.registration.output_folder import write_field, write_transform
from monai_probreg.spatial.physical import grid_points

ants = pytest.importorskip("ants", reason="antspyx (the .[bench] extra) is not installed")

LABEL_AGREEMENT = 0.999  # issue #53: labels identical in at least 99.9% of the voxels
IMAGE_TOLERANCE = 0.01  # issue #53: max |ours - ANTs| within 1% of the moving image's intensity range
MOVED_FACTOR = 10  # the transform changes 10x more than each tolerance allows (against no transform at all)
IN_VIEW = 0.5  # the output shows at least this fraction of the phantom's intensity range: the phantom is in view
HEADER_ATOL = 1e-4  # mm (origin, spacing) and direction cosines: NIfTI's float32 header, read back by ITK

MOVING_SPACING = (1.1, 0.9, 1.2)  # mm, on test_apply's oblique axes
MOVING_CENTRE = (4.0, -6.0, 10.0)  # LPS mm: the origin well away from 0
REFERENCE_SHAPE = (30, 34, 28)
REFERENCE_SPACING = (1.3, 1.0, 1.2)  # mm
REFERENCE_ANGLES_DEG = (15.0, -10.0, 25.0)  # x, y, z Euler: axes off the LPS axes (not a permutation)
REFERENCE_FLIP = np.diag([-1.0, 1.0, 1.0])  # a left-handed index frame (determinant -1)
FIELD_MM = 5.0  # largest displacement component of the smooth fields
COARSE_SHAPE = (12, 14, 11)  # about 25 mm across: part of the reference grid lies outside it
COARSE_SPACING = (2.0, 1.8, 2.1)  # mm
COARSE_OFFSET_MM = (1.0, -2.0, 0.5)  # its centre off the reference's
AFFINE_ANGLES_DEG = (6.0, -4.0, 9.0)
AFFINE_TRANSLATION_MM = (2.0, -1.5, 3.0)
AFFINE_SCALES = (1.04, 0.97, 1.01)  # a true affine, not a rigid map
AFFINE_PIVOT_MM = (3.0, 1.0, -2.0)  # the files' centre (ITK FixedParameters), off the phantom's centre
TRANSFORMS = ("warp", "coarse_field", "affine_tfm", "ants_mat")
ANTS_INTERPOLATORS = {"linear": ("linear", "moving"), "nearest": ("nearestNeighbor", "label")}  # ANTs' name, input


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """The moving image and labels, the reference grid and the four transform files (module docstring)."""
    root = tmp_path_factory.mktemp("apply_ants")
    image, labels = asymmetric_phantom()
    moving_grid = _oblique_grid(image.shape, MOVING_SPACING, MOVING_CENTRE)
    centre = grid_points(image.shape, moving_grid).reshape(-1, 3).mean(0)
    rotation = Rotation.from_euler("xyz", REFERENCE_ANGLES_DEG, degrees=True).as_matrix()
    reference_grid = np.eye(4)
    reference_grid[:3, :3] = rotation @ REFERENCE_FLIP * np.asarray(REFERENCE_SPACING)
    reference_grid[:3, 3] = centre - reference_grid[:3, :3] @ ((np.asarray(REFERENCE_SHAPE) - 1) / 2)
    coarse_grid = _oblique_grid(COARSE_SHAPE, COARSE_SPACING, centre + np.asarray(COARSE_OFFSET_MM))
    matrix = rigid_matrix(AFFINE_ANGLES_DEG, AFFINE_TRANSLATION_MM, centre)
    matrix[:3, :3] = matrix[:3, :3] @ np.diag(AFFINE_SCALES)
    pivot = centre + np.asarray(AFFINE_PIVOT_MM)
    ants_affine = ants.create_ants_transform(
        transform_type="AffineTransform",
        dimension=3,
        matrix=matrix[:3, :3],
        center=pivot,
        translation=matrix[:3, 3] - pivot + matrix[:3, :3] @ pivot,  # T(p) = M (p - c) + c + t
    )
    ants.write_transform(ants_affine, str(root / "affine.mat"))
    transforms = {
        "warp": write_field(root / "warp.nii.gz", _smooth_field(REFERENCE_SHAPE, FIELD_MM, 0), reference_grid),
        "coarse_field": write_field(root / "coarse.nii.gz", _smooth_field(COARSE_SHAPE, FIELD_MM, 1), coarse_grid),
        "affine_tfm": write_transform(root / "affine.tfm", matrix, pivot),
        "ants_mat": root / "affine.mat",
    }
    return SimpleNamespace(
        image=image,
        moving=save_lps(root / "moving.nii.gz", image, moving_grid),
        label=save_lps(root / "label.nii.gz", labels, moving_grid),
        reference=save_lps(root / "reference.nii.gz", np.zeros(REFERENCE_SHAPE, np.float32), reference_grid),
        transforms=transforms,
    )


@pytest.mark.parametrize("interpolation", list(ANTS_INTERPOLATORS))
@pytest.mark.parametrize("transform", TRANSFORMS)
def test_apply_matches_ants_apply_transforms(scene, tmp_path: Path, transform: str, interpolation: str):
    """apply and ``ants.apply_transforms`` on the same files: the same grid, labels identical in >= 99.9% of the
    voxels, images within 1% of the range; and the transform moves 10x more than that (against none at all)."""
    ants_name, source = ANTS_INTERPOLATORS[interpolation]
    moving, path = getattr(scene, source), scene.transforms[transform]
    out = tmp_path / "ours.nii.gz"
    result = _apply("-t", path, "-i", moving, "-r", scene.reference, "-o", out, "-n", interpolation)
    assert result.rc == 0, result.err
    assert ("outside the field's grid" in result.err) == (transform == "coarse_field")  # partial coverage exercised
    fixed, moving_image = ants.image_read(str(scene.reference)), ants.image_read(str(moving))
    theirs = ants.apply_transforms(fixed=fixed, moving=moving_image, transformlist=[str(path)], interpolator=ants_name)
    unmoved = ants.resample_image_to_target(moving_image, fixed, interp_type=ants_name).numpy()
    written = ants.image_read(str(out))
    for attribute in ("origin", "spacing", "direction"):
        np.testing.assert_allclose(getattr(written, attribute), getattr(theirs, attribute), atol=HEADER_ATOL)
    ours, theirs = _array(out), theirs.numpy()
    assert ours.shape == theirs.shape == REFERENCE_SHAPE
    if interpolation == "nearest":
        agreement = np.mean(ours == theirs)
        moved = np.mean(theirs != unmoved)
        assert agreement >= LABEL_AGREEMENT, f"labels equal in {agreement:.5f} of the voxels"
        assert moved > MOVED_FACTOR * (1 - LABEL_AGREEMENT), f"the transform changes {moved:.5f} of the labels"
        assert set(np.unique(ours)) == {0, *PHANTOM_LABELS}  # every label in view
    else:
        scale = np.ptp(scene.image)
        difference = np.abs(ours - theirs).max() / scale
        moved = np.abs(theirs - unmoved).max() / scale
        assert difference <= IMAGE_TOLERANCE, f"max |ours - ANTs| = {difference:.2e} of the range"
        assert moved > MOVED_FACTOR * IMAGE_TOLERANCE, f"the transform changes the image by {moved:.3f} of the range"
        assert np.ptp(ours) > IN_VIEW * scale
