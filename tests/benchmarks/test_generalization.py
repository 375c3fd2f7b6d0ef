"""benchmarks/generalization.py: its scores computed by hand on tiny cases, the synthetic heads' geometry, the ANTs
records kept across runs, and the script end to end on two tiny label maps (network and default rows, no ANTs)."""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from bench_helpers import load_benchmark
from conftest import FIXED_LPS, asymmetric_phantom, save_lps

from monai_probreg.spatial.volume_io import read_label

generalization = load_benchmark("generalization")


def test_dice_is_the_mean_over_the_labels_both_maps_have():
    fixed = np.array([1, 1, 2, 2, 0, 3])
    warped = np.array([1, 2, 2, 2, 0, 0])
    # label 1: 2*1/(1+2) = 2/3; label 2: 2*2/(3+2) = 4/5; label 3 only in the fixed map: left out; 7 in neither
    assert generalization.dice(warped, fixed, [1, 2, 3, 7]) == pytest.approx((2 / 3 + 4 / 5) / 2)
    assert np.isnan(generalization.dice(warped, fixed, [7]))


def test_brain_ncc_is_the_correlation_inside_the_templates_brain():
    rng = np.random.default_rng(0)
    template = np.zeros((6, 7, 8))
    template[1:5, 2:6, 2:7] = rng.uniform(1, 2, size=(4, 4, 5))
    assert generalization.brain_ncc(template * 3 + 1, template) == pytest.approx(1.0)
    assert generalization.brain_ncc(-template, template) == pytest.approx(-1.0)
    noisy = template + 100 * (template == 0) * rng.standard_normal(template.shape)  # outside the brain: ignored
    assert generalization.brain_ncc(noisy, template) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def label_maps(tmp_path_factory):
    """Two FreeSurfer-labelled phantoms named like SynthSeg's held-out maps, inside a larger empty field of view."""
    folder = tmp_path_factory.mktemp("label_maps")
    for n, name in enumerate(generalization.SYNTH_MAPS):
        _, labels = asymmetric_phantom((40, 44, 36), seed=n)
        fs = np.zeros((56, 60, 52), np.int16)
        fs[8:48, 8:52, 8:44] = np.select([labels == 1, labels == 2, labels == 3, labels == 4], [2, 41, 12, 507], 0)
        save_lps(folder / f"{name}.nii.gz", fs, FIXED_LPS)
    return folder


def test_a_synthetic_head_is_cropped_in_place_deformed_and_rendered(label_maps, tmp_path):
    source = label_maps / f"{generalization.SYNTH_MAPS[0]}.nii.gz"
    image_path, label_path = generalization.synthetic_head(source, 0, tmp_path)
    original, head = read_label(source), read_label(label_path)
    nonzero = np.argwhere(original.array > 0)
    lo = np.maximum(nonzero.min(0) - generalization.SYNTH_CROP_MARGIN, 0)
    hi = np.minimum(nonzero.max(0) + generalization.SYNTH_CROP_MARGIN + 1, original.shape)
    assert head.shape == tuple(hi - lo)  # the head's box plus the margin, inside the field of view
    # the crop's voxel 0 is where the original's voxel lo was: cropping moves no anatomy in space
    np.testing.assert_allclose(
        head.index_to_lps[:3, 3], original.index_to_lps[:3, :3] @ lo + original.index_to_lps[:3, 3]
    )
    assert set(np.unique(head.array)) <= set(np.unique(original.array))
    crop = original.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    moved = (head.array != crop)[crop > 0].mean()
    assert 0.0 < moved < 0.2, f"a smooth deformation of a few mm changes some labels, not most: {moved:.3f}"
    image = nib.load(image_path)
    assert image.shape == head.shape and np.allclose(image.affine, nib.load(label_path).affine)
    (tmp_path / "again").mkdir()
    again, _ = generalization.synthetic_head(source, 0, tmp_path / "again")
    assert np.array_equal(nib.load(again).get_fdata(), image.get_fdata())  # seeded: the same head twice


