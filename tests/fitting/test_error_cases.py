"""monai_probreg.fitting.error_cases: the error model's cases read the features at the subject probe's voxels and the
deformable step's squared error, and the fit recovers a planted model."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting import error_cases, subject_probe
from monai_probreg.registration.model import LoadedModel
from monai_probreg.registration.scan import Registered
from monai_probreg.uncertainty.error_model import ERROR_FEATURES

# the affine's linear part (not orthogonal): the error is taken before it, as the subject probe takes it
LINEAR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.2, 0.9, 1.1])
ERROR = np.array([1.0, -2.0, 2.0])  # |ERROR|^2 = 9


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    image, labels = asymmetric_phantom((24, 28, 20))
    brain = np.where(labels > 0, np.clip(image, 0.05, None) * 200, 0).astype(np.float32)
    return save_lps(tmp_path_factory.mktemp("errors") / "template.nii.gz", brain, FIXED_LPS)


def _fake_register_scan(seen: dict, scale: float = 1.0):
    def register_scan(model, fixed, moving, out_dir, options=None, check=None):
        seen.update(options=options)
        shape = fixed.grid.shape
        # feature k: the model grid's first index times k (a map that differs voxel by voxel, known in closed form)
        index = np.indices(shape)[0].astype(np.float32)
        features = np.stack([k * index for k in range(len(ERROR_FEATURES))])
        points = fixed.points
        truth = seen["truth"]
        warp = truth + scale * (LINEAR @ ERROR)  # misses the truth by LINEAR ERROR: ERROR before the affine
        affine = np.eye(4)
        affine[:3, :3] = LINEAR
        check(Registered(warp.astype(np.float32), affine, points, None, np.eye(3), features))
        return {}

    return register_scan


def test_a_case_reads_the_features_at_the_probes_voxels_and_the_squared_error(template, monkeypatch):
    seen = {}
    real_case = error_cases.subject_case

    def subject_case(*args):
        case = real_case(*args)
        seen["truth"], seen["case"] = case.subject.true_warp, case
        return case

    monkeypatch.setattr(error_cases, "subject_case", subject_case)
    monkeypatch.setattr(subject_probe, "register_scan", _fake_register_scan(seen))
    model = LoadedModel(torch.nn.Identity(), 16, torch.device("cpu"), Path("model.pt"), Path("inference.yaml"))
    refinement = RefinementSettings(num_iterations=2)
    features, squared = error_cases.error_case(model, "T", template, 5, refinement)
    case = seen["case"]
    assert features.shape == (len(case.voxels), len(ERROR_FEATURES)) and squared.shape == (len(case.voxels),)
    np.testing.assert_allclose(squared, 9.0, rtol=1e-4)
    # feature k at a voxel = k times its model-grid first index, read through the grid's mapping
    index = case.fixed.grid.to_fixed(np.indices(case.fixed.grid.shape)[0][..., None].astype(np.float32))[..., 0]
    expected = index.reshape(-1)[case.voxels]
    for k in range(len(ERROR_FEATURES)):
        np.testing.assert_allclose(features[:, k], k * expected)
    options = seen["options"]
    assert options.error_features and options.samples == 0 and options.seed == 5 and options.affine.seed == 5
    assert options.refinement == refinement and not options.qc and not options.inverse


def test_no_templates_no_error_model():
    assert error_cases.fitted_error_model(None, SimpleNamespace(images={}), [], RefinementSettings()) is None


def test_the_model_is_fitted_on_every_templates_case_with_its_own_seed(monkeypatch):
    seeds = []
    rng = np.random.default_rng(0)
    truth = rng.normal(size=len(ERROR_FEATURES) + 1)

    def error_case(model, template, path, seed, refinement):
        seeds.append((template, path, seed))
        features = rng.normal(size=(200, len(ERROR_FEATURES)))
        return features, np.exp(features @ truth[:-1] + truth[-1]) - error_cases.SQUARED_ERROR_FLOOR

    monkeypatch.setattr(error_cases, "error_case", error_case)
    index = SimpleNamespace(images={"A": "a.nii.gz", "B": "b.nii.gz"})
    fitted = error_cases.fitted_error_model(None, index, ["A", "B"], RefinementSettings())
    assert fitted == pytest.approx(tuple(truth), abs=1e-6)
    seed = error_cases.ERROR_MODEL_SEED
    assert seeds == [("A", "a.nii.gz", seed), ("B", "b.nii.gz", seed + 1)]
