"""monai_probreg.registration.scan: its options (samples, the refinement a library call gets by default)."""

from __future__ import annotations

import numpy as np
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


@pytest.mark.parametrize("bins", [-1, 1, 2.5])
def test_contrast_match_bins_must_be_none_or_at_least_two(bins):
    with pytest.raises(ValueError, match=rf"contrast_match_bins must be 0 \(none\) or an integer >= 2; got {bins}"):
        RegistrationOptions(contrast_match_bins=bins)


@pytest.mark.parametrize("contrast", ["T2", "", None, "Other"])
def test_contrast_must_be_same_or_other(contrast):
    with pytest.raises(ValueError, match=rf"contrast must be one of \('same', 'other'\); got {contrast!r}"):
        RegistrationOptions(contrast=contrast)


@pytest.mark.parametrize("bins", [0, 16])
def test_the_network_reads_the_moving_scan_in_the_fixed_contrast_when_asked(tmp_path, monkeypatch, bins):
    """contrast_match_bins N: what the network (and after it the refinement and the quality estimate) reads is the
    resampled moving scan mapped onto the fixed image's contrast (match_contrast of the two model inputs); 0: the
    resampled scan itself."""
    from monai_probreg.registration import scan
    from monai_probreg.registration.affine_stage import model_input
    from monai_probreg.spatial.contrast import match_contrast

    case = moved_phantom([6.0, -4.0, 5.0], [2.0, -1.0, 1.5])
    model = load_model(tiny_bundle(tmp_path / "bundle", BUNDLE_DIR))
    fixed = prepare_fixed(save_lps(tmp_path / "fixed.nii.gz", case.image, FIXED_LPS))
    inverted = np.where(case.moved > 0.05, 1.0 - case.moved, 0.0).astype(np.float32)  # another contrast
    moving = save_lps(tmp_path / "moving.nii.gz", inverted, case.grid)
    read, resampled = {}, {}

    def network(model, moving_input, fixed_input, stage):
        read["input"] = moving_input
        raise RuntimeError("stop after the network's input")

    def keep(fixed, moving, affine):
        resampled["input"] = model_input(fixed, moving, affine)
        return resampled["input"]

    monkeypatch.setattr(scan, "register_network", network)
    monkeypatch.setattr(scan, "model_input", keep)
    options = RegistrationOptions(affine=FAST_AFFINE_SETTINGS, contrast_match_bins=bins)
    with pytest.raises(RuntimeError, match="stop after"):
        register_scan(model, fixed, moving, tmp_path / "out", options=options)
    image = resampled["input"].image
    expected = image if bins == 0 else match_contrast(image, fixed.model_input, bins)
    np.testing.assert_array_equal(read["input"], expected)
    if bins:  # inside the object, the inverted contrast is made the fixed image's again
        inside = (image > 0) & (fixed.model_input > 0.05)
        assert np.corrcoef(image[inside], fixed.model_input[inside])[0, 1] < 0
        assert np.corrcoef(read["input"][inside], fixed.model_input[inside])[0, 1] > 0.5


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
    assert default["model"]["contrast_match_bins"] == 0  # the moving scan as it is (--contrast same)
    plain = RegistrationOptions(**fast, refinement=RefinementSettings())
    network = register_scan(model, fixed, moving, tmp_path / "network", options=plain)
    assert network["model"]["refinement"]["num_iterations"] == 0 and "refine" not in network["timings_s"]


def test_the_freed_memory_goes_back_between_the_stages_that_allocate_otherwise(tmp_path, monkeypatch):
    """register_scan gives the freed memory back after the model, the refinement, the maps (both parts), the quality
    estimate (both parts, with a quality model) and the compose stage, and the compose stage between its parts;
    every file is still written."""
    from monai_probreg.registration import compose, scan

    events = []
    monkeypatch.setattr(scan, "trim_freed_memory", lambda: events.append("trim"))
    monkeypatch.setattr(compose, "trim_freed_memory", lambda: events.append("trim inside compose"))
    case = moved_phantom([6.0, -4.0, 5.0], [2.0, -1.0, 1.5])
    model = load_model(tiny_bundle(tmp_path / "bundle", BUNDLE_DIR))
    fixed = prepare_fixed(save_lps(tmp_path / "fixed.nii.gz", case.image, FIXED_LPS))
    moving = save_lps(tmp_path / "moving.nii.gz", case.moved, case.grid)
    options = RegistrationOptions(affine=FAST_AFFINE_SETTINGS)
    summary = register_scan(
        model, fixed, moving, tmp_path / "out", options=options, report=lambda s, _: events.append(s)
    )
    stages = [e for e in events if not e.startswith("trim")]
    assert [events[events.index(s) - 1] for s in ("model", "refine", "compose")] == ["trim"] * 3
    maps = [n for n, e in enumerate(events) if e == "maps"]
    assert len(maps) == 2 and all(events[n - 1] == "trim" for n in maps)  # before the quality estimate, and after
    quality = [n for n, e in enumerate(events) if e == "quality"]  # two parts with a quality model, else none
    assert all(events[n - 1] == "trim" for n in quality)
    assert events.count("trim") == 5 + len(quality) and events.count("trim inside compose") == 3
    assert stages.index("refine") == stages.index("model") + 1
    assert "warp.nii.gz" in summary["outputs"] and "inverse_warp.nii.gz" in summary["outputs"]