def test_ants_records_are_computed_once_and_kept_in_the_file(tmp_path):
    path = tmp_path / "ants.json"
    calls = []
    cache = generalization.AntsCache(path)
    first = cache.get("case:abc", lambda: calls.append(1) or {"dice": 0.5})
    again = generalization.AntsCache(path).get("case:abc", lambda: calls.append(1) or {"dice": 0.0})
    assert calls == [1] and first["dice"] == again["dice"] == 0.5
    assert again["cached"] is True and "cached" not in first
    assert "computed_at" in json.loads(path.read_text())["case:abc"]


def test_the_script_scores_the_synthetic_pairs_and_skips_what_is_missing(label_maps, tmp_path, capsys):
    out = tmp_path / "out"
    code = generalization.main(
        [
            "--parts",
            "synthetic",
            "native",
            "--no-ants",
            "--label-maps",
            str(label_maps),
            "--native-dir",
            str(tmp_path / "none"),
            "--threads",
            "1",
            "--out-dir",
            str(out),
            "--refine-iterations",
            "2",
            "--refined-variants",
            "fine=image_grid_factor:2",
        ]
    )
    assert code == 0
    result = json.loads((out / "generalization.json").read_text())
    assert "skipped" in result["parts"]["native"]
    rows = result["parts"]["synthetic"]
    assert set(rows) == {"network (shipped)", "refined (shipped)", "fine (shipped)"}
    assert result["refined_variants"] == {"fine": {"image_grid_factor": 2}}
    pairs = {
        f"{a}_{s}_to_{b}_{s}"
        for s in generalization.SYNTH_SEEDS
        for a, b in (generalization.SYNTH_MAPS, generalization.SYNTH_MAPS[::-1])
    }
    for row in rows.values():
        assert set(row["per_pair"]) == pairs and 0.0 < row["dice"] <= 1.0
        assert row["dice"] == pytest.approx(np.mean(list(row["per_pair"].values())))
    assert (out / "generalization.png").is_file() and "| refined (shipped) |" in result["markdown"]


def test_jobs_run_the_parts_side_by_side_into_one_table(label_maps, tmp_path):
    """--jobs 2: one process per group of parts (this script again), merged: the same rows as one process gives."""
    args = ["--no-ants", "--label-maps", str(label_maps), "--native-dir", str(tmp_path / "none"), "--threads", "1"]
    args += ["--refine-iterations", "2", "--parts", "synthetic", "native"]
    assert generalization.main([*args, "--out-dir", str(tmp_path / "one")]) == 0
    assert generalization.main([*args, "--jobs", "2", "--out-dir", str(tmp_path / "two")]) == 0
    one, two = (json.loads((tmp_path / d / "generalization.json").read_text()) for d in ("one", "two"))
    assert list(two["parts"]) == ["native", "synthetic"]  # PARTS' order
    assert two["parts"] == one["parts"]
    assert set(two["jobs"]) == {"native", "synthetic"} and two["seconds"] == max(two["jobs"].values())
    assert two["markdown"] == one["markdown"] and (tmp_path / "two" / "generalization.png").is_file()


def test_a_failed_job_is_named_after_every_job_ended(tmp_path):
    """--jobs: the processes whose parts failed (an unknown variant field) are named once all of them have ended."""
    argv = ["--no-ants", "--refined-variants", "odd=grid_size:3"]
    with pytest.raises(SystemExit, match=r"parts lpba40 \(exit 1\); demo native \(exit 1\) failed"):
        generalization.run_jobs(argv, [["lpba40"], ["demo", "native"]])


def test_part_groups_balance_the_parts_cost():
    groups = generalization.part_groups(list(generalization.PARTS), 2)
    assert groups == [["lpba40"], ["demo", "native", "synthetic"]]
    assert generalization.part_groups(["demo", "native"], 4) == [["demo"], ["native"]]  # no empty group
    assert generalization.part_groups(["native", "demo"], 1) == [["demo", "native"]]


