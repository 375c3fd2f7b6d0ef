"""The MONAI model zoo's checks on the bundle, run as the zoo runs them (``monai.bundle`` functions), offline:
``verify_metadata`` against the local schema, ``verify_net_in_out`` and ``ckpt_export`` on ``zoo_network_def``
(:class:`~monai_probreg.networks.pair_input.PairInputNet`). Every check runs on a temporary copy of
``bundle/configs``; where ``inference.yaml`` has no ``zoo_network_def`` yet, a small extra config adds it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
import yaml
from monai.bundle import ckpt_export, verify_metadata, verify_net_in_out

from monai_probreg import ProbRegNet
from monai_probreg.networks.pair_input import PairInputNet

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "bundle" / "configs"
# kept next to the checkout (never copied into it; /work/shared/monai/README.md); MONAI would download it otherwise
SCHEMA = ROOT.parent / "shared" / "monai" / "meta_schema_20240725.json"
needs_schema = pytest.mark.skipif(
    not SCHEMA.is_file(), reason=f"offline metadata schema not found at {SCHEMA} (it is never downloaded in tests)"
)
ZOO_KEY = "zoo_network_def"
# the zoo's entry, as it is (to be) written in inference.yaml: network_def's settings, PairInputNet's call
ZOO_ENTRY = {
    "_target_": "monai_probreg.networks.pair_input.PairInputNet",
    "spatial_dims": 3,
    "enc_channels": "@enc_channels",
    "dec_channels": "@dec_channels",
    "int_downsize": "@int_downsize",
    "num_steps": "@num_steps",
    "network_size": "@network_size",
    "unet_precision": "@unet_precision",
    "channels_last": "@channels_last",
    "fast_sampling": "@fast_sampling",
}
SMALL = {
    "network_size": [16, 16, 16],
    "enc_channels": [4, 8, 8, 8],
    "dec_channels": [8, 8, 8, 8, 4],
    "unet_precision": "fp32",
    "channels_last": False,
}


@pytest.fixture()
def bundle_configs(tmp_path) -> dict[str, str]:
    """Paths of the copied ``metadata.json`` and the config list that defines ``zoo_network_def``."""
    configs = tmp_path / "configs"
    shutil.copytree(CONFIGS, configs)
    config_files = [str(configs / "inference.yaml")]
    if ZOO_KEY not in yaml.safe_load((configs / "inference.yaml").read_text()):
        (configs / "zoo.yaml").write_text(yaml.safe_dump({ZOO_KEY: ZOO_ENTRY}))
        config_files.append(str(configs / "zoo.yaml"))
    return {"meta_file": str(configs / "metadata.json"), "config_file": config_files}


@needs_schema
def test_verify_metadata_offline(bundle_configs):
    verify_metadata(meta_file=bundle_configs["meta_file"], filepath=str(SCHEMA))  # raises on any violation


def test_verify_net_in_out_on_the_zoo_entry(bundle_configs):
    # the zoo's call: net(torch.rand(1, 2, 16, 16, 16)) -> output.shape[1] == pred's 3 channels, float32
    verify_net_in_out(net_id=ZOO_KEY, device="cpu", n=1, **bundle_configs, **SMALL)


def test_verify_net_in_out_catches_a_wrong_channel_count(bundle_configs):
    with pytest.raises(ValueError, match="output channel number"):
        verify_net_in_out(
            net_id=ZOO_KEY,
            device="cpu",
            n=1,
            **bundle_configs,
            **SMALL,
            **{"_meta_#network_data_format#outputs#pred#num_channels": 2},
        )


def test_pair_input_net_is_probreg_net_displacement():
    torch.manual_seed(0)
    net = PairInputNet(
        enc_channels=(4, 8),
        dec_channels=(8, 8, 4),
        network_size=(16, 16, 16),
        unet_precision="fp32",
        channels_last=False,
    ).eval()
    plain = ProbRegNet(
        enc_channels=(4, 8),
        dec_channels=(8, 8, 4),
        network_size=(16, 16, 16),
        unet_precision="fp32",
        channels_last=False,
    ).eval()
    plain.load_state_dict(net.state_dict())  # same parameters, same keys
    for p in net.parameters():
        p.data.normal_(0.0, 0.2)
    plain.load_state_dict(net.state_dict())
    image = torch.rand(1, 2, 24, 20, 16)
    with torch.no_grad():
        torch.testing.assert_close(net(image), plain(image[:, :1], image[:, 1:]).displacement, rtol=0, atol=0)
    with pytest.raises(ValueError, match="moving and fixed on the channel axis"):
        net(torch.rand(1, 3, 16, 16, 16))


def test_ckpt_export_scripts_the_zoo_entry(bundle_configs, tmp_path):
    from monai.bundle import ConfigParser

    parser = ConfigParser()
    parser.read_config(bundle_configs["config_file"])
    parser.update(SMALL)
    torch.manual_seed(0)
    weights = parser.get_parsed_content("network_def")  # the workflows' ProbRegNet: its state_dict is model.pt's
    assert type(weights) is ProbRegNet
    for p in weights.parameters():
        p.data.normal_(0.0, 0.2)  # random weights, far from the near-zero initial velocity
    ckpt = tmp_path / "model.pt"
    torch.save(weights.state_dict(), ckpt)
    out = tmp_path / "model.ts"

    ckpt_export(net_id=ZOO_KEY, filepath=str(out), ckpt_file=str(ckpt), **bundle_configs, **SMALL)

    scripted = torch.jit.load(str(out))
    eager = parser.get_parsed_content(ZOO_KEY, instantiate=True)
    eager.load_state_dict(torch.load(ckpt, weights_only=True))
    eager.eval()
    image = torch.rand(1, 2, 32, 16, 16)  # not the network grid: resized in and out
    with torch.no_grad():
        expected = eager(image)
        actual = scripted(image)
    assert expected.shape == (1, 3, 32, 16, 16)
    assert expected.abs().max() > 0.1  # a real displacement, not the initial zero
    torch.testing.assert_close(actual, expected, rtol=0, atol=1e-5)
