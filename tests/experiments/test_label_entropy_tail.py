"""experiments/label_entropy_tail.py: the tied voxels ranked below every non-zero entropy by their key, the std
carried by the inverse mean, bad keys refused, the two forms of the samples, a run on the tiny dataset."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import load_script, run_validation_study

study = load_script("experiments", "label_entropy_tail")


def test_tied_voxels_rank_below_every_non_zero_entropy_and_by_their_key():
    entropy = torch.tensor([0.0, 0.3, 0.0, 1e-3, 0.0])
    key = torch.tensor([5.0, 0.0, 0.5, 9.0, 0.0])
    scored = study.tie_broken(entropy, key)
    assert torch.equal(scored[[1, 3]], entropy[[1, 3]])  # non-zero entropies kept as they were
    order = scored.argsort(descending=True).tolist()
    assert order == [1, 3, 4, 2, 0]  # the entropies first, then the tied voxels by growing key


def test_an_entropy_below_the_tolerance_counts_as_tied():
    entropy = torch.tensor([study.ZERO_ENTROPY / 2, study.ZERO_ENTROPY])
    scored = study.tie_broken(entropy, torch.tensor([1.0, 1.0]))
    assert float(scored[0]) == pytest.approx(-0.5) and float(scored[1]) == pytest.approx(study.ZERO_ENTROPY)


def test_a_key_of_another_shape_is_refused():
    with pytest.raises(ValueError, match=r"expected a key of the entropy's shape \(3,\)"):
        study.tie_broken(torch.zeros(3), torch.zeros(4))


def test_a_negative_key_is_refused():
    with pytest.raises(ValueError, match="expected a key >= 0"):
        study.tie_broken(torch.zeros(2), torch.tensor([1.0, -1.0]))


def test_the_tail_std_is_carried_by_the_inverse_mean():
    from monai_probreg import ProbRegNet

    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    size = (8, 8, 8)
    log_var = torch.zeros(1, 3, 4, 4, 4)
    log_var[:, :, :2] = math.log(4.0)  # std 2 in the lower half of axis 0, 1 in the upper (velocity grid units)
    still = study.tail_std(network, torch.zeros(1, 3, 4, 4, 4), log_var, size)
    expected = study.displacement_variance(log_var, size).mean(1).sqrt()[0]
    torch.testing.assert_close(still, expected)  # zero mean: read where it is
    shift = torch.zeros(1, 3, 4, 4, 4)
    shift[:, 0] = 9 / 7  # a constant velocity: exp(-v) a translation, (8 - 1) / (4 - 1) image voxels per unit
    with torch.inference_mode():
        inverse = network.velocity_to_displacement(-shift, size)
    torch.testing.assert_close(inverse[0, 0], torch.full(size, -3.0))  # voxel x reads the fixed grid at x - 3
    moved = study.tail_std(network, shift, log_var, size)
    torch.testing.assert_close(moved[3:], expected[:5], rtol=1e-4, atol=1e-5)


def test_main_writes_the_table(tmp_path, tiny_dataset, single_thread):
    report = run_validation_study(study, tmp_path, tiny_dataset, "label_entropy_tail", "--subjects", "T01")
    assert report["subjects"] == ["T01"] and list(report["summary"]) == list(study.SAMPLES)
    for form, summary in report["summary"].items():
        assert {"wrong_fraction", "boundary_distance", "zero_fraction", "wrong_among_zero"} <= set(summary)
        assert any(n.startswith("ties broken by the posterior's tail") for n in summary)
        for name, value in summary.items():
            assert math.isnan(value) or 0 <= value <= 1, (form, name)
    assert "label entropy, K = 16" in report["markdown"] and "Gaussian samples" in report["markdown"]


def test_the_study_skips_without_a_dataset(tmp_path, capsys):
    assert study.main(["--dataset-dir", str(tmp_path / "none"), "--out-dir", str(tmp_path)]) == 0
    assert "skipped" in capsys.readouterr().out


def test_the_older_samples_differ_from_the_shipped_only_in_their_dof():
    from monai_probreg.uncertainty.calibration import Calibration

    shipped = Calibration(0.04, 0.0, 3.0, 10.0, None, 2.9)
    student, gaussian = (drawn(shipped) for drawn in study.SAMPLES.values())
    assert student == shipped and gaussian == shipped._replace(interval_dof=None)
