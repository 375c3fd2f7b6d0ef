"""experiments/laplace_posterior.py: the Gauss-Newton curvature and the Laplace precision in closed form on tiny
grids, and a run on the tiny dataset."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from conftest import load_script, run_validation_study

bench = load_script("experiments", "laplace_posterior")


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_curvature_of_a_ramp_is_its_squared_slope_along_its_axis_only(axis):
    size, velocity = (8, 10, 12), (4, 5, 6)
    ramp = torch.arange(size[axis], dtype=torch.float32) * 0.1
    shape = [1, 1, 1, 1, 1]
    shape[2 + axis] = size[axis]
    image = ramp.view(shape).expand(1, 1, *size).clone()
    curv = bench.curvature(image, velocity, normalised=False)
    assert curv.shape == (1, 3, *velocity)
    # 0.1 intensity per image voxel = 0.2 per velocity voxel of displacement (the image grid is twice finer)
    assert torch.allclose(curv[0, axis], torch.full(velocity, 0.04), atol=1e-6)
    for other in {0, 1, 2} - {axis}:
        assert torch.equal(curv[0, other], torch.zeros(velocity))


def test_normalised_curvature_divides_by_the_local_variance():
    image = torch.rand(1, 1, 12, 12, generator=torch.Generator().manual_seed(0))
    plain = bench.curvature(image, (6, 6), normalised=False)
    normalised = bench.curvature(image, (6, 6), normalised=True)
    assert normalised.shape == plain.shape == (1, 2, 6, 6)
    assert bool((normalised > plain).all())  # a variance of intensities in [0, 1] (+ the floor) is below 1
    flat = bench.curvature(torch.full((1, 1, 12, 12), 0.3), (6, 6), normalised=True)
    assert torch.equal(flat, torch.zeros_like(flat))


def test_laplace_variance_is_the_inverse_of_prior_pull_and_curvature():
    shape = (1, 3, 2, 3, 4)
    log_var = torch.full(shape, math.log(0.04))
    output = SimpleNamespace(velocity_log_var=log_var, velocity_mean=torch.zeros(shape))
    curv = torch.full(shape, 0.01)
    refinement = SimpleNamespace(prior_lambda=1.5, posterior_weight=0.25)
    residual = torch.full((1, 1, 2, 3, 4), 0.02)
    out = bench.candidates(
        output, residual, curv, 2 * curv, torch.zeros(shape), torch.zeros(shape), refinement, 100.0, 1e3
    )
    prior = 1.5 * 2 * 3 + 0.25 / 0.04
    assert torch.allclose(out["laplace k=1000"], torch.full(shape, 1 / (prior + 10.0)))
    assert torch.allclose(out["laplace ncc k=1000"], torch.full(shape, 1 / (prior + 20.0)))
    assert torch.allclose(out["network + residual (shipped form)"], torch.full(shape, 0.04 + 100 * 0.02))
    # a sum of terms weighs each term by its mean: two constant terms sum to 2
    assert torch.allclose(out["residual + constant"], torch.full(shape, 2.0))
    assert all(v.shape == shape for v in out.values())


def test_scaled_sets_the_mean():
    base = torch.tensor([1.0, 3.0])
    assert torch.allclose(bench.scaled(base, 4.0), torch.tensor([2.0, 6.0]))


def test_too_few_samples_are_refused(tmp_path, tiny_dataset):
    with pytest.raises(SystemExit, match="--samples must be >= 2"):
        bench.main(["--dataset-dir", str(tiny_dataset), "--samples", "1", "--out-dir", str(tmp_path)])


def test_main_writes_the_table(tmp_path, tiny_dataset, single_thread):
    report = run_validation_study(
        bench, tmp_path, tiny_dataset, "laplace_posterior", "--subjects", "T01", "--samples", "2"
    )
    assert report["subjects"] == ["T01"] and report["train_subjects_for_the_probe"] == ["T02", "T03"]
    row = report["summary"]["laplace k=10000"]
    assert set(row) == {"spearman", "spearman + bias", "label_auroc"}
    assert all(math.isnan(v) or -1 <= v <= 1 for v in row.values())
    assert "network + residual (shipped form)" in report["markdown"]
