"""One home for each default: evaluate.yaml is an overlay of inference.yaml (it holds only what evaluation does
differently; everything reads the two merged, :func:`monai_probreg.fitting.stages.bundle_parser`), and the posterior
sample count is one named constant (``monai_probreg.uncertainty.calibration.POSTERIOR_SAMPLES``) the others read."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from monai_probreg.fitting.stages import OVERLAY_BASES, bundle_parser, config_files
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES
from monai_probreg.weights.settings import network_settings

ROOT = Path(__file__).resolve().parents[2]
BUNDLE = ROOT / "bundle"
CONFIGS = BUNDLE / "configs"

# the keys evaluate.yaml sets although inference.yaml has them, each with why evaluation needs its own value; any
# other key of inference.yaml written again in evaluate.yaml is a repeat that can drift
EVALUATE_OVERRIDES = {
    "output_dir": "its own run folder (runs/evaluate), so an evaluation never mixes with an inference run",
    "dataset_index": "scores need the dataset's own atlas labels: no default template stands in for a missing atlas",
    "pairs": "labelled pairs only (labelled_pairs, read_pairs_file(require_labels=True)): a clear error without labels",
    "with_labels": "every pair is labelled: the preprocessing loads labels without reading the pairs first",
    "handlers": "RegistrationScorer (scores.csv, summary.json) instead of RegistrationWriter's maps",
}
# what the merged evaluate config must resolve exactly as inference.yaml does: the network and its weights, the
# refinement, the calibration and the quality check's inputs
SHARED_VALUES = (
    "model_file",
    "device",
    "divisor",
    "refinement",
    "calibrate",
    "calibration",
    "std_scale",
    "bias_fraction",
    "quality_estimate",
    "num_samples",
)


def _raw(name: str) -> dict:
    return yaml.safe_load((CONFIGS / name).read_text(encoding="utf-8"))


def test_evaluate_yaml_alone_repeats_none_of_inference_yaml():
    evaluate, inference = _raw("evaluate.yaml"), _raw("inference.yaml")
    repeated = set(evaluate) & set(inference)
    assert repeated == set(EVALUATE_OVERRIDES), f"evaluate.yaml repeats {sorted(repeated - set(EVALUATE_OVERRIDES))}"
    for key in EVALUATE_OVERRIDES:  # an override equal to the base would be a repeat under another name
        assert evaluate[key] != inference[key], key
    assert not any(key.startswith("refine_") for key in evaluate)  # the refinement's one home is inference.yaml


def test_an_overlay_is_read_after_its_base_and_each_file_once():
    assert config_files(BUNDLE, ["evaluate.yaml"]) == [CONFIGS / "inference.yaml", CONFIGS / "evaluate.yaml"]
    both = [CONFIGS / "inference.yaml", CONFIGS / "evaluate.yaml", CONFIGS / "multi_gpu_inference.yaml"]
    assert config_files(BUNDLE, ["evaluate.yaml", "multi_gpu_inference.yaml"]) == both
    assert config_files(BUNDLE, ["inference.yaml", "evaluate.yaml", "multi_gpu_inference.yaml"]) == both
    assert config_files(BUNDLE, ["train.yaml"]) == [CONFIGS / "train.yaml"]  # not an overlay: as it is
    for overlay, base in OVERLAY_BASES.items():
        assert (CONFIGS / overlay).is_file() and (CONFIGS / base).is_file()


def test_merged_evaluate_resolves_inference_yamls_objects():
    evaluate, inference = bundle_parser(BUNDLE, ["evaluate.yaml"]), bundle_parser(BUNDLE, ["inference.yaml"])
    for key in SHARED_VALUES:
        assert evaluate.get_parsed_content(key) == inference.get_parsed_content(key), key
    assert evaluate.get_parsed_content("refinement").enabled  # the default path refines, in both
    for key in ("network_def", "zoo_network_def"):
        assert network_settings(evaluate.get_parsed_content(key)) == network_settings(
            inference.get_parsed_content(key)
        ), key
    # the quality check and the inferer are inference.yaml's, built on the same refinement
    assert evaluate.get_parsed_content("inferer").refinement == inference.get_parsed_content("refinement")
    assert evaluate["quality_check"] == inference["quality_check"]
    # and evaluation's own: the scorer, recording the refinement in use
    assert evaluate["handlers"][0]["_target_"].endswith("RegistrationScorer")
    assert evaluate["handlers"][0]["config"]["refinement"] == "$@refinement.as_dict()"
    assert evaluate.get_parsed_content("output_dir") == str(BUNDLE / "runs" / "evaluate")


def test_an_inherited_value_is_overridden_through_the_merged_config():
    # what --refine_iterations 0 --network_size null on the command line of both files does
    evaluate = bundle_parser(BUNDLE, ["evaluate.yaml"], {"refine_iterations": 0, "network_size": None})
    assert not evaluate.get_parsed_content("refinement").enabled
    assert evaluate.get_parsed_content("handlers#0#config#network_size") is None


# ----------------------------------------------------------------------------------------- the posterior sample count
# a literal count of posterior samples assigned or defaulted: `NAME_SAMPLES = 16`, `samples: int = 16`,
# `num_samples: 16`, `add_argument("--samples", ..., default=16)`
SAMPLE_LITERAL = (
    re.compile(rf"(?i)\b\w*samples?\b[\"']?\s*(?::\s*int\s*)?[:=]\s*{POSTERIOR_SAMPLES}\b"),
    re.compile(rf"(?i)[\"']--samples[\"'].*\bdefault\s*=\s*{POSTERIOR_SAMPLES}\b"),
)
SOURCES = ("monai_probreg", "benchmarks", "experiments", "bundle/configs")


def test_the_sample_count_has_one_home():
    found = [
        f"{path.relative_to(ROOT)}:{n}"
        for folder in SOURCES
        for path in sorted((ROOT / folder).rglob("*"))
        if path.suffix in (".py", ".yaml")
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if any(p.search(line) for p in SAMPLE_LITERAL)
    ]
    assert found == ["monai_probreg/uncertainty/calibration.py:" + _constant_line()], found


def _constant_line() -> str:
    lines = (ROOT / "monai_probreg" / "uncertainty" / "calibration.py").read_text(encoding="utf-8").splitlines()
    return str(next(n for n, line in enumerate(lines, 1) if line.startswith("POSTERIOR_SAMPLES = ")))


def test_the_others_read_the_sample_count(capsys):
    from monai_probreg.cli.main import build_parser
    from monai_probreg.fitting import command
    from monai_probreg.fitting.calibration_probes import ProbeSettings
    from monai_probreg.registration.demo import DEMO_SAMPLES

    assert "POSTERIOR_SAMPLES" in _raw("inference.yaml")["num_samples"]  # a reference, not a second literal
    assert bundle_parser(BUNDLE, ["inference.yaml"]).get_parsed_content("num_samples") == POSTERIOR_SAMPLES
    assert DEMO_SAMPLES == ProbeSettings().samples == POSTERIOR_SAMPLES
    assert command.build_parser().parse_args(["--dataset-dir", "d"]).samples == POSTERIOR_SAMPLES
    with pytest.raises(SystemExit):
        build_parser().parse_args(["demo", "--help"])
    assert f"--samples defaults to {POSTERIOR_SAMPLES}" in " ".join(capsys.readouterr().out.split())
    # the shipped sidecar was fitted with that count: tests/uncertainty/test_calibration.py ties it to num_samples
