"""monai_probreg.weights.averaging: the mean of checkpoints' weights, with the checks a user needs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from monai_probreg import ProbRegNet
from monai_probreg.utils.errors import InputError, UntrustedFileError
from monai_probreg.weights.averaging import average_state_dicts, average_weight_files, main, read_model_state
from monai_probreg.weights.loading import load_weights
from monai_probreg.weights.settings import settings_path, write_network_settings

SMALL = {"enc_channels": (4, 8), "dec_channels": (8, 8, 4), "network_size": (16, 16, 16)}


def _net(seed: int, **kwargs) -> ProbRegNet:
    torch.manual_seed(seed)
    return ProbRegNet(**{**SMALL, **kwargs})


def _save(tmp_path: Path, name: str, net: ProbRegNet, training_state: bool = False) -> Path:
    path = tmp_path / name
    state = net.state_dict()
    torch.save({"model": state, "optimizer": {"lr": 1e-4}} if training_state else state, path)
    return path


def test_average_is_the_elementwise_mean():
    a, b, c = (_net(s).state_dict() for s in (0, 1, 2))
    averaged = average_state_dicts([a, b, c])
    for key, tensor in a.items():
        assert torch.allclose(averaged[key], (tensor + b[key] + c[key]) / 3, atol=1e-7)
        assert averaged[key].dtype == tensor.dtype


def test_average_of_copies_is_the_same_weights():
    state = _net(0).state_dict()
    averaged = average_state_dicts([state, {k: v.clone() for k, v in state.items()}])
    assert all(torch.equal(averaged[k], v) for k, v in state.items())


def test_training_states_and_plain_weights_read_alike(tmp_path):
    net = _net(0)
    plain, training = _save(tmp_path, "a.pt", net), _save(tmp_path, "b.pt", net, training_state=True)
    assert read_model_state(plain).keys() == read_model_state(training).keys()
    assert all(torch.equal(read_model_state(plain)[k], v) for k, v in read_model_state(training).items())


def test_files_are_averaged_atomically_with_their_network_settings(tmp_path):
    nets = [_net(s) for s in (0, 1)]
    inputs = [_save(tmp_path, f"w{i}.pt", n, training_state=i == 1) for i, n in enumerate(nets)]
    write_network_settings(inputs[0], nets[0])
    out = average_weight_files(inputs, tmp_path / "out" / "mean.pt")
    assert settings_path(out).read_text() == settings_path(inputs[0]).read_text()
    assert sorted(p.name for p in out.parent.iterdir()) == ["mean.network.json", "mean.pt"]  # no temporaries left
    loaded = load_weights(_net(5), out)  # strict load, settings checked
    expected = average_state_dicts([n.state_dict() for n in nets])
    assert all(torch.allclose(loaded.state_dict()[k], v) for k, v in expected.items())


def test_inputs_of_another_network_are_refused_by_name(tmp_path):
    a = _save(tmp_path, "a.pt", _net(0))
    b = _save(tmp_path, "wide.pt", _net(0, enc_channels=(4, 16)))
    with pytest.raises(InputError, match=r"wide\.pt.*shape"):
        average_weight_files([a, b], tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()


def test_inputs_with_other_keys_are_refused(tmp_path):
    state = _net(0).state_dict()
    extra = {**state, "extra.weight": torch.zeros(1)}
    with pytest.raises(InputError, match="keys only in second"):
        average_state_dicts([state, extra], ["first", "second"])


def test_integer_buffers_must_agree():
    state = {"w": torch.ones(2), "count": torch.tensor(3)}
    assert average_state_dicts([state, {**state, "w": torch.zeros(2)}])["count"] == 3
    with pytest.raises(InputError, match="count"):
        average_state_dicts([state, {**state, "count": torch.tensor(4)}])


def test_one_input_is_not_an_average():
    with pytest.raises(InputError, match="at least 2"):
        average_state_dicts([_net(0).state_dict()])


def test_disagreeing_network_settings_are_refused(tmp_path):
    nets = [_net(0), _net(1, num_steps=5)]
    inputs = [_save(tmp_path, f"w{i}.pt", n) for i, n in enumerate(nets)]
    for path, net in zip(inputs, nets):
        write_network_settings(path, net)
    with pytest.raises(InputError, match="different network settings"):
        average_weight_files(inputs, tmp_path / "out.pt")


class _Payload:
    """Unpickling this would run ``os.system('touch <marker>')``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def test_a_pickle_that_runs_code_is_refused(tmp_path):
    good = _save(tmp_path, "a.pt", _net(0))
    evil, marker = tmp_path / "evil.pt", tmp_path / "code_ran"
    torch.save({"model": _net(1).state_dict(), "hook": _Payload(marker)}, evil)
    with pytest.raises(UntrustedFileError, match="evil.pt"):
        average_weight_files([good, evil], tmp_path / "out.pt")
    assert not marker.exists() and not (tmp_path / "out.pt").exists()


def test_command_line_reports_errors_in_one_line(tmp_path, capsys):
    good = _save(tmp_path, "a.pt", _net(0))
    assert main([str(good), str(tmp_path / "missing.pt"), "--out", str(tmp_path / "o.pt")]) == 2
    assert "missing.pt" in capsys.readouterr().err
    assert main([str(good), str(_save(tmp_path, "b.pt", _net(1))), "--out", str(tmp_path / "o.pt")]) == 0
    assert (tmp_path / "o.pt").is_file()
