"""experiments/label_entropy_ranking.py: the partial-volume label distribution in closed form on tiny grids, and a
run on the tiny dataset."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import load_script, run_validation_study

bench = load_script("experiments", "label_entropy_ranking")


def test_partial_volume_splits_a_half_voxel_shift_between_the_two_neighbours():
    labels = torch.tensor([[1, 2, 3, 4]], dtype=torch.int16)  # (1, 4): 2-d, axis 1 varies
    displacement = torch.zeros(1, 2, 1, 4)
    displacement[0, 1] = 0.5  # every voxel reads half a voxel towards higher indices along axis 1
    weights, values = bench.partial_volume(labels, displacement)
    assert weights.shape == values.shape == (4, 4)
    assert torch.allclose(weights.sum(0), torch.ones(4))
    mass = {}
    for w, v in zip(weights[:, 1], values[:, 1]):  # voxel 1 (label 2) reads between labels 2 and 3
        mass[int(v)] = mass.get(int(v), 0.0) + float(w)
    assert mass[2] == pytest.approx(0.5) and mass[3] == pytest.approx(0.5)
    # the last voxel reads half outside the grid: that half is label 0
    last = {}
    for w, v in zip(weights[:, 3], values[:, 3]):
        last[int(v)] = last.get(int(v), 0.0) + float(w)
    assert last[4] == pytest.approx(0.5) and last[0] == pytest.approx(0.5)


def test_partial_volume_of_the_zero_displacement_is_the_label_itself():
    labels = torch.randint(0, 5, (3, 4, 5), generator=torch.Generator().manual_seed(0)).to(torch.int16)
    weights, values = bench.partial_volume(labels, torch.zeros(1, 3, 3, 4, 5))
    top = weights.argmax(0)
    assert torch.equal(values.gather(0, top[None])[0], labels.reshape(-1).to(values.dtype))
    assert torch.allclose(weights.max(0).values, torch.ones(60))


def test_partial_volume_rejects_a_displacement_of_another_grid():
    with pytest.raises(ValueError, match=r"expected a displacement \(1, 2"):
        bench.partial_volume(torch.zeros(3, 4, dtype=torch.int16), torch.zeros(1, 2, 4, 3))


def test_soft_label_maps_entropy_and_disagreement():
    labels = torch.tensor([[1, 1, 2, 2]], dtype=torch.int16)
    still = torch.zeros(1, 2, 1, 4)
    half = still.clone()
    half[0, 1] = 0.5
    answer = labels.clone()
    maps = bench.soft_label_maps(labels, [still, still], answer)
    assert torch.equal(maps["entropy"], torch.zeros(1, 4)) and torch.equal(maps["disagreement"], torch.zeros(1, 4))
    # voxel 1 reads between labels 1 and 2 in one sample of two: p = (3/4, 1/4)
    maps = bench.soft_label_maps(labels, [still, half], answer)
    expected = -(0.75 * math.log(0.75) + 0.25 * math.log(0.25))
    assert float(maps["entropy"][0, 1]) == pytest.approx(expected, rel=1e-5)
    assert float(maps["disagreement"][0, 1]) == pytest.approx(0.25)
    assert float(maps["entropy"][0, 0]) == pytest.approx(0.0, abs=1e-6)  # reads between two voxels of label 1


def test_too_few_samples_are_refused(tmp_path, tiny_dataset):
    with pytest.raises(SystemExit, match="--samples must be >= 2"):
        bench.main(["--dataset-dir", str(tiny_dataset), "--samples", "1", "--out-dir", str(tmp_path)])


def test_main_writes_the_table(tmp_path, tiny_dataset, single_thread):
    report = run_validation_study(
        bench, tmp_path, tiny_dataset, "label_entropy_ranking", "--subjects", "T01", "--samples", "2"
    )
    assert report["subjects"] == ["T01"]
    names = set(report["summary"])
    assert {"wrong_fraction", "boundary_distance", "nearest, K = 2: entropy", "partial volume, K = 2: entropy"} <= names
    for name, value in report["summary"].items():
        assert math.isnan(value) or 0 <= value <= 1, name
    assert "partial volume" in report["markdown"]