def test_the_ants_cache_keeps_what_another_process_wrote(tmp_path):
    path = tmp_path / "ants.json"
    first, second = generalization.AntsCache(path), generalization.AntsCache(path)
    first.get("a", lambda: {"ncc": 0.1})
    second.get("b", lambda: {"ncc": 0.2})  # read before "a" was written
    assert set(json.loads(path.read_text())) == {"a", "b"}


def test_missing_label_maps_skip_the_part(tmp_path):
    rows = generalization.part_synthetic({}, {}, tmp_path, None)
    assert "skipped" in rows and "training_seg_11" in rows["skipped"]


def test_a_refined_variant_may_not_take_a_rows_name(tmp_path):
    with pytest.raises(SystemExit, match="'refined' is taken"):
        generalization.main(["--parts", "synthetic", "--no-ants", "--refined-variants", "refined=num_iterations:3"])


def test_the_lpba40_part_runs_each_variant_as_refine_overrides(tmp_path, monkeypatch):
    """part_lpba40 hands accuracy_table.py the default rows once and each variant as a refined row whose fields are
    evaluate.yaml overrides (refine_<field>=<value>); the rows are named after the variant."""
    calls = []
    row = {"aggregate": {t: {"mean_dice": {"mean": 0.5, "std": 0.02}} for t in ("atlas", "pairs")}}
    row["aggregate_all"] = {"num_folding": {"mean": 0.0}, "runtime_s": {"mean": 4.5}}

    def fake_main(argv):
        calls.append(argv)
        out = Path(argv[argv.index("--out-dir") + 1])
        methods = argv[argv.index("--methods") + 1 :]
        methods = methods[: next((i for i, a in enumerate(methods) if a.startswith("--")), len(methods))]
        (out / "accuracy_table.json").write_text(json.dumps({"methods": {m: row for m in methods}}))
        return 0

    monkeypatch.setattr(generalization.accuracy_table, "main", fake_main)
    variants = {"fine": {"image_grid_factor": 2, "num_iterations": 5}}
    rows = generalization.part_lpba40([None], 10, tmp_path, 1, None, variants)
    assert set(rows) == {"network (shipped)", "refined (shipped)", "fine (shipped)"}
    assert rows["fine (shipped)"] == {
        "to_atlas": 0.5,
        "pairs": 0.5,
        "num_folding_per_pair": 0.0,
        "to_atlas_std": 0.02,
        "pairs_std": 0.02,
        "seconds_per_pair": 4.5,
    }
    default, fine = calls
    assert not any(a.startswith("--override") for a in default)
    assert fine[fine.index("--methods") + 1] == "refined"
    assert {a for a in fine if a.startswith("--override")} == {
        "--override=refine_image_grid_factor=2",
        "--override=refine_num_iterations=5",
    }


def test_a_refined_variant_with_an_unknown_field_is_named(tmp_path):
    with pytest.raises(SystemExit, match="'odd'.*grid_size"):
        generalization.main(["--parts", "synthetic", "--no-ants", "--refined-variants", "odd=grid_size:3"])


def test_a_skull_stripped_t2_like_brain_drops_the_head_and_turns_the_contrast(label_maps, tmp_path):
    """brain_only: no label from 500 on is left and the crop is the brain's; the T2-like table renders white matter
    (2, 41) darker than the putamen (12), the T1-like one brighter."""
    from monai_probreg.data.label_synthesis import T1_LIKE, T2_LIKE

    source = label_maps / f"{generalization.SYNTH_MAPS[0]}.nii.gz"
    brightness = {}
    for name, table in (("t1", T1_LIKE), ("t2", T2_LIKE)):
        (tmp_path / name).mkdir()
        image_path, label_path = generalization.synthetic_head(source, 0, tmp_path / name, table, brain_only=True)
        labels, image = read_label(label_path).array, nib.load(image_path).get_fdata()
        assert labels.max() < generalization.EXTRA_CEREBRAL_FROM and set(np.unique(labels)) == {0, 2, 12, 41}
        assert image.shape == labels.shape
        brightness[name] = {v: image[labels == v].mean() for v in (2, 12)}
    assert brightness["t1"][2] > brightness["t1"][12] and brightness["t2"][2] < brightness["t2"][12]
