"""Tests of any-pair data: subject pairs, pair-list files, scan caching and the random pair dataset."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import make_tiny_dataset

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.pairs import (
    ATLAS_ID,
    PairDataset,
    mixed_sampler,
    ordered_pairs,
    read_pairs_file,
    scan_dicts,
    subject_pairs,
)
from monai_probreg.data.transforms import registration_transforms
from monai_probreg.utils.errors import InputError


@pytest.fixture(scope="module")
def four(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("four"), num_subjects=4, shape=(16, 16, 16))


def test_subject_pairs_are_every_ordered_pair_then_every_subject_to_the_atlas(four):
    index = index_dataset(four)
    pairs = subject_pairs(index, ["T01", "T02", "T03"], require_labels=True)
    ids = [p["id"] for p in pairs]
    assert ids == [
        "T01_to_T02",
        "T01_to_T03",
        "T02_to_T01",
        "T02_to_T03",
        "T03_to_T01",
        "T03_to_T02",
        "T01_to_atlas",
        "T02_to_atlas",
        "T03_to_atlas",
    ]
    first = pairs[0]
    assert first["moving"].endswith("T01.nii.gz") and first["fixed"].endswith("T02.nii.gz")
    assert first["moving_label"].endswith("labels/T01.nii.gz") and first["fixed_label"].endswith("labels/T02.nii.gz")
    assert pairs[-1]["fixed"] == str(index.atlas_image)
    assert len(subject_pairs(index, ["T01", "T02"], include_atlas=False)) == 2
    with pytest.raises(ValueError, match="T09"):
        subject_pairs(index, ["T09"])


def test_ordered_pairs_weights_the_atlas_and_never_moves_it_by_default():
    ids = ["S1", "S2", "S3", ATLAS_ID]
    pairs = ordered_pairs(ids, atlas_repeats=2)
    assert len(pairs) == 3 * 2 + 3 * 2
    assert all(m != f and m != 3 for m, f in pairs)
    assert sum(f == 3 for _, f in pairs) == 6
    assert ordered_pairs(ids, atlas_repeats=0) == [(m, f) for m in range(3) for f in range(3) if m != f]
    assert (3, 0) in ordered_pairs(ids, atlas_as_moving=True)
    with pytest.raises(ValueError, match="atlas_repeats"):
        ordered_pairs(ids, atlas_repeats=-1)
    with pytest.raises(ValueError, match="no pair"):
        ordered_pairs(["S1"])


def test_ordered_pairs_adds_each_scan_against_itself_self_repeats_times():
    ids = ["S1", "S2", ATLAS_ID]
    plain = ordered_pairs(ids, atlas_repeats=1)
    pairs = ordered_pairs(ids, atlas_repeats=1, self_repeats=3)
    assert pairs[: len(plain)] == plain
    extra = pairs[len(plain) :]
    assert sorted(extra) == sorted([(0, 0), (1, 1), (2, 2)] * 3)
    assert ordered_pairs(["S1"], self_repeats=1) == [(0, 0)]
    with pytest.raises(ValueError, match="self_repeats"):
        ordered_pairs(ids, self_repeats=-1)


def test_pair_dataset_builds_pairs_from_cached_scans_with_the_pair_keys(four):
    index = index_dataset(four)
    scans = scan_dicts(index, ["T01", "T02"], require_labels=True)
    assert [s["id"] for s in scans] == ["T01", "T02", ATLAS_ID]
    transform = registration_transforms(image_keys=["image"], label_keys=["label"])
    cached = [transform(s) | {"id": s["id"]} for s in scans]
    seen = []
    dataset = PairDataset(cached, ordered_pairs([s["id"] for s in scans]), transform=lambda d: seen.append(d) or d)
    item = dataset[0]
    assert item["id"] == "T01_to_T02" and len(dataset) == 4 and seen
    assert torch.equal(item["moving"], cached[0]["image"]) and torch.equal(item["fixed_label"], cached[1]["label"])
    # the pair is the same as the pair-dict path would give (same transforms, keys renamed)
    reference = registration_transforms()(subject_pairs(index, ["T01", "T02"], include_atlas=False)[0])
    for key in ("moving", "fixed", "moving_label", "fixed_label"):
        torch.testing.assert_close(item[key].as_tensor(), reference[key].as_tensor(), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"index scans 0\.\.2"):
        PairDataset(cached, [(0, 3)])
    self_pair = PairDataset(cached, [(1, 1)])[0]  # a self pair: the same scan on both sides
    assert self_pair["id"] == "T02_to_T02" and torch.equal(self_pair["moving"], self_pair["fixed"])


def test_read_pairs_file_csv_and_json_with_relative_paths(four, tmp_path):
    csv_file = four / "pairs.csv"
    csv_file.write_text(
        "moving,fixed,moving_label,fixed_label\nimages/T01.nii.gz,images/T02.nii.gz,"
        "labels/T01.nii.gz,labels/T02.nii.gz\nimages/T03.nii.gz,atlas/A01_image.nii.gz,,\n"
    )
    pairs = read_pairs_file(csv_file)
    assert [p["id"] for p in pairs] == ["T01_to_T02", "T03_to_A01_image"]
    assert pairs[0]["moving_label"] == str(four / "labels" / "T01.nii.gz") and "moving_label" not in pairs[1]
    json_file = tmp_path / "pairs.json"
    json_file.write_text(
        json.dumps(
            {
                "registration_val": [
                    {
                        "moving": str(four / "images" / "T02.nii.gz"),
                        "fixed": str(four / "images" / "T04.nii.gz"),
                        "id": "a",
                    }
                ]
            }
        )
    )
    assert read_pairs_file(json_file) == [
        {"moving": str(four / "images" / "T02.nii.gz"), "fixed": str(four / "images" / "T04.nii.gz"), "id": "a"}
    ]
    with pytest.raises(InputError, match="needs moving_label"):
        read_pairs_file(csv_file, require_labels=True)


@pytest.mark.parametrize(
    "text, words",
    [
        ("moving,fixed\nimages/T01.nii.gz,images/T99.nii.gz\n", "T99.nii.gz' does not exist"),
        ("moving,other\nimages/T01.nii.gz,x\n", "expected 'moving' and 'fixed'"),
        ("moving,fixed,moving_label\nimages/T01.nii.gz,images/T02.nii.gz,labels/T01.nii.gz\n", "both label maps"),
        (
            "moving,fixed,id\nimages/T01.nii.gz,images/T02.nii.gz,x\nimages/T02.nii.gz,images/T01.nii.gz,x\n",
            "used twice",
        ),
        ("moving,fixed\n", "non-empty list"),
    ],
)
def test_bad_pairs_files_name_the_file_and_the_pair(four, tmp_path, text, words):
    bad = four / f"bad_{abs(hash(text))}.csv"
    bad.write_text(text)
    with pytest.raises(InputError, match=words) as err:
        read_pairs_file(bad)
    assert bad.name in str(err.value)


def test_a_missing_or_unparsable_pairs_file_is_named(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_pairs_file(tmp_path / "none.csv")
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(InputError, match="broken.json"):
        read_pairs_file(broken)


def test_mixed_sampler_draws_each_dataset_at_its_fraction_whatever_its_size():
    sampler = mixed_sampler([10, 1000], [0.5, 0.5], num_samples=4000, generator=torch.Generator().manual_seed(0))
    drawn = torch.tensor(list(sampler))
    first = (drawn < 10).float().mean().item()
    assert abs(first - 0.5) < 0.03  # sizes 10 and 1000: uniform sampling would give 0.01
    assert drawn.max() < 1010 and len(set((drawn[drawn < 10]).tolist())) == 10


def test_mixed_sampler_never_draws_a_dataset_of_fraction_zero():
    drawn = list(mixed_sampler([5, 5], [1.0, 0.0], num_samples=200, generator=torch.Generator().manual_seed(0)))
    assert max(drawn) < 5


@pytest.mark.parametrize(
    "sizes, fractions, num_samples",
    [
        ([5, 5], [1.0], 10),
        ([], [], 10),
        ([0, 5], [0.5, 0.5], 10),
        ([5, 5], [-0.1, 1.1], 10),
        ([5, 5], [0, 0], 10),
        ([5, 5], [0.5, 0.5], 0),
    ],
)
def test_mixed_sampler_rejects_bad_arguments(sizes, fractions, num_samples):
    with pytest.raises(ValueError, match="expected|must be"):
        mixed_sampler(sizes, fractions, num_samples)


def test_pair_dataset_prefixes_pair_ids_with_its_space(four):
    index = index_dataset(four)
    scans = [{"id": s["id"], "image": torch.zeros(1, 2, 2, 2)} for s in scan_dicts(index, index.ids[:2])]
    assert PairDataset(scans, [(0, 1)], space="template")[0]["id"] == f"template:{scans[0]['id']}_to_{scans[1]['id']}"
    assert PairDataset(scans, [(0, 1)])[0]["id"] == f"{scans[0]['id']}_to_{scans[1]['id']}"
