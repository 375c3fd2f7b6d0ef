"""bundle/configs/inference.yaml end to end on the tiny synthetic dataset, with random weights.

A temporary copy of the bundle (configs/ + a random-weights models/model.pt) is registered against; the tests pin
the wiring and the geometry of what is written (files, shapes, affines, label ids), not registration quality.
"""

from __future__ import annotations

import math

import nibabel as nib
import numpy as np
import pytest
from bundle_fixtures import infer_workflow
from conftest import BUNDLE_DIR, TINY_LABELS, make_tiny_dataset

from monai_probreg.engines.outputs import OUTPUT_NAMES
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.fitting.stages import bundle_parser

pytestmark = pytest.mark.usefixtures("single_thread")


def test_inference_writes_every_subject_on_the_atlas_grid(tmp_path, tiny_dataset, bundle):
    # the network alone (refine_iterations 0): random weights then give the identity, which the Jacobian check pins;
    # the default path's refinement is covered by test_evaluate_workflow's refinement test
    wf = infer_workflow("inference.yaml", bundle, tiny_dataset, tmp_path / "out", refine_iterations=0)
    assert wf.check_properties() == []  # InferProperties (+ MetaProperties when metadata.json exists), optional IDs
    wf.run()
    wf.finalize()

    out = tmp_path / "out"
    ids = sorted(p.name[: -len(".nii.gz")] for p in (tiny_dataset / "images").iterdir())
    assert sorted(p.name for p in out.iterdir()) == sorted([*ids, "README.txt"])
    assert "in VOXELS" in (out / "README.txt").read_text()
    assert not [p for p in out.rglob(".*")], "no temporary file may be left behind"
    atlas = nib.load(tiny_dataset / "atlas" / "A01_image.nii.gz")
    ras_affine = nib.as_closest_canonical(atlas).affine  # 32^3 is a multiple of 16: no padding
    for sid in ids:
        images = {name: nib.load(out / sid / f"{name}.nii.gz") for name in OUTPUT_NAMES}
        for name, image in images.items():
            assert image.shape == (atlas.shape if name != "displacement" else (*atlas.shape, 1, 3)), (sid, name)
            np.testing.assert_allclose(image.affine, ras_affine, atol=1e-6, err_msg=f"{sid} {name}")  # float32 header
        assert images["displacement"].header.get_intent()[0] == "vector"
        labels = np.asarray(images["warped_label"].dataobj)
        assert set(np.unique(labels)) <= {0, *TINY_LABELS} and set(np.unique(labels)) & set(TINY_LABELS)
        # random initial weights: |u| < 1e-4 voxels, |J - 1| ~ 1e-5 measured; 1e-3 leaves a 100x margin
        np.testing.assert_allclose(images["jacobian"].get_fdata(), 1.0, atol=1e-3)
        assert np.isfinite(images["entropy"].get_fdata()).all()
        std = images["displacement_std"].get_fdata()
        assert np.isfinite(std).all() and std.min() >= 0 and std.max() > 0  # sampled: a spread, however small
        label_entropy = images["label_entropy"].get_fdata()  # at most log of the labels present (and 0)
        assert label_entropy.min() >= 0 and label_entropy.max() <= math.log(len(TINY_LABELS) + 1) + 1e-5
        warped = images["warped"].get_fdata()
        assert 0.0 <= warped.min() and warped.max() <= 1.0  # percentile-scaled intensities


def test_inference_without_labels_writes_no_label_maps(tmp_path, bundle):
    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=1, with_labels=False)
    wf = infer_workflow("inference.yaml", bundle, dataset, tmp_path / "out")
    wf.run()
    assert sorted(p.name for p in (tmp_path / "out" / "T01").iterdir()) == sorted(
        f"{name}.nii.gz" for name in OUTPUT_NAMES if name not in ("warped_label", "label_entropy")
    )


def test_inference_takes_a_pairs_file_without_labels(tmp_path, tiny_dataset, bundle):
    pairs = tmp_path / "pairs.json"
    import json

    pairs.write_text(
        json.dumps([{"moving": f"{tiny_dataset}/images/T01.nii.gz", "fixed": f"{tiny_dataset}/images/T02.nii.gz"}])
    )
    wf = infer_workflow("inference.yaml", bundle, tmp_path / "no_such_dataset", tmp_path / "out", pairs_file=str(pairs))
    wf.run()
    wf.finalize()
    written = sorted(p.name for p in (tmp_path / "out" / "T01_to_T02").iterdir())
    assert "warped.nii.gz" in written and "displacement.nii.gz" in written and "warped_label.nii.gz" not in written


