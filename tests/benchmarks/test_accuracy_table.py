"""benchmarks/accuracy_table.py on the tiny synthetic dataset, with random weights (never the real data).

Pins what the README table rests on: the JSON layout (tasks "atlas" and "pairs", rows per method), Dice in [0, 1],
the no-registration Dice equal to Dice computed with numpy from the label files, a random near-identity model scoring
like no registration, the refinement row using its settings, the subjects read from train.yaml's val_ids, rows that
cannot run saying why, and the missing-dataset exit. When antspyx is importable,
also ANTs SyN (about 0.5 s per 32^3 pair): it must improve Dice (moving = subject, fixed = atlas), and its forward
field converted to our convention must reproduce ANTs' own nearest-neighbour label warp.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from bench_helpers import load_benchmark
from conftest import DEFAULT_WEIGHTS, TINY_LABELS, bundle_with_random_model, numpy_mean_dice

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "benchmarks" / "accuracy_table.py"
SUBJECTS = ["T01", "T02", "T03"]
FAST = ["--threads", "1", "--override", "network_size=[16,16,16]"]  # 1 thread; a small UNet grid (any size loads)
RECORD_KEYS = {"mean_dice", "dice", "num_folding", "percent_folding", "std_log_jacobian", "runtime_s"}
AGGREGATE_KEYS = RECORD_KEYS - {"dice"}


accuracy_table = load_benchmark("accuracy_table")


def _ants_importable() -> bool:
    try:
        import ants  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(autouse=True)
def _one_itk_thread(monkeypatch, single_thread):
    monkeypatch.setenv("ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS", "1")  # main() sets it; monkeypatch restores it


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the bundle's configs with a randomly initialised ProbRegNet state_dict in models/model.pt."""
    return bundle_with_random_model(tmp_path_factory.mktemp("bundle"), REPO / "bundle", network_size=None)


def _run(tmp_path: Path, dataset: Path, bundle: Path, *extra: str) -> dict:
    out = tmp_path / "out"
    argv = ["--dataset-dir", str(dataset), "--bundle-root", str(bundle), "--out-dir", str(out), *FAST, *extra]
    assert accuracy_table.main(argv) == 0
    return json.loads((out / "accuracy_table.json").read_text())


