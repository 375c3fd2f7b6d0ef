"""monai_probreg.fitting.subject_probe: the subject probe's cases and the frame its errors are taken in."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.data.synthetic import brain_mask
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting import subject_probe as probe
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.scan import Registered
from monai_probreg.uncertainty.calibration import Calibration

# the affine's linear part: 90 degrees about the third LPS axis, then scaled (not orthogonal: L^-1 != L^T)
LINEAR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.2, 0.9, 1.1])
SHIFT = np.array([3.0, -2.0, 1.0])
# the variance components' axes (columns): LPS axes 2, 0, 1 (a cyclic permutation: AXES != AXES.T)
AXES = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
DEFORMABLE = np.array([0.5, -1.0, 2.0])  # the deformable step's displacement, before the affine: |.| = 2.2913
ERROR = np.array([1.0, 0.0, 2.0])  # the deformable step's error, in the posterior's frame (before the affine)
ERROR_COMPONENTS = np.array([2.0, 1.0, 0.0])  # ERROR along AXES' columns, by hand
VARIANCE = np.array([0.25, 1.0, 4.0])


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    image, labels = asymmetric_phantom((24, 28, 20))
    brain = np.where(labels > 0, np.clip(image, 0.05, None) * 200, 0).astype(np.float32)  # skull-stripped
    return save_lps(tmp_path_factory.mktemp("probe") / "template.nii.gz", brain, FIXED_LPS)


def test_a_case_is_the_same_for_the_same_seed_and_samples_inside_the_brain(template):
    case = probe.subject_case("T", template, 7, 300)
    again = probe.subject_case("T", template, 7, 300)
    other = probe.subject_case("T", template, 8, 300)
    assert case.seed == 7 and len(case.voxels) == 300 and np.array_equal(case.voxels, again.voxels)
    assert np.array_equal(case.subject.true_warp, again.subject.true_warp)
    assert not np.array_equal(case.subject.true_warp, other.subject.true_warp)
    assert brain_mask(case.fixed.image).reshape(-1)[case.voxels].all()


def test_errors_are_taken_in_the_posteriors_frame_with_the_calibration_asked(template, monkeypatch):
    """phi = A o (id + d): a registration whose deformable step moved every voxel by DEFORMABLE and missed the truth
    by ERROR (both before the affine A) gives the error ERROR along the variance axes, the std of the variance and the
    length of DEFORMABLE, whatever A's turn and scaling."""
    case = probe.subject_case("T", template, 3, 200)
    points = case.fixed.points
    warp = points @ LINEAR.T + SHIFT - points + LINEAR @ DEFORMABLE  # A(p + d) - p
    case = case._replace(subject=SimpleNamespace(image=case.subject.image, true_warp=warp - LINEAR @ ERROR))
    affine = np.eye(4)
    affine[:3, :3], affine[:3, 3] = LINEAR, SHIFT
    seen = {}

    def fake_register_scan(model, fixed, moving, out_dir, options=None, check=None):
        seen.update(model=model, options=options, moving=moving)
        variance = np.broadcast_to(VARIANCE, points.shape)
        check(Registered(warp.astype(np.float32), affine, points, variance, AXES))
        return {}

    monkeypatch.setattr(probe, "register_scan", fake_register_scan)
    model = LoadedModel(torch.nn.Identity(), 16, torch.device("cpu"), Path("model.pt"), Path("inference.yaml"))
    refinement = RefinementSettings(num_iterations=2)
    std, error, norm = probe.subject_errors(model, case, Calibration(0.5, 0.1, 3.0), 4, refinement)
    assert std.shape == error.shape == norm.shape == (3, 200)
    np.testing.assert_allclose(error, np.broadcast_to(ERROR_COMPONENTS[:, None], (3, 200)), atol=1e-4)
    np.testing.assert_allclose(std, np.broadcast_to(np.sqrt(VARIANCE)[:, None], (3, 200)))
    np.testing.assert_allclose(norm, np.linalg.norm(DEFORMABLE), atol=1e-4)
    # the registration ran with the calibration asked, no quality estimate, the case's seed and the refinement
    assert (seen["model"].std_scale, seen["model"].bias_fraction, seen["model"].quality) == (0.5, 0.1, None)
    assert seen["model"].interval_dof == 3.0
    assert seen["options"].samples == 4 and seen["options"].seed == 3 and seen["options"].affine.seed == 3
    assert seen["options"].refinement == refinement and seen["moving"] is case.subject.image
