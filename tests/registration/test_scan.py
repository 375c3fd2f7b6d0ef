"""monai_probreg.registration.scan: its options (samples, the refinement a library call gets by default)."""

from __future__ import annotations

import pytest
from conftest import BUNDLE_DIR, FAST_AFFINE_SETTINGS, FIXED_LPS, moved_phantom, save_lps, tiny_bundle

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.scan import register_scan
from monai_probreg.utils.errors import InputError


@pytest.mark.parametrize("samples", [-1, 1])
def test_samples_must_allow_a_standard_deviation(samples):
    with pytest.raises(InputError, match="--samples"):
        RegistrationOptions(samples=samples)


def test_the_library_default_is_the_models_refinement_as_on_the_command_line(tmp_path):
    """RegistrationOptions(refinement=None), the default: register_scan refines as the model's config says (what
    ``monai-probreg register`` runs); explicit settings, e.g. RefinementSettings() (no steps), are used as given."""
    case = moved_phantom([6.0, -4.0, 5.0], [2.0, -1.0, 1.5])
    bundle = tiny_bundle(tmp_path / "bundle", BUNDLE_DIR)
    model = load_model(bundle)
    assert model.refinement.enabled  # inference.yaml refines by default
    fixed = prepare_fixed(save_lps(tmp_path / "fixed.nii.gz", case.image, FIXED_LPS))
    moving = save_lps(tmp_path / "moving.nii.gz", case.moved, case.grid)
    fast = {"qc": False, "inverse": False, "maps": False, "affine": FAST_AFFINE_SETTINGS}
    default = register_scan(model, fixed, moving, tmp_path / "default", options=RegistrationOptions(**fast))
    assert default["model"]["refinement"] == model.refinement.as_dict() and "refine" in default["timings_s"]
    plain = RegistrationOptions(**fast, refinement=RefinementSettings())
    network = register_scan(model, fixed, moving, tmp_path / "network", options=plain)
    assert network["model"]["refinement"]["num_iterations"] == 0 and "refine" not in network["timings_s"]
