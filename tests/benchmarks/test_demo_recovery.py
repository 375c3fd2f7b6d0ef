"""benchmarks/demo_recovery.py's ANTs SyN row on a small template (only where antspyx is importable, the ``.[bench]``
extra): ANTs' composed field is read in warp.nii.gz's convention, so a subject that is the template shifted by a
known amount is recovered to a fraction of a voxel, and one left as it is scores no displacement. A sign error or an
axis swap in the reading would leave about twice the shift."""

from __future__ import annotations

import numpy as np
import pytest
from bench_helpers import load_benchmark
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.data.synthetic import SyntheticSettings
from monai_probreg.registration.inputs import prepare_fixed

demo_recovery = load_benchmark("demo_recovery")


@pytest.fixture(scope="module")
def fixed(tmp_path_factory):
    pytest.importorskip("ants", reason="antspyx (the .[bench] extra) is not installed")
    image, labels = asymmetric_phantom((48, 52, 44))
    template = np.where(labels > 0, np.clip(image, 0.05, None) * 200, 0).astype(np.float32)
    path = save_lps(
        tmp_path_factory.mktemp("template") / "template.nii.gz", template, FIXED_LPS @ np.diag([1.5, 1.5, 1.5, 1.0])
    )
    return prepare_fixed(path)


def test_ants_recovers_a_known_shift_in_our_convention(fixed, monkeypatch):
    monkeypatch.setenv("ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS", "1")
    shift_only = SyntheticSettings(
        max_rotation_deg=0, max_shift_mm=4.0, deform_rms_mm=0, bias_coeff=0, noise_fraction=0, axcodes="PIR"
    )
    case = demo_recovery.ants_case(fixed, 3, shift_only)
    assert case["before"]["median_mm"] > 2.0  # a shift of a few mm to undo
    assert case["after"]["median_mm"] < 0.35 * case["before"]["median_mm"], case
    assert case["coverage"] is None and case["affine_only"] is None and case["seconds"] > 0


def test_ants_on_the_template_itself_invents_little(fixed, monkeypatch):
    monkeypatch.setenv("ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS", "1")
    case = demo_recovery.ants_case(fixed, 0, demo_recovery.IDENTITY)
    assert case["before"]["median_mm"] == 0.0 and case["after"]["median_mm"] < 0.5
