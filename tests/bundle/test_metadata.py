"""bundle/configs/metadata.json: valid against the model-zoo schema (offline) and true to the network it describes."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import pytest
from monai.bundle import verify_metadata

import monai_probreg
from monai_probreg import ProbRegNet

ROOT = Path(__file__).resolve().parents[2]
META = ROOT / "bundle" / "configs" / "metadata.json"
# kept next to the checkout (never copied into it); MONAI would otherwise download it from the "schema" URL
SCHEMA = ROOT.parent / "shared" / "monai" / "meta_schema_20240725.json"
needs_schema = pytest.mark.skipif(
    not SCHEMA.is_file(), reason=f"offline metadata schema not found at {SCHEMA} (it is never downloaded in tests)"
)


@pytest.fixture(scope="module")
def metadata() -> dict:
    return json.loads(META.read_text())


@needs_schema
def test_metadata_verifies_against_the_schema():
    verify_metadata(meta_file=str(META), filepath=str(SCHEMA))  # raises ValueError on any violation


@needs_schema
def test_schema_check_is_not_vacuous(tmp_path, metadata):
    broken = json.loads(json.dumps(metadata))
    broken["network_data_format"]["inputs"]["image"]["num_channels"] = "two"
    path = tmp_path / "metadata.json"
    path.write_text(json.dumps(broken))
    with pytest.raises(ValueError, match="Failed validating"):
        verify_metadata(meta_file=str(path), filepath=str(SCHEMA))


def test_input_channels_are_moving_then_fixed(metadata):
    image = metadata["network_data_format"]["inputs"]["image"]
    assert image["num_channels"] == 2
    assert image["channel_def"] == {"0": "moving", "1": "fixed"}
    # ... which is the order ProbRegNet takes them (and concatenates them) in
    assert list(inspect.signature(ProbRegNet.forward).parameters)[1:3] == ["moving", "fixed"]


def test_prediction_is_a_displacement_with_one_channel_per_axis(metadata):
    outputs = metadata["network_data_format"]["outputs"]
    image = metadata["network_data_format"]["inputs"]["image"]
    assert outputs["pred"]["num_channels"] == len(image["spatial_shape"]) == 3
    assert outputs["pred"]["spatial_shape"] == image["spatial_shape"]  # returned on the input grid


def test_package_version_matches_the_installed_package(metadata):
    assert metadata["required_packages_version"]["monai-probreg"] == monai_probreg.__version__
