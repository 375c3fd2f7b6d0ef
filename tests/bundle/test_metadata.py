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


def test_the_package_version_is_the_bundle_release(metadata):
    """One version: the package's (pyproject reads monai_probreg.__version__) is the bundle's release."""
    assert metadata["version"] == monai_probreg.__version__
    assert 'version = { attr = "monai_probreg.__version__" }' in (ROOT / "pyproject.toml").read_text()
    assert next(iter(metadata["changelog"])) == metadata["version"]  # the newest release has its changelog line


# --- large_files.yml: the model zoo's list of the shipped weights -----------------------------------------------------
BUNDLE = ROOT / "bundle"


def _large_files() -> list[dict]:
    from monai.bundle import ConfigParser

    parser = ConfigParser()
    parser.read_config(str(BUNDLE / "large_files.yml"))  # as the zoo's CI reads it
    return parser.get()["large_files"]


def test_large_files_lists_exactly_the_shipped_weights_and_their_hashes():
    from monai.apps.utils import check_hash

    entries = _large_files()
    shipped = sorted(str(p.relative_to(BUNDLE)) for p in (BUNDLE / "models").iterdir() if p.suffix in (".pt", ".ts"))
    assert sorted(e["path"] for e in entries) == shipped == ["models/model.pt", "models/model.ts"]
    for entry in entries:
        assert set(entry) == {"path", "url", "hash_val", "hash_type"} and entry["hash_type"] == "sha256"
        assert check_hash(BUNDLE / entry["path"], entry["hash_val"], entry["hash_type"]), entry["path"]


def test_large_files_pass_the_zoos_download_step_without_a_download(tmp_path):
    """The zoo's CI hands each entry to download_url: a file in place with its hash is kept (the empty url is never
    used); a changed one is refused."""
    from monai.apps.utils import HashCheckError, download_url

    for entry in _large_files():
        download_url(
            url=entry["url"], filepath=BUNDLE / entry["path"], hash_val=entry["hash_val"], hash_type=entry["hash_type"]
        )
    changed = tmp_path / "model.pt"
    changed.write_bytes((BUNDLE / "models" / "model.pt").read_bytes() + b"\0")
    entry = _large_files()[0]
    with pytest.raises(HashCheckError):
        download_url(url=entry["url"], filepath=changed, hash_val=entry["hash_val"], hash_type=entry["hash_type"])


@pytest.mark.parametrize("config", ["inference.yaml", "evaluate.yaml"])
def test_the_configs_default_weights_are_the_zoos_models_model_pt(config):
    from monai_probreg.fitting.stages import bundle_parser

    parser = bundle_parser(BUNDLE, [config])
    assert Path(parser.get_parsed_content("model_file")) == BUNDLE / "models" / "model.pt"


def test_the_shipped_torchscript_is_the_export_of_the_shipped_weights():
    import torch

    weights = torch.load(BUNDLE / "models" / "model.pt", weights_only=True)
    exported = torch.jit.load(str(BUNDLE / "models" / "model.ts"), map_location="cpu").state_dict()
    assert all(torch.equal(exported["network." + key], value) for key, value in weights.items())
