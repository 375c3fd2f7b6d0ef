"""benchmarks/common.py, the helpers the scripts share, and how the scripts reach it: plain imports (the script's own
folder is on sys.path when it runs, and benchmarks/ through PYTHONPATH for the experiments; pytest's pythonpath gives
the tests the same), no sys.path edits, no private name of another script."""

from __future__ import annotations

import ast
import sys

import common
import pytest
from bench_helpers import REPO

SCRIPTS = sorted((REPO / "benchmarks").glob("*.py")) + sorted((REPO / "experiments").glob("*.py"))
LOCAL = {p.stem for p in SCRIPTS}


def _edits_sys_path(tree: ast.AST) -> bool:
    return any(
        isinstance(node, ast.Attribute)
        and node.attr == "path"
        and isinstance(node.value, ast.Name)
        and node.value.id == "sys"
        for node in ast.walk(tree)
    )


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_scripts_import_each_other_plainly_and_only_public_names(script):
    tree = ast.parse(script.read_text())
    assert not _edits_sys_path(tree), f"{script.name} touches sys.path"
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module in LOCAL:
            private = [a.name for a in node.names if a.name.startswith("_")]
            assert not private, f"{script.name} imports {private} from {node.module}.py"


def test_default_paths_are_next_to_the_checkout():
    assert common.REPO == REPO
    assert common.DEFAULT_DATASET == REPO.parent / "shared" / "data" / "lpba40"
    assert common.DEFAULT_NATIVE == REPO.parent / "shared" / "data" / "lpba40-native"
    assert common.DEFAULT_OUT == REPO / "benchmarks" / "results"


def test_parse_overrides_reads_yaml_values_and_refuses_a_bare_key():
    assert common.parse_overrides(["network_size=[80,96,80]", "network_size=null", "unet_precision=fp32"]) == {
        "network_size": None,
        "unet_precision": "fp32",
    }
    assert common.parse_overrides(["a=1", "b=0.5", "c=[1, 2]"]) == {"a": 1, "b": 0.5, "c": [1, 2]}
    for bad in ("network_size", "=3"):
        with pytest.raises(SystemExit, match="--override expects KEY=VALUE"):
            common.parse_overrides([bad])


def test_bundle_parser_reads_the_configs_with_bundle_root_and_overrides():
    bundle = REPO / "bundle"
    parser = common.bundle_parser(bundle, ["evaluate.yaml"], {"refine_iterations": 3})
    assert parser["bundle_root"] == str(bundle)
    assert parser.get_parsed_content("refinement").num_iterations == 3  # set before anything is parsed
    val_ids = common.bundle_parser(bundle, ["train.yaml"]).get_parsed_content("val_ids")
    assert len(val_ids) > 0 and all(isinstance(s, str) for s in val_ids)


def test_ants_available_reports_a_missing_antspyx(monkeypatch):
    monkeypatch.setitem(sys.modules, "ants", None)  # `import ants` raises ImportError
    ok, message = common.ants_available()
    assert not ok and message.startswith("antspyx not importable (")


def test_run_command_runs_the_cli_in_a_fresh_process_and_names_a_failure(tmp_path):
    done, wall = common.run_command("--help")
    assert done.returncode == 0 and "register" in done.stdout and wall > 0
    missing = tmp_path / "missing.nii.gz"
    with pytest.raises(RuntimeError, match="monai_probreg.cli.main register --moving .*missing.nii.gz.* failed"):
        common.run_command("register", "--moving", str(missing), "--out", str(tmp_path / "out"))


@pytest.mark.parametrize(
    "text, expected",
    [
        ("fine=num_iterations:10,velocity_grid_factor:2", ("fine", {"num_iterations": 10, "velocity_grid_factor": 2})),
        ("lam=prior_lambda:3.5", ("lam", {"prior_lambda": 3.5})),
        ("g=image_loss:gaussian,image_weight:1", ("g", {"image_loss": "gaussian", "image_weight": 1})),
        ("plain=", ("plain", {})),
        ("sym=symmetric_start:true,x:False", ("sym", {"symmetric_start": True, "x": False})),
    ],
)
def test_a_variant_is_a_name_and_typed_fields(text, expected):
    assert common.parse_variant(text) == expected
