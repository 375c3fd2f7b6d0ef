"""monai_probreg.weights.export: the TorchScript file reproduces the eager eval-mode model at its fixed input shape, refuses
any other input, carries its contract as metadata, is written atomically; and the command line.

Tolerance for eager vs exported outputs: the export's own VERIFY_RTOL / VERIFY_ATOL (1e-4, reasoned in
monai_probreg/export.py): the traced graph runs the same float32 kernels; observed differences are ~1e-6 on
``warped`` and ~1e-8 voxels on ``displacement``, while a trace that baked in a wrong value or shape is off by O(1).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
import yaml
from monai.bundle import ConfigParser

from monai_probreg import ProbRegNet
from monai_probreg.engines.registration import register_pair
from monai_probreg.weights.export import (
    EXPORT_OUTPUTS,
    METADATA_FILE,
    VERIFY_ATOL,
    VERIFY_RTOL,
    MeanRegistration,
    _clear_grid_caches,
    export_torchscript,
    read_export_metadata,
)

ROOT = Path(__file__).resolve().parents[2]
SIZE = (32, 32, 32)
SHAPE = [1, 1, *SIZE]
NETWORK_SIZES = {"native-grid": None, "network_size-16": (16, 16, 16)}


pytestmark = pytest.mark.usefixtures("single_thread")


def _net(network_size, seed: int = 0) -> ProbRegNet:
    """Random weights, with a mean head strong enough for ~1 voxel displacements (the paper's init gives ~0)."""
    torch.manual_seed(seed)
    # float32 UNet: the export traces the float32 path, so the eager reference must not be the bf16 one (the default
    # on CPUs with native bf16); channels-last and fast sampling stay on, float32 rounding only
    net = ProbRegNet(network_size=network_size, unet_precision="fp32")
    with torch.no_grad():
        net.unet.mean_head.weight.normal_(0.0, 1.0)
    return net


def _pair(seed: int, shape=SHAPE, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=dtype), torch.rand(*shape, generator=g, dtype=dtype)


def _load(path: Path, extra: dict | None = None) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="`torch.jit.load` is deprecated", category=DeprecationWarning)
        return torch.jit.load(str(path), _extra_files=extra if extra is not None else {})


@pytest.fixture(scope="module", params=list(NETWORK_SIZES), ids=list(NETWORK_SIZES))
def exported(request, tmp_path_factory) -> tuple[ProbRegNet, Path]:
    """(the eager network, left in train mode, and its export at SIZE)."""
    torch.set_num_threads(1)
    net = _net(NETWORK_SIZES[request.param]).train()
    with torch.no_grad():
        net(*_pair(seed=5))  # warm the identity-grid caches: the export must not store them as constants
    path = export_torchscript(net, SIZE, tmp_path_factory.mktemp("export") / "model.ts")
    return net, path


def test_exported_model_matches_eager_eval_mode(exported):
    net, path = exported
    assert net.training, "export must not change the caller's network (it traces an eval-mode copy)"
    model = _load(path)
    moving, fixed = _pair(seed=7)  # neither of the two pairs the export traced / verified with
    with torch.no_grad():
        traced = model(moving, fixed)
    eager = register_pair(net, moving, fixed)  # eval mode: the posterior mean velocity
    assert eager.displacement.abs().max() > 0.5, "displacements too small for the comparison to mean anything"
    assert isinstance(traced, tuple) and len(traced) == len(EXPORT_OUTPUTS)
    for name, value in zip(EXPORT_OUTPUTS, traced):
        torch.testing.assert_close(value, getattr(eager, name), rtol=VERIFY_RTOL, atol=VERIFY_ATOL, msg=name)
    assert not any(p.requires_grad for p in model.parameters())
    assert "value=<Tensor>" not in str(model.inlined_graph), "identity grids stored as constants (caches not cleared)"


