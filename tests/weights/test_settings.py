"""monai_probreg.weights.settings: weights carry their network settings; a network that differs is refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from monai_probreg import ProbRegNet
from monai_probreg.fitting.stages import bundle_parser
from monai_probreg.utils.errors import InputError
from monai_probreg.weights.loading import load_weights
from monai_probreg.weights.settings import (
    NetworkSettingsWriter,
    check_network_settings,
    network_settings,
    settings_path,
    write_network_settings,
)

ROOT = Path(__file__).resolve().parents[2]
SMALL = {"enc_channels": (4, 8), "dec_channels": (8, 8, 4), "network_size": (16, 16, 16)}


def _saved(tmp_path: Path, **kwargs) -> tuple[Path, ProbRegNet]:
    net = ProbRegNet(**{**SMALL, **kwargs})
    path = tmp_path / "weights.pt"
    torch.save(net.state_dict(), path)
    write_network_settings(path, net)
    return path, net


def test_the_json_sits_next_to_the_weights_and_records_the_settings(tmp_path):
    path, net = _saved(tmp_path, num_steps=5)
    assert settings_path(path) == tmp_path / "weights.network.json"
    recorded = json.loads(settings_path(path).read_text())
    assert recorded == {
        "spatial_dims": 3,
        "enc_channels": [4, 8],
        "dec_channels": [8, 8, 4],
        "int_downsize": 2,
        "num_steps": 5,
        "bidirectional": False,
        "network_size": [16, 16, 16],
    }
    assert check_network_settings(path, ProbRegNet(**SMALL, num_steps=5)) == recorded


@pytest.mark.parametrize(
    "change, named",
    [
        ({"network_size": (32, 32, 32)}, "network_size: trained with [16, 16, 16], the network has [32, 32, 32]"),
        ({"network_size": None}, "network_size: trained with [16, 16, 16], the network has None"),
        ({"num_steps": 4}, "num_steps: trained with 7, the network has 4"),
        ({"bidirectional": True}, "bidirectional: trained with False, the network has True"),
    ],
)
def test_a_setting_that_leaves_no_trace_in_the_tensors_is_refused_by_name(tmp_path, change, named):
    path, _ = _saved(tmp_path)
    other = ProbRegNet(**{**SMALL, **change})
    other.load_state_dict(torch.load(path, weights_only=True))  # the tensors alone would load silently
    with pytest.raises(InputError, match="weights.pt.*does not fit this network") as err:
        load_weights(other, path)
    assert named in str(err.value)


def test_speed_levers_are_not_settings(tmp_path):
    path, _ = _saved(tmp_path)
    load_weights(ProbRegNet(**SMALL, unet_precision="fp32", channels_last=False, fast_sampling=False), path)


def test_weights_without_the_json_load_as_before(tmp_path):
    net = ProbRegNet(**SMALL)
    torch.save(net.state_dict(), tmp_path / "elsewhere.pt")
    assert check_network_settings(tmp_path / "elsewhere.pt", ProbRegNet(**SMALL)) is None
    load_weights(ProbRegNet(**SMALL), tmp_path / "elsewhere.pt")


@pytest.mark.parametrize("text", ["{not json", "[1, 2]"])
def test_an_unreadable_json_is_an_input_error_naming_it(tmp_path, text):
    path, net = _saved(tmp_path)
    settings_path(path).write_text(text)
    with pytest.raises(InputError, match="weights.network.json"):
        load_weights(net, path)


def test_the_writer_waits_for_the_weights_and_then_writes(tmp_path):
    net = ProbRegNet(**SMALL)
    writer = NetworkSettingsWriter(tmp_path / "model.pt", net)
    writer()
    assert not settings_path(tmp_path / "model.pt").exists()  # no weights yet: nothing to describe
    torch.save(net.state_dict(), tmp_path / "model.pt")
    writer()
    assert json.loads(settings_path(tmp_path / "model.pt").read_text()) == network_settings(net)


@pytest.mark.parametrize("config", ["inference.yaml", "evaluate.yaml"])
@pytest.mark.parametrize("weights", sorted(p.name for p in (ROOT / "bundle" / "models").glob("*.pt")))
def test_the_shipped_weights_carry_settings_that_fit_the_configs(config, weights):
    parser = bundle_parser(ROOT / "bundle", [config])
    path = ROOT / "bundle" / "models" / weights
    assert settings_path(path).is_file()
    assert check_network_settings(path, parser.get_parsed_content("network_def")) is not None