def test_table_json_and_chart(tmp_path, tiny_dataset, bundle, capsys):
    with_ants = _ants_importable()
    methods = ["identity", "ours", "refined"] + (["ants"] if with_ants else [])
    # posterior weight 0: the random head's log_var of -10 would pin the refined mean to the network's
    result = _run(
        tmp_path,
        tiny_dataset,
        bundle,
        "--subjects",
        *SUBJECTS,
        "--methods",
        *methods,
        "--refine-iterations",
        "3",
        "--override",
        "refine_posterior_weight=0",
    )

    assert result["subjects"] == SUBJECTS and result["dataset_dir"] == str(tiny_dataset.resolve())
    assert {"settings", "versions", "methods", "markdown", "tasks"} <= set(result)
    # every subject -> the atlas, then the 6 ordered pairs of 3 subjects (fixed never the atlas)
    assert result["tasks"]["atlas"] == [f"{s}_to_atlas" for s in SUBJECTS]
    assert result["tasks"]["pairs"] == [f"{m}_to_{f}" for m in SUBJECTS for f in SUBJECTS if m != f]
    assert result["settings"]["threads"] == 1
    assert result["settings"]["network (evaluate.yaml)"]["network_size"] == [16, 16, 16]
    assert result["settings"]["refinement (evaluate.yaml, refined row)"]["num_iterations"] == 3
    assert result["settings"]["refinement (evaluate.yaml, refined row)"]["posterior_weight"] == 0
    assert result["settings"]["model_file"] == str(bundle / "models" / DEFAULT_WEIGHTS)  # evaluate.yaml's default
    assert result["versions"]["torch"] == torch.__version__
    # rows in table order, whatever the order of --methods
    assert list(result["methods"]) == [m for m in accuracy_table.METHODS if m in methods]

    rows = result["methods"]
    for key, row in rows.items():
        assert row["status"] == "ok" and row["name"] == accuracy_table.METHODS[key]
        assert list(row["per_pair"]) == result["tasks"]["atlas"] + result["tasks"]["pairs"]
        assert set(row["aggregate"]) == {"atlas", "pairs"} and set(row["aggregate_all"]) == AGGREGATE_KEYS
        for pid, record in row["per_pair"].items():
            assert set(record) == RECORD_KEYS | {"task"} and record["task"] == ("atlas" if "atlas" in pid else "pairs")
            assert set(record["dice"]) == {str(lab) for lab in TINY_LABELS}
            assert all(0.0 <= d <= 1.0 for d in [record["mean_dice"], *record["dice"].values()]), (key, record)
            assert isinstance(record["num_folding"], int) and record["num_folding"] >= 0
        for task in ("atlas", "pairs"):
            dice = [r["mean_dice"] for r in row["per_pair"].values() if r["task"] == task]
            # population std over the pairs of a task, as evaluate.yaml's summary.json (float64 sums: 1e-12)
            assert row["aggregate"][task]["mean_dice"]["mean"] == pytest.approx(np.mean(dice), abs=1e-12)
            assert row["aggregate"][task]["mean_dice"]["std"] == pytest.approx(np.std(dice), abs=1e-12)

    identity, ours = rows["identity"]["per_pair"], rows["ours"]["per_pair"]
    for sid in SUBJECTS:
        pid = f"{sid}_to_atlas"
        # RAS reorientation and padding do not change Dice: equal to numpy on the files (float64: 1e-12)
        assert identity[pid]["mean_dice"] == pytest.approx(numpy_mean_dice(tiny_dataset, sid), abs=1e-12)
        # random initial weights move voxels by < 1e-4: the nearest-neighbour warp is the identity
        assert ours[pid]["mean_dice"] == pytest.approx(identity[pid]["mean_dice"], abs=1e-12)
        assert ours[pid]["runtime_s"] > 0 and identity[pid]["runtime_s"] == 0
    # the refinement moves the random model's ~0 field towards the pair: Dice changes on some pair
    refined = rows["refined"]["per_pair"]
    assert any(refined[p]["mean_dice"] != ours[p]["mean_dice"] for p in ours)
    assert rows["refined"]["refinement"]["num_iterations"] == 3 and "refinement" not in rows["ours"]
    assert rows["ours"]["threads"] == 1 and rows["identity"]["threads"] is None

    if with_ants:
        ants_rows = rows["ants"]["per_pair"]
        assert rows["ants"]["threads"] == 1 and result["versions"]["antspyx"]
        for pid in result["tasks"]["atlas"]:
            # the phantoms differ by shifts of up to 2 voxels: SyN takes Dice from ~0.7 to ~0.93 (observed);
            # a swapped moving/fixed or a mis-converted grid would not improve it
            assert ants_rows[pid]["mean_dice"] > identity[pid]["mean_dice"] + 0.05, pid
            assert ants_rows[pid]["runtime_s"] > 0 and np.isfinite(ants_rows[pid]["std_log_jacobian"])

    out = capsys.readouterr().out
    assert result["markdown"] in out
    assert "| method | validation -> atlas: mean Dice (std) | pairs between validation subjects: mean Dice" in out
    assert "[9/9] T03_to_T02 ours + refinement: Dice" in out  # progress per pair
    png = (tmp_path / "out" / "accuracy_table.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_default_subjects_are_train_yaml_val_ids(tmp_path, tiny_dataset, bundle):
    """The split is written once, in train.yaml: the script reads val_ids from the bundle it is given."""
    custom = tmp_path / "bundle"
    shutil.copytree(bundle, custom)
    train = custom / "configs" / "train.yaml"
    text = train.read_text()
    assert text.count("\nval_ids: ") == 1
    train.write_text(
        "\n".join("val_ids: [T03, T01]" if line.startswith("val_ids: ") else line for line in text.splitlines()) + "\n"
    )
    result = _run(tmp_path, tiny_dataset, custom, "--methods", "identity", "--tasks", "pairs")
    assert result["subjects"] == ["T03", "T01"] and list(result["methods"]) == ["identity"]
    assert result["tasks"] == {"pairs": ["T03_to_T01", "T01_to_T03"]}


def test_rows_without_antspyx_or_weights_say_why(tmp_path, tiny_dataset, bundle, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ants", None)  # `import ants` raises ImportError
    result = _run(
        tmp_path,
        tiny_dataset,
        bundle,
        "--subjects",
        "T01",
        "--tasks",
        "atlas",
        "--methods",
        "identity",
        "ants",
        "ours",
        "--model-file",
        str(tmp_path / "missing.pt"),
    )
    rows = result["methods"]
    assert rows["ants"]["status"].startswith("skipped: antspyx not importable")
    assert rows["ours"]["status"] == f"not trained (no {tmp_path / 'missing.pt'})"
    assert rows["ours"]["per_pair"] == {} and "aggregate" not in rows["ours"]
    assert rows["identity"]["status"] == "ok" and result["versions"]["antspyx"] is None
    out = capsys.readouterr().out
    assert "| ANTs SyN | skipped: antspyx not importable" in out


def test_bad_refine_iterations_stop_before_any_work(tmp_path, tiny_dataset, bundle):
    with pytest.raises(SystemExit, match="--refine-iterations must be >= 1; got 0"):
        _run(tmp_path, tiny_dataset, bundle, "--refine-iterations", "0")


def test_ants_field_reproduces_ants_label_warp(tiny_dataset):
    """Our reading of ANTs' composed forward field (voxels, component k = array axis k, pull-back) warps the labels
    exactly as ANTs' nearest-neighbour interpolation does, and the sign matters."""
    pytest.importorskip("ants")
    from monai.data import Dataset

    from monai_probreg.blocks.warp import warp_labels
    from monai_probreg.data.dataset import index_dataset, labelled_pairs
    from monai_probreg.data.transforms import registration_transforms
    from monai_probreg.metrics.scores import score_pair

    item = Dataset(labelled_pairs(index_dataset(tiny_dataset), ["T01"]), registration_transforms())[0]
    pair = {k: v[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
    ants_labels, displacement, runtime = accuracy_table.ants_register(
        pair["moving"], pair["fixed"], pair["moving_label"]
    )
    assert displacement.shape == (1, 3, 32, 32, 32) and runtime > 0
    ours = warp_labels(pair["moving_label"].as_tensor(), displacement)
    # both sample the moving labels nearest neighbour at the same points x + u(x); only points within float32
    # rounding of a voxel boundary could differ (none observed): allow 0.1% of voxels
    assert (ours != ants_labels).float().mean().item() < 1e-3
    forward = score_pair(displacement, pair["moving_label"], pair["fixed_label"]).mean_dice
    backward = score_pair(-displacement, pair["moving_label"], pair["fixed_label"]).mean_dice
    assert forward > backward + 0.1
