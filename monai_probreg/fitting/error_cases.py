"""The error model's cases: synthetic subjects of training scans, registered by the command, whose errors are known.

:mod:`monai_probreg.uncertainty.error_model` predicts the answer's squared error from features of the registered
pair. Its coefficients are fitted here, by least squares, on cases made as the calibration's subject probe makes its
own (:mod:`monai_probreg.fitting.subject_probe`: a training scan turned, shifted and deformed by a known field, with a
bias field and noise, registered back onto it by :func:`~monai_probreg.registration.scan.register_scan`), from other
training scans than the subject probe's and seeds far from its own (:data:`ERROR_MODEL_SEED`): the calibration is
then fitted, and scored held out, on cases the error model never saw. Per case, at the subject probe's subsampled
brain voxels: the features (on the model grid, read on the fixed grid) and the squared error of the answer's
deformable step, mm^2 (its components summed; the frame does not change a length).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from monai_probreg.data.dataset import DatasetIndex
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.population_probe import VOXELS_PER_CASE
from monai_probreg.fitting.subject_probe import SUBJECT_SEED, registered_case, subject_case
from monai_probreg.registration.model import LoadedModel
from monai_probreg.uncertainty.error_model import fit_error_model

__all__ = ["ERROR_MODEL_SEED", "ERROR_MODEL_TEMPLATES", "SQUARED_ERROR_FLOOR", "error_case", "fitted_error_model"]

ERROR_MODEL_TEMPLATES = 8  # training scans the error model is fitted on (those after the subject probe's)
ERROR_MODEL_SEED = SUBJECT_SEED + 500  # template n's synthetic subject: this seed + n (the subject probe's: + 0..)
SQUARED_ERROR_FLOOR = 1e-6  # mm^2, inside the fitted log of the squared error (a voxel the answer got exactly)


def error_case(
    model: LoadedModel, template_id: str, path: str | Path, seed: int, refinement: RefinementSettings
) -> tuple[np.ndarray, np.ndarray]:
    """(features (N, F), squared errors (N,) mm^2) of the synthetic subject of the scan at ``path`` for ``seed``,
    registered by the command's path with ``model`` (raw posterior) and ``refinement``."""
    case = subject_case(template_id, path, seed, VOXELS_PER_CASE, model.divisor)
    registered = registered_case(model, case, 0, refinement, error_features=True)
    grid = case.fixed.grid
    columns = [grid.to_fixed(f[..., None])[..., 0].reshape(-1)[case.voxels] for f in registered.error_features]
    warp = registered.warp.reshape(-1, 3)[case.voxels].astype(np.float64)
    truth = case.subject.true_warp.reshape(-1, 3)[case.voxels].astype(np.float64)
    error = np.linalg.solve(registered.affine[:3, :3], (warp - truth).T).T  # the deformable step's, as the probe's
    return np.stack(columns, 1).astype(np.float64), (error**2).sum(1)


def fitted_error_model(
    model: LoadedModel, index: DatasetIndex, templates: Sequence[str], refinement: RefinementSettings
) -> tuple[float, ...] | None:
    """The error model's coefficients fitted on the synthetic subjects of ``templates`` (template n: seed
    :data:`ERROR_MODEL_SEED` + n); None without templates (the calibration's term then reads the residual)."""
    if not templates:
        return None
    features, squared = [], []
    for n, template in enumerate(tqdm(templates, desc="error model", unit="template", disable=None)):
        case = error_case(model, template, index.images[template], ERROR_MODEL_SEED + n, refinement)
        features.append(case[0])
        squared.append(case[1])
    return fit_error_model(features, squared, SQUARED_ERROR_FLOOR)