@pytest.mark.parametrize("config", ["inference.yaml", "evaluate.yaml"])
def test_refinement_is_on_by_default_and_settable_from_the_config(config):
    """Both workflows hand the config's ``refinement`` to their inferer: on by default (the default path), the
    library's other defaults otherwise; refine_iterations 0 turns it off."""
    parser = bundle_parser(BUNDLE_DIR, [config])
    default = parser.get_parsed_content("inferer").refinement
    # the shipped default path: 20 steps of 0.3 with a quarter of the pull, the first 18 on the network's grid and the
    # last 2 with the loss images twice finer, the similarity guard on, the library's other defaults
    expected = RefinementSettings(
        num_iterations=20,
        learning_rate=0.3,
        posterior_weight=0.25,
        image_grid_factor=2,
        coarse_iterations=18,
        similarity_guard=True,
    )
    assert default.enabled and default == expected and parser["refine_image_grid_factor"] == 2
    parser = bundle_parser(BUNDLE_DIR, [config])
    parser["refine_iterations"] = 0
    assert not parser.get_parsed_content("inferer").refinement.enabled
    parser = bundle_parser(BUNDLE_DIR, [config])
    parser["refine_iterations"] = 1  # fewer steps than the finer ones: every step finer
    assert parser.get_parsed_content("inferer").refinement.coarse_iterations == 0
    parser = bundle_parser(BUNDLE_DIR, [config])
    parser["refine_iterations"], parser["refine_prior_lambda"] = 20, 3.0
    parser["refine_image_loss"], parser["refine_image_weight"], parser["refine_fold_backtracks"] = "gaussian", 1.0, 0
    refinement = parser.get_parsed_content("inferer").refinement
    assert refinement.enabled and refinement.num_iterations == 20 and refinement.prior_lambda == 3.0
    assert refinement.coarse_iterations == 20 - parser["refine_fine_iterations"]  # the finer steps stay last
    assert (refinement.image_loss, refinement.image_weight, refinement.fold_backtracks) == ("gaussian", 1.0, 0)
    parser["refine_fold_local_steps"], parser["refine_image_grid_factor"] = 2, 1
    refinement = parser.get_parsed_content("inferer", lazy=False).refinement
    assert (refinement.fold_local_steps, refinement.image_grid_factor) == (2, 1)


def test_inference_twice_writes_the_same_files(tmp_path, tiny_dataset, bundle):
    """Issue "Same input, same output": the posterior samples are seeded (sample_seed), nothing else is random."""
    for name in ("first", "second"):
        wf = infer_workflow("inference.yaml", bundle, tiny_dataset, tmp_path / name)
        wf.run()
        wf.finalize()
    first = sorted(p.relative_to(tmp_path / "first") for p in (tmp_path / "first").rglob("*") if p.is_file())
    assert first and first == sorted(
        p.relative_to(tmp_path / "second") for p in (tmp_path / "second").rglob("*") if p.is_file()
    )
    for path in first:
        assert (tmp_path / "first" / path).read_bytes() == (tmp_path / "second" / path).read_bytes(), path


def test_the_writer_draws_the_label_entropy_as_the_shipped_sidecar_says():
    """inference.yaml hands the writer the sidecar's sample_gain and interval_dof: the label entropy's samples are
    drawn from the calibrated Student-t posterior the intervals describe."""
    from monai_probreg.uncertainty.calibration import calibration_for

    parser = bundle_parser(BUNDLE_DIR, ["inference.yaml"])
    shipped = calibration_for(BUNDLE_DIR / "models" / "model.pt")
    assert shipped.interval_dof is not None  # the shipped intervals are Student-t
    assert parser.get_parsed_content("interval_dof") == shipped.interval_dof
    assert parser.get_parsed_content("sample_gain") == shipped.sample_gain
    writer = next(h for h in parser["handlers"] if h["_target_"].endswith("RegistrationWriter"))
    assert (writer["interval_dof"], writer["sample_gain"]) == ("@interval_dof", "@sample_gain")


@pytest.mark.parametrize("dof", [0.0, -2.0, float("nan")])
def test_the_writer_refuses_a_bad_interval_dof(tmp_path, dof):
    from monai_probreg.engines.handlers import RegistrationWriter

    with pytest.raises(ValueError, match="interval_dof"):
        RegistrationWriter(tmp_path, names=("warped",), interval_dof=dof)