def test_metadata_states_the_fixed_shape_and_conventions(exported):
    net, path = exported
    extra = {METADATA_FILE: ""}
    model = _load(path, extra)
    meta = json.loads(extra[METADATA_FILE])
    assert meta == read_export_metadata(path)  # read from the zip without loading the model: same content
    assert meta["input_shape"] == SHAPE and meta["input_dtype"] == "float32" and meta["device"] == "cpu"
    assert meta["inputs"] == ["moving", "fixed"]
    velocity_grid = [n // 2 for n in (net.network_size or SIZE)]
    assert meta["outputs"] == {
        "warped": SHAPE,
        "displacement": [1, 3, *SIZE],
        "velocity_mean": [1, 3, *velocity_grid],
        "velocity_log_var": [1, 3, *velocity_grid],
    }
    assert list(meta["outputs"]) == list(EXPORT_OUTPUTS)  # the order of the returned tuple
    assert meta["units"] == "voxels" and "warped[x] = moving[x + displacement[x]]" in meta["convention"]
    assert meta["network"]["network_size"] == (list(net.network_size) if net.network_size else None)
    assert max(meta["verification"]["max_abs_diff"].values()) <= VERIFY_ATOL
    assert model.input_shape.tolist() == SHAPE  # also a buffer of the module


@pytest.mark.parametrize(
    "shape, dtype, message",
    [
        ((1, 1, 48, 48, 48), torch.float32, r"must have shape \[1, 1, 32, 32, 32\].*got \[1, 1, 48, 48, 48\]"),
        ((1, 1, 32, 32, 16), torch.float32, r"must have shape \[1, 1, 32, 32, 32\]"),
        ((2, 1, 32, 32, 32), torch.float32, r"must have shape \[1, 1, 32, 32, 32\]"),
        ((1, 2, 32, 32, 32), torch.float32, r"must have shape \[1, 1, 32, 32, 32\]"),
        ((1, 1, 32, 32, 32), torch.float64, "must be float32"),
    ],
)
def test_other_inputs_are_refused_not_silently_resampled(exported, shape, dtype, message):
    # A raw trace would accept e.g. a 48^3 pair and silently return 32^3 outputs (sizes recorded at trace time);
    # the scripted check inside the traced graph turns that into an error naming both shapes.
    model = _load(exported[1])
    moving, fixed = _pair(seed=3, shape=shape, dtype=dtype)
    with pytest.raises(torch.jit.Error, match=message), torch.no_grad():
        model(moving, fixed)


class _ValueBaked(ProbRegNet):
    """Reads a voxel value into Python: tracing freezes the tracing input's value into the graph (a trace bug)."""

    def forward(self, moving, fixed):
        out = super().forward(moving, fixed)
        return out._replace(warped=out.warped + float(moving[0, 0, 0, 0, 0]))


def _graph_signature(net: ProbRegNet, moving: torch.Tensor, fixed: torch.Tensor) -> list[str]:
    """The traced graph's nodes with value names, mangled type names and source locations stripped."""
    _clear_grid_caches(net)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        traced = torch.jit.trace(MeanRegistration(net.eval(), SHAPE), (moving, fixed), check_trace=False)
    _clear_grid_caches(net)
    return [
        re.sub(r"___torch_mangle_\d+\.", "", re.sub(r"%[\w.]+", "%", str(n))).split(" # ")[0]
        for n in traced.inlined_graph.nodes()
    ]


def test_trace_does_not_depend_on_the_tracing_input():
    # Two very different inputs must give the same graph, constants included: the Python-side logic on the traced
    # path (CachedWarp's grid cache, resize_displacement's size branch, Warp's normalisation) is shape-only.
    net = _net((16, 16, 16))
    random_pair, flat_pair = _pair(seed=0), (torch.zeros(*SHAPE), torch.ones(*SHAPE))
    signature = _graph_signature(net, *random_pair)
    assert signature == _graph_signature(net, *flat_pair)
    assert not any("value=<Tensor>" in node for node in signature), "identity grids must be built in the graph"
    baked = _ValueBaked(network_size=(16, 16, 16))  # the comparison can fail: a value read in Python shows up
    assert _graph_signature(baked, *random_pair) != _graph_signature(baked, *flat_pair)


def test_written_atomically_and_not_at_all_when_verification_fails(tmp_path):
    path = tmp_path / "model.ts"
    path.write_bytes(b"previous model")
    baked = _ValueBaked(network_size=(16, 16, 16))
    with pytest.raises(RuntimeError, match=r"does not reproduce the eager one.*not written"):
        export_torchscript(baked, SIZE, path)
    assert path.read_bytes() == b"previous model" and os.listdir(tmp_path) == ["model.ts"]
    export_torchscript(_net((16, 16, 16)), SIZE, path)
    assert os.listdir(tmp_path) == ["model.ts"]  # the temporary file was renamed, nothing left behind
    assert read_export_metadata(path)["input_shape"] == SHAPE


def test_input_size_is_checked(tmp_path):
    with pytest.raises(ValueError, match="input_size must be 3 positive sizes"):
        export_torchscript(_net(None), (32, 32), tmp_path / "model.ts")
    with pytest.raises(ValueError, match="multiple of 16"):  # the UNet's own check, before anything is written
        export_torchscript(_net(None), (32, 32, 40), tmp_path / "model.ts")
    assert os.listdir(tmp_path) == []


def test_bundle_export_config_on_top_of_inference(tmp_path):
    net = _net((16, 16, 16))
    torch.save(net.state_dict(), tmp_path / "model.pt")
    parser = ConfigParser()
    parser.read_config([str(ROOT / "bundle" / "configs" / name) for name in ("inference.yaml", "export.yaml")])
    parser.update(
        {
            "bundle_root": str(tmp_path),
            "model_file": str(tmp_path / "model.pt"),
            "device": "cpu",
            "network_size": [16, 16, 16],
            "input_size": list(SIZE),
        }
    )
    parser.get_parsed_content("run")
    out = tmp_path / "models" / "model.ts"
    assert read_export_metadata(out)["input_shape"] == SHAPE
    moving, fixed = _pair(seed=13)
    with torch.no_grad():
        displacement = _load(out)(moving, fixed)[1]
    torch.testing.assert_close(
        displacement, register_pair(net, moving, fixed).displacement, rtol=VERIFY_RTOL, atol=VERIFY_ATOL
    )


def test_command_line_exports_from_a_bundle_config(tmp_path):
    config = yaml.safe_load((ROOT / "bundle" / "configs" / "inference.yaml").read_text())
    config["network_size"] = [16, 16, 16]  # the shipped network block, at a grid small enough for a test
    (tmp_path / "inference.yaml").write_text(yaml.safe_dump(config))
    net = _net((16, 16, 16))
    torch.save(net.state_dict(), tmp_path / "model.pt")
    out = tmp_path / "models" / "model.ts"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "monai_probreg.weights.export",
            "--model-file",
            str(tmp_path / "model.pt"),
            "--config",
            str(tmp_path / "inference.yaml"),
            "--out",
            str(out),
            "--input-size",
            *map(str, SIZE),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert result.returncode == 0, result.stderr
    assert f"wrote {out}" in result.stdout and "[1, 1, 32, 32, 32]" in result.stdout
    assert read_export_metadata(out)["network"]["network_size"] == [16, 16, 16]
    moving, fixed = _pair(seed=11)
    with torch.no_grad():
        warped, displacement, _, _ = _load(out)(moving, fixed)
    eager = register_pair(net, moving, fixed)
    torch.testing.assert_close(displacement, eager.displacement, rtol=VERIFY_RTOL, atol=VERIFY_ATOL)
    torch.testing.assert_close(warped, eager.warped, rtol=VERIFY_RTOL, atol=VERIFY_ATOL)
