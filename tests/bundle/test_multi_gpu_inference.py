"""Sharded batch inference: monai_probreg.engines.sharding and bundle/configs/multi_gpu_inference.yaml.

In process: the partition covers every subject once, the merge reproduces a single-process summary and refuses
incomplete shards. End to end: two gloo processes under torchrun on the tiny dataset, compared with one process.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import TINY_LABELS

from monai_probreg.engines.score_files import read_scores, write_scores
from monai_probreg.engines.sharding import MANIFEST, SHARDS_DIR, merge_shards, shard_dir, shard_items
from monai_probreg.fitting.stages import config_files
from monai_probreg.metrics.scores import PairScores

ROOT = Path(__file__).resolve().parents[2]
SHARDED = ROOT / "bundle" / "configs" / "multi_gpu_inference.yaml"


@pytest.mark.parametrize("world_size", [1, 2, 3, 7])
def test_shards_are_disjoint_and_cover_every_subject_once(world_size):
    items = [f"S{i:02d}" for i in range(5)]
    shards = [shard_items(items, rank, world_size) for rank in range(world_size)]
    assert sorted(sum(shards, [])) == items  # each exactly once, also with more ranks than subjects (7)
    assert shards[0][:2] == items[::world_size][:2]  # rank r takes r, r + W, ...
    with pytest.raises(ValueError, match="expected 0 <= rank < world_size, got rank=3, world_size=3"):
        shard_items(items, 3, 3)


def test_rank_comes_from_the_environment_without_a_process_group(monkeypatch, tmp_path):
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "3")
    assert shard_items(list(range(7)), None, None) == [1, 4]
    assert shard_dir(tmp_path) == str(tmp_path / SHARDS_DIR / "rank_1_of_3")


def _scores(seed: float, labels=(21, 22)) -> tuple[PairScores, PairScores]:
    dice = {lab: 0.5 + 0.1 * seed + 0.01 * lab % 0.2 for lab in labels}
    base = {lab: d - 0.2 for lab, d in dice.items()}
    return (
        PairScores(dice, sum(dice.values()) / len(dice), int(seed), 0.01 * seed, 0.1 + seed / 100, 1.0 + seed),
        PairScores(base, sum(base.values()) / len(base), 0, 0.0, 0.0, 0.0),
    )


def test_merge_reproduces_the_single_process_summary(tmp_path):
    rows = [(f"S{i:02d}", *_scores(i)) for i in range(5)]
    rows[3] = (rows[3][0], rows[3][1]._replace(dice={21: 0.7, 22: math.nan}), rows[3][2])  # a NaN survives the trip
    config = {"model_file": "m.pt", "network_size": [16, 16, 16]}
    single = write_scores(tmp_path / "single", rows, config)
    assert read_scores(tmp_path / "single" / "scores.json")[0][3][1].dice[22] != 0.7  # NaN, read back as NaN
    sharded = tmp_path / "sharded"
    for rank in range(2):
        shard = Path(shard_dir(sharded, rank, 2))
        write_scores(shard, shard_items(rows, rank, 2), config)
        for sid, _, _ in shard_items(rows, rank, 2):  # a subject folder, as inference.yaml writes it
            (shard / sid).mkdir()
            (shard / sid / "warped.nii.gz").write_text(sid)
    manifest = merge_shards(sharded)
    assert manifest["summary"] == single
    assert json.loads((sharded / "summary.json").read_text()) == single
    assert (sharded / "scores.csv").read_text() == (tmp_path / "single" / "scores.csv").read_text()
    assert json.loads((sharded / MANIFEST).read_text())["subjects_per_rank"] == {
        "0": ["S00", "S02", "S04"],
        "1": ["S01", "S03"],
    }
    assert [(sharded / f"S{i:02d}" / "warped.nii.gz").read_text() for i in range(5)] == [f"S{i:02d}" for i in range(5)]
    assert not (sharded / SHARDS_DIR).exists()


def test_merge_refuses_missing_or_mixed_shards(tmp_path):
    with pytest.raises(FileNotFoundError, match="no shard folders"):
        merge_shards(tmp_path)
    Path(shard_dir(tmp_path, 0, 3)).mkdir(parents=True)
    Path(shard_dir(tmp_path, 2, 3)).mkdir(parents=True)
    with pytest.raises(ValueError, match=r"expected 3 shards .* none from ranks \[1\]"):
        merge_shards(tmp_path)
    Path(shard_dir(tmp_path, 0, 2)).mkdir(parents=True)
    with pytest.raises(ValueError, match=r"different world sizes \[2, 3\]"):
        merge_shards(tmp_path)


def _bundle_run(configs: list[Path], bundle: Path, dataset: Path, out: Path, nproc: int, returncode: int = 0) -> str:
    """Run ``monai.bundle run`` on ``configs``: under torchrun with ``nproc`` gloo processes, or plain if 0."""
    launcher = ["-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}"] if nproc else []
    cmd = [
        sys.executable,
        *launcher,
        "-m",
        "monai.bundle",
        "run",
        "--config_file",
        "[" + ",".join(f"'{c}'" for c in configs) + "]",
        "--bundle_root",
        str(bundle),
        "--dataset_dir",
        str(dataset),
        "--output_dir",
        str(out),
        "--num_workers",
        "0",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}  # gloo on CPU even on a GPU host
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    log = proc.stdout + proc.stderr
    assert proc.returncode == returncode, log[-4000:]
    return log


needs_gloo = pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="torch.distributed with the gloo backend is not available in this torch build",
)


@needs_gloo
def test_two_process_evaluate_equals_one_process(tmp_path, tiny_dataset, bundle):
    single = tmp_path / "single"
    _bundle_run(config_files(bundle, ["evaluate.yaml"]), bundle, tiny_dataset, single, nproc=0)
    sharded = tmp_path / "sharded"
    log = _bundle_run([*config_files(bundle, ["evaluate.yaml"]), SHARDED], bundle, tiny_dataset, sharded, nproc=2)
    assert "merged 2 shards, 3 subjects" in log
    assert sorted(p.name for p in sharded.iterdir()) == sorted([MANIFEST, "scores.csv", "scores.json", "summary.json"])
    manifest = json.loads((sharded / MANIFEST).read_text())
    assert manifest["subjects_per_rank"] == {"0": [], "1": []} and manifest["num_subjects"] == 3  # scored, no folders
    one, two = (json.loads((d / "summary.json").read_text()) for d in (single, sharded))
    # the same subjects through the same float32 code in another process: identical scores, only runtimes differ
    for section in ("dice_per_label", "no_registration", "config"):
        assert one[section] == two[section], section
    for field in ("mean_dice", "num_folding", "std_log_jacobian"):
        assert one["registered"][field] == two["registered"][field], field
    assert set(one["dice_per_label"]) == {str(lab) for lab in TINY_LABELS}
    assert [row[0] for row in read_scores(sharded / "scores.json")[0]] == ["T01", "T02", "T03"]


@needs_gloo
def test_two_process_inference_writes_every_subject_once(tmp_path, tiny_dataset, bundle):
    out = tmp_path / "out"
    log = _bundle_run([bundle / "configs" / "inference.yaml", SHARDED], bundle, tiny_dataset, out, nproc=2)
    assert "merged 2 shards, 3 subjects" in log
    assert sorted(p.name for p in out.iterdir()) == ["README.txt", "T01", "T02", "T03", MANIFEST]
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest == {
        "world_size": 2,
        "subjects_per_rank": {"0": ["T01", "T03"], "1": ["T02"]},
        "num_subjects": 3,
        "scored": False,
        "failed": [],
    }
    for sid in ("T01", "T02", "T03"):
        assert (out / sid / "displacement.nii.gz").is_file() and (out / sid / "warped_label.nii.gz").is_file()


@needs_gloo
def test_two_process_evaluate_skips_a_damaged_subject_and_fails(tmp_path, tiny_dataset, bundle):
    dataset = tmp_path / "data"
    shutil.copytree(tiny_dataset, dataset)
    damaged = dataset / "images" / "T02.nii.gz"  # rank 1's only subject
    damaged.write_bytes(damaged.read_bytes()[: damaged.stat().st_size // 2])
    out = tmp_path / "out"
    log = _bundle_run([*config_files(bundle, ["evaluate.yaml"]), SHARDED], bundle, dataset, out, nproc=2, returncode=1)
    assert "merged 2 shards, 2 subjects" in log
    failed = list(csv.DictReader((out / "failed.csv").open()))
    assert [r["id"] for r in failed] == ["T02"] and str(damaged) in failed[0]["reason"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_subjects"] == 2 and summary["failed"][0]["id"] == "T02"
    assert json.loads((out / MANIFEST).read_text())["failed"] == summary["failed"]
