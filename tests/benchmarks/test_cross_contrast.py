"""benchmarks/cross_contrast.py: the summary of its cases by hand, its table, and a clean skip without the label
maps (the real run is the benchmark itself)."""

from __future__ import annotations

import pytest
from bench_helpers import load_benchmark

cross_contrast = load_benchmark("cross_contrast")


def _case(kind: str, contrast: str, rows: dict) -> dict:
    return {"pair": "a->b", "seed": 0, "kind": kind, "contrast": contrast, "rows": rows}


def test_the_summary_averages_dice_and_counts_folds_and_warnings_per_group():
    cases = [
        _case("brain", "T2->T1", {"m": {"dice": 0.6, "num_folding": 2, "warning": ""}}),
        _case("brain", "T2->T1", {"m": {"dice": 0.8, "num_folding": 1, "warning": "less alike"}}),
        _case("head", "T2->T1", {"m": {"dice": 0.5, "num_folding": 0, "warning": ""}}),
    ]
    summary = cross_contrast.summarise(cases)
    assert summary["brain T2->T1"]["m"] == {"dice": pytest.approx(0.7), "num_folding": 3, "warned": 1, "pairs": 2}
    assert summary["head T2->T1"]["m"]["pairs"] == 1
    table = cross_contrast.markdown({"summary": summary})
    assert "| brain T2->T1 | m | 0.7000 | 3 | 1 of 2 |" in table


def test_without_the_label_maps_it_skips(tmp_path, capsys):
    assert cross_contrast.main(["--label-maps", str(tmp_path / "none"), "--out-dir", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().out.startswith("skipped:")
    assert not (tmp_path / "out").exists()


def test_a_method_without_a_quality_estimate_has_no_warned_count():
    cases = [_case("head", "T2->T1", {"ANTs SyN": {"dice": 0.6, "num_folding": 0, "seconds": 3.0}})]
    summary = cross_contrast.summarise(cases)
    assert summary["head T2->T1"]["ANTs SyN"]["warned"] is None
    assert "| head T2->T1 | ANTs SyN | 0.6000 | 0 | – |" in cross_contrast.markdown({"summary": summary})


def test_a_rows_contrast_and_map_reach_the_options_and_the_rest_the_refinement():
    """The --contrast other rows run as the command does: contrast "other" (no quality estimate) and the map's bins
    on RegistrationOptions, the other fields on the refinement; a row without them keeps "same" and no map."""
    from types import SimpleNamespace

    from monai_probreg.engines.refinement import RefinementSettings

    model = SimpleNamespace(refinement=RefinementSettings(num_iterations=3))
    fields = {"posterior_weight": 0.0, "contrast": "other", "contrast_match_bins": 16}
    options = cross_contrast._options(model, fields, seed=1)
    assert (options.contrast, options.contrast_match_bins, options.seed) == ("other", 16, 1)
    assert options.refinement.posterior_weight == 0.0 and options.refinement.num_iterations == 3
    assert fields == {"posterior_weight": 0.0, "contrast": "other", "contrast_match_bins": 16}  # not consumed
    plain = cross_contrast._options(model, {}, seed=0)
    assert (plain.contrast, plain.contrast_match_bins) == ("same", 0)
    assert plain.affine.local_stage == "other-contrast"  # the settings' default: the step runs with "other"


def test_a_rows_affine_local_reaches_the_affine_settings():
    from types import SimpleNamespace

    from monai_probreg.engines.refinement import RefinementSettings

    model = SimpleNamespace(refinement=RefinementSettings(num_iterations=3))
    options = cross_contrast._options(model, {"contrast": "other", "affine_local": "never"}, seed=0)
    assert options.affine.local_stage == "never" and options.contrast == "other"


@pytest.mark.parametrize(
    "variant, message",
    [
        ("bad=affine_local:sometimes", "local_stage must be one of"),
        ("bad=contrast:T2", "contrast must be one of"),
        ("bad=no_such_field:1", "no_such_field"),
    ],
)
def test_a_bad_variant_stops_before_any_registration(tmp_path, variant, message):
    maps = tmp_path / "maps"
    maps.mkdir()
    for name in cross_contrast.MAPS:
        (maps / f"{name}.nii.gz").write_bytes(b"")  # present: the check comes before anything reads them
    with pytest.raises(SystemExit, match=message):
        cross_contrast.main(["--label-maps", str(maps), "--refined-variants", variant, "--out-dir", str(tmp_path)])
