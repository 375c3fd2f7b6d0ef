"""monai_probreg.registration.affine_stage: when the local-correlation step runs (the one rule), which starts mutual
information runs from, and that a pair of one contrast gets mutual information's answer untouched."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import FAST_AFFINE_SETTINGS, FIXED_LPS, moved_phantom, save_lps

from monai_probreg.registration import affine_stage as stage
from monai_probreg.registration.inputs import prepare_fixed, read_moving
from monai_probreg.registration.options import InitialTransform, RegistrationOptions
from monai_probreg.spatial.affine import align
from monai_probreg.spatial.affine_settings import LOCAL_STAGE

SETTINGS = dataclasses.replace(FAST_AFFINE_SETTINGS, local_levels_mm=(2.0,), local_kernels=(3,), local_iterations=(10,))


@pytest.mark.parametrize("local_stage", LOCAL_STAGE)
@pytest.mark.parametrize("contrast", ["same", "other"])
def test_the_local_step_runs_always_or_for_another_contrast(local_stage, contrast):
    expected = local_stage == "always" or (local_stage == "other-contrast" and contrast == "other")
    settings = dataclasses.replace(SETTINGS, local_stage=local_stage)
    assert stage.local_stage_runs(settings, contrast) is expected


@pytest.fixture
def pair(tmp_path):
    case = moved_phantom([6.0, -4.0, 5.0], [2.0, -1.0, 1.5])
    fixed = prepare_fixed(save_lps(tmp_path / "fixed.nii.gz", case.image, FIXED_LPS))
    inverted = np.where(case.moved > 0.05, 1.0 - case.moved, 0.0).astype(np.float32)  # another contrast
    moving = read_moving(save_lps(tmp_path / "moving.nii.gz", inverted, case.grid))
    return fixed, moving


def _counting_align(monkeypatch) -> list[str]:
    """align as it is, recording each call's initializer."""
    starts: list[str] = []

    def counted(fixed, moving, settings, *args):
        starts.append(settings.initializer)
        return align(fixed, moving, settings, *args)

    monkeypatch.setattr(stage, "align", counted)
    return starts


def test_one_contrast_gets_mutual_informations_answer(pair, monkeypatch):
    fixed, moving = pair
    starts = _counting_align(monkeypatch)
    result = stage.affine_stage(fixed, moving, RegistrationOptions(affine=SETTINGS))
    expected = align(fixed.image, moving.image, SETTINGS, None, fixed.samples_for(SETTINGS))
    np.testing.assert_array_equal(result.matrix, expected.matrix)
    assert starts == ["moments"] and [s.name for s in result.stages] == ["rigid", "affine"]


def test_another_contrast_runs_both_starts_then_the_local_step(pair, monkeypatch):
    fixed, moving = pair
    starts = _counting_align(monkeypatch)
    result = stage.affine_stage(fixed, moving, RegistrationOptions(affine=SETTINGS, contrast="other"))
    assert starts == list(SETTINGS.local_starts)
    assert [s.name for s in result.stages] == ["rigid", "affine", "local correlation"]
    assert "of 2" in result.stages[-1].stop_condition
    # the ITK form is the refined matrix's, not the start's
    np.testing.assert_allclose(result.transform.GetMatrix().__array__(), result.matrix[:3, :3], atol=1e-6)


def test_never_turns_the_local_step_off_for_another_contrast(pair, monkeypatch):
    fixed, moving = pair
    starts = _counting_align(monkeypatch)
    settings = dataclasses.replace(SETTINGS, local_stage="never")
    result = stage.affine_stage(fixed, moving, RegistrationOptions(affine=settings, contrast="other"))
    assert starts == ["moments"] and result.stages[-1].name == "affine"


def test_an_initial_transform_is_the_only_start(pair, monkeypatch):
    fixed, moving = pair
    starts = _counting_align(monkeypatch)
    initial = InitialTransform("earlier.tfm", np.eye(4), np.zeros(3), "start")
    options = RegistrationOptions(affine=SETTINGS, contrast="other", initial=initial)
    result = stage.affine_stage(fixed, moving, options)
    assert starts == ["moments"] and "of 1" in result.stages[-1].stop_condition
