"""experiments/uncertainty_ceiling.py: its oracles and baseline in closed form on tiny tensors, and a run on the tiny
dataset."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import load_script, run_validation_study

bench = load_script("experiments", "uncertainty_ceiling")


def test_oracle_log_var_is_the_squared_error_at_the_reference_level():
    mean = torch.zeros(1, 3, 4, 5, 6)
    truth = torch.randn(1, 3, 4, 5, 6, generator=torch.Generator().manual_seed(0))
    reference = torch.full_like(mean, math.log(0.5))  # variance 0.5 everywhere
    for scale in (0.25, 1.0, 4.0):
        oracle = bench.oracle_log_var(mean, truth, reference, scale)
        assert float(oracle.exp().mean()) == pytest.approx(0.5 * scale, rel=1e-5)
        # proportional to the squared error voxel by voxel (ratios of the variances = ratios of squared errors)
        squared = truth.pow(2) + bench.ORACLE_EPS
        ratio = oracle.exp() / squared
        assert torch.allclose(ratio, ratio.flatten()[0].expand_as(ratio), rtol=1e-4)


@pytest.mark.parametrize("bad", ["shape", "scale"])
def test_oracle_log_var_rejects_bad_input(bad):
    mean = torch.zeros(1, 3, 4, 4, 4)
    if bad == "shape":
        with pytest.raises(ValueError, match="of one shape"):
            bench.oracle_log_var(mean, torch.zeros(1, 3, 4, 4, 5), mean)
    else:
        with pytest.raises(ValueError, match="scale must be > 0"):
            bench.oracle_log_var(mean, mean + 1, mean, 0.0)


def test_directional_samples_lie_on_the_line_through_the_mean_and_the_truth():
    mean = torch.randn(1, 3, 4, 4, 4, generator=torch.Generator().manual_seed(1))
    truth = mean + torch.randn(1, 3, 4, 4, 4, generator=torch.Generator().manual_seed(2))
    samples = bench.directional_samples(mean, truth, 64, torch.Generator().manual_seed(3))
    assert samples.shape == (64, 3, 4, 4, 4)
    t = ((samples - mean) / (truth - mean)).flatten(1)
    assert torch.allclose(t, t[:, :1].expand_as(t), atol=1e-4)  # one t per sample, the same at every voxel
    assert abs(float(t[:, 0].mean())) < 0.4 and 0.6 < float(t[:, 0].std()) < 1.4  # t ~ N(0, 1)
    with pytest.raises(ValueError, match=r"\(1, D, \*V\)"):
        bench.directional_samples(mean.expand(2, -1, -1, -1, -1), truth.expand(2, -1, -1, -1, -1), 4, torch.Generator())


def test_boundary_distance_is_zero_on_both_sides_of_a_boundary_and_grows_away_from_it():
    labels = torch.zeros(12, 1, 1, dtype=torch.int16)
    labels[6:] = 3  # one boundary between voxels 5 and 6
    distance = bench.boundary_distance(labels)[:, 0, 0]
    assert distance.tolist() == [5, 4, 3, 2, 1, 0, 0, 1, 2, 3, 4, 5]


def test_scores_rank_the_wrong_voxels():
    """A map that is high exactly on the wrong voxels scores 1; its negation 0; the region excludes background."""
    predicted = torch.tensor([0, 0, 1, 1, 1, 2, 2, 2], dtype=torch.int16)
    truth = torch.tensor([0, 1, 1, 1, 2, 2, 2, 2], dtype=torch.int16)
    wrong = (predicted != truth).float()
    result = bench.scores(predicted, truth, {"perfect": wrong, "inverted": -wrong})
    assert result["perfect"] == 1.0 and result["inverted"] == 0.0
    assert result["wrong_fraction"] == pytest.approx(2 / 7)  # voxel 0 is background in both: outside the region
    # boundary distance of the predicted map over the region (voxels 1-7): 0, 0, 1, 0, 0, 1, 2; the wrong voxels
    # (1 and 4) sit at 0: each beats 3 of the 5 right ones and ties 2 -> (2 * (3 + 2 / 2)) / 10
    assert result["boundary_distance"] == pytest.approx(0.8)


def test_main_writes_the_table(tmp_path, tiny_dataset, single_thread):
    report = run_validation_study(
        bench, tmp_path, tiny_dataset, "uncertainty_ceiling", "--subjects", "T01", "--samples", "2"
    )
    assert report["subjects"] == ["T01"] and report["train_subjects_for_the_probe"] == ["T02", "T03"]
    for kind in ("real", "probe"):
        m = report["summary"][kind]
        assert 0 <= m["wrong_fraction"] <= 1
        assert np.isnan(m["calibrated"]) or 0 <= m["calibrated"] <= 1  # NaN: a probe of a random model moves nothing
    assert 0 <= report["summary"]["real"]["boundary_distance"] <= 1
    assert "oracle direction" in report["markdown"] and "wrongly propagated" in report["markdown"]


def test_scores_are_nan_where_no_voxel_or_every_voxel_is_wrong():
    labels = torch.tensor([0, 1, 1, 2, 2], dtype=torch.int16)
    same = bench.scores(labels, labels, {"calibrated": torch.rand(5)})
    assert same["wrong_fraction"] == 0.0 and math.isnan(same["calibrated"]) and math.isnan(same["boundary_distance"])


def test_too_few_samples_are_refused(tmp_path, tiny_dataset):
    with pytest.raises(SystemExit, match="--samples must be >= 2"):
        bench.main(["--dataset-dir", str(tiny_dataset), "--samples", "1", "--out-dir", str(tmp_path)])


@pytest.mark.parametrize(("scale", "name"), [(1 / 64, "1/64"), (0.25, "1/4"), (1.0, "1"), (4.0, "4")])
def test_scale_names(scale, name):
    assert bench.scale_name(scale) == name
