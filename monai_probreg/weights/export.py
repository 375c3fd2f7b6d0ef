"""Export a trained :class:`~monai_probreg.ProbRegNet` as a TorchScript file for deployment (``models/model.ts``).

The exported file is a ``torch.jit.trace`` of :class:`MeanRegistration`, the eval-mode (posterior-mean, so
deterministic) registration with a plain tuple output. Its contract, also stored in the file (see below):

- inputs: ``forward(moving, fixed)``, each **exactly** ``(1, 1, *input_size)`` float32 on the device the model
  was exported on. The shape is fixed by tracing; anything else is refused by a scripted check that is part of
  the traced graph (``torch.jit.Error`` naming the expected and the received shape, dtype or device).
- outputs, in this order (:data:`EXPORT_OUTPUTS`): ``warped`` (1, 1, *S), ``displacement`` (1, D, *S) in voxels of
  the input grid, ``velocity_mean`` and ``velocity_log_var`` (1, D, *V) on the velocity grid, in velocity-grid
  voxels (``log_var`` is log sigma^2). ``V = network_size (or S) / int_downsize``.
- conventions (the package's, ``monai_probreg/__init__.py``): channel k of a field is the component along tensor
  axis 2 + k (no xyz flip); warping pulls back, ``warped[x] = moving[x + displacement[x]]``, linear, voxel
  centres at integer indices (``align_corners=True``); the moving image is resampled into the fixed grid.

Why a wrapper: ``ProbRegNet.forward`` returns a :class:`~monai_probreg.RegistrationOutput` whose
``inverse_displacement`` and ``warped_fixed`` are ``None`` unless ``bidirectional``; a traced function must return
tensors (or tuples of them), so the wrapper returns the four tensors above as a tuple.

Why tracing is safe at a fixed shape, and only there: the only Python-side logic on the traced path is shape
logic (input checks, ``network_size`` resizing, ``resize_displacement``'s "same size?" branch and its
align-corners scale factors, MONAI ``Warp``'s grid normalisation by ``size - 1``, ``CachedWarp``'s grid cache
keyed on the shape). None of it depends on voxel values, so one trace is valid for every input of the traced
shape; :func:`export_torchscript` checks that on an input different from the tracing one. At another shape the
recorded sizes would be wrong: without the input check a raw trace silently returns outputs at the traced size
(e.g. a 48^3 pair into a 32^3 trace gives a 32^3 "displacement"), which is why the check exists.
Before tracing, the identity-grid caches are emptied so the grids are built inside the graph (``arange``) instead
of being stored in the file as constants (60 MB for a 160 x 192 x 160 grid).

Device: tracing records the device of the grids it builds, so the file runs on the device it was exported on
(``--device``); to deploy on GPU, export on GPU. float32 only: the eager model's inference speed levers (bf16
UNet, channels-last, threaded sampling; :class:`~monai_probreg.ProbRegNet`) are switched off in the traced copy.

The file carries ``metadata.json`` as a TorchScript extra file (input shape, output names and shapes, units,
channel order, pull-back convention, network settings, the verification result); read it with
:func:`read_export_metadata` (without loading the model) or ``torch.jit.load(path, _extra_files=...)``. The
traced module also has a buffer ``input_shape`` (int64, ``[1, 1, *input_size]``).

Command line (builds the network from a bundle config's ``network_def``, loads a ``state_dict``, exports)::

    python -m monai_probreg.weights.export --model-file bundle/models/model.pt --config bundle/configs/inference.yaml \\
        --out bundle/models/model.ts --input-size 160 192 160

The MONAI model zoo's own export, ``python -m monai.bundle ckpt_export --net_id zoo_network_def``, is the other
route: ``torch.jit.script`` (not a trace) of :class:`~monai_probreg.networks.pair_input.PairInputNet`, any input
size, one 2-channel input (moving, fixed) and the displacement alone as output (float32, the plain UNet path, the
one-pass sampling grid; ``tests/bundle/test_bundle_checks.py``). This module's file is the deployment one: all four
outputs, and its contract stored in the file.

ONNX is not exported: ``torch.onnx`` needs the ``onnx``/``onnxscript`` packages, which are not dependencies.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import json
import os
import warnings
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

import monai_probreg
from monai_probreg.blocks import warp as _warp
from monai_probreg.networks.probreg_net import ProbRegNet
from monai_probreg.utils.files import atomic_write
from monai_probreg.weights.loading import load_weights

__all__ = [
    "EXPORT_OUTPUTS",
    "METADATA_FILE",
    "VERIFY_RTOL",
    "VERIFY_ATOL",
    "MeanRegistration",
    "export_torchscript",
    "read_export_metadata",
    "main",
]

EXPORT_OUTPUTS = ("warped", "displacement", "velocity_mean", "velocity_log_var")
METADATA_FILE = "metadata.json"
# Eager vs traced: the same float32 kernels, yet not bit-identical after the warps (observed at 32^3: warped
# ~1.5e-6, displacement ~1e-8 voxels, velocities identical; at 160x192x160 with the shipped weights: warped 1.4e-5 at
# 12 of 4.9M voxels, where a sampling coordinate a few ulps off lands on a steep intensity edge). 1e-4 (absolute:
# intensities in [0, 1], voxels; relative: large displacements) is far below anything visible; a trace that baked
# in a wrong shape or value is off by O(1).
VERIFY_RTOL = 1e-4
VERIFY_ATOL = 1e-4


def _check_input(x: Tensor, name: str, shape: list[int], device_type: str) -> Tensor:
    """Runtime guard compiled with ``torch.jit.script``, so it survives tracing (a Python ``assert`` or ``if``
    would be evaluated once at trace time and dropped)."""
    if x.shape != shape:
        raise ValueError(
            name + " must have shape " + str(shape) + " (fixed when the model was traced); got " + str(x.shape)
        )
    if x.dtype != torch.float32:
        raise TypeError(name + " must be float32")
    if x.device.type != device_type:
        raise ValueError(
            name + " must be on " + device_type + " (the device the model was traced on); got " + x.device.type
        )
    return x


@contextlib.contextmanager
def _quiet_jit() -> Iterator[None]:
    """Silence the warnings torch.jit emits on a path we have checked: torch 2.13 marks every ``torch.jit`` entry
    point as deprecated (TorchScript is still what MONAI bundles ship), and each TracerWarning on this path is a
    shape comparison or a size turned into an int (module docstring)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings(
            "ignore", message=r"`torch\.jit\.\w+` is (deprecated|not supported)", category=DeprecationWarning
        )
        yield


@functools.lru_cache(maxsize=1)
def _scripted_check() -> Callable[[Tensor, str, list[int], str], Tensor]:
    with _quiet_jit():
        return torch.jit.script(_check_input)


class MeanRegistration(nn.Module):
    """Eval-mode registration with a traceable output: ``forward(moving, fixed)`` -> the tuple
    ``(warped, displacement, velocity_mean, velocity_log_var)`` (see the module docstring for shapes and units).

    Args:
        network: the model; put it in eval mode yourself (``export_torchscript`` does) so the velocity is the
            posterior mean rather than a sample.
        input_shape: the full input shape ``(1, 1, *S)`` that ``forward`` accepts; enforced by a scripted check.
        device_type: device type the inputs must be on (``"cpu"``, ``"cuda"``).
    """

    def __init__(self, network: ProbRegNet, input_shape: Sequence[int], device_type: str = "cpu") -> None:
        super().__init__()
        self.network = network
        self.shape = [int(n) for n in input_shape]
        self.device_type = device_type
        self.register_buffer("input_shape", torch.tensor(self.shape, dtype=torch.int64))
        self._check = _scripted_check()

    def forward(self, moving: Tensor, fixed: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        moving = self._check(moving, "moving", self.shape, self.device_type)
        fixed = self._check(fixed, "fixed", self.shape, self.device_type)
        out = self.network(moving, fixed)
        return out.warped, out.displacement, out.velocity_mean, out.velocity_log_var


def _clear_grid_caches(network: nn.Module) -> None:
    """Empty the identity-grid caches the traced path uses (the network's own and the shared ``warp_image`` ones),
    so tracing records how to build the grids rather than storing them as constants."""
    for layer in [*network.modules(), *_warp._WARPS.values()]:
        if isinstance(layer, _warp.CachedWarp):
            layer.ref_grid = None
            layer._grid_key = None


def _random_pair(shape: Sequence[int], device: torch.device, seed: int) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    pair = torch.rand(2, *shape, generator=g)  # images live in [0, 1]
    return pair[0].to(device), pair[1].to(device)


def _metadata(
    network: ProbRegNet,
    input_shape: list[int],
    outputs: Sequence[Tensor],
    device: torch.device,
    max_abs_diff: dict[str, float],
) -> dict[str, Any]:
    d = network.spatial_dims
    return {
        "format": "TorchScript (torch.jit.trace) of monai_probreg.weights.export.MeanRegistration, eval mode",
        "monai_probreg_version": monai_probreg.__version__,
        "torch_version": torch.__version__,
        "input_shape": input_shape,
        "input_dtype": "float32",
        "device": str(device),
        "inputs": ["moving", "fixed"],
        "outputs": {name: list(t.shape) for name, t in zip(EXPORT_OUTPUTS, outputs)},
        "units": "voxels",
        "displacement": "in voxels of the input grid; channel k is the component along tensor axis 2 + k "
        f"(array axis k of the {d}-d image, no xyz flip)",
        "velocity": "posterior mean and log-variance (log sigma^2) on the velocity grid, in velocity-grid voxels; "
        "channel k along tensor axis 2 + k",
        "convention": "pull back: warped[x] = moving[x + displacement[x]], linear interpolation, voxel centres at "
        "integer indices (align_corners=True); the moving image is resampled into the fixed grid",
        "velocity_used": "posterior mean (eval mode, deterministic)",
        "network": {
            "spatial_dims": d,
            "network_size": list(network.network_size) if network.network_size is not None else None,
            "int_downsize": network.unet.int_downsize,
            "num_steps": network.integrate.num_steps,
            "padding_mode": network.padding_mode,
        },
        "verification": {"rtol": VERIFY_RTOL, "atol": VERIFY_ATOL, "max_abs_diff": max_abs_diff},
    }


def export_torchscript(network: ProbRegNet, input_size: Sequence[int], path: str | os.PathLike) -> Path:
    """Trace ``network``'s eval-mode registration at input shape ``(1, 1, *input_size)`` and write it to ``path``.

    Steps: a frozen copy of ``network`` (eval mode, ``requires_grad=False``; ``network`` itself is not modified) is
    wrapped in :class:`MeanRegistration` and traced on its device on one random pair; the trace is run on a
    second random pair and compared with the eager copy (``torch.testing.assert_close``, :data:`VERIFY_RTOL`,
    :data:`VERIFY_ATOL`); the file is saved with ``metadata.json`` under a temporary name next to ``path``,
    loaded back and renamed onto ``path`` (``os.replace``), so ``path`` is either the old file or a verified one.

    Raises:
        ValueError: ``input_size`` does not have ``network.spatial_dims`` entries (or the network rejects it).
        RuntimeError: the traced model does not reproduce the eager one (nothing is written).
    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    size = [int(n) for n in input_size]
    if len(size) != network.spatial_dims or min(size) < 1:
        raise ValueError(f"input_size must be {network.spatial_dims} positive sizes; got {list(input_size)}")
    input_shape = [1, 1, *size]
    net = copy.deepcopy(network).eval().requires_grad_(False)
    # the portable float32 path: no bf16 autocast or channels-last UNet (CPU-specific), MONAI's Warp (the threaded
    # grid_sample would bake this machine's thread count into the graph)
    net.unet_precision, net.channels_last, net.fast_sampling = "fp32", False, False
    device = next(net.parameters()).device
    wrapper = MeanRegistration(net, input_shape, device.type).to(device)
    trace_pair, check_pair = _random_pair(input_shape, device, 0), _random_pair(input_shape, device, 1)
    with torch.no_grad():
        expected = wrapper(*check_pair)
        _clear_grid_caches(net)
        with _quiet_jit():
            traced = torch.jit.trace(wrapper, trace_pair, check_trace=False)
        _clear_grid_caches(net)
        actual = traced(*check_pair)
    max_abs_diff = {
        name: float((a - e).abs().max()) if a.shape == e.shape else float("inf")
        for name, a, e in zip(EXPORT_OUTPUTS, actual, expected)
    }
    try:
        for name, a, e in zip(EXPORT_OUTPUTS, actual, expected):
            torch.testing.assert_close(a, e, rtol=VERIFY_RTOL, atol=VERIFY_ATOL, msg=lambda m, n=name: f"{n}: {m}")
    except AssertionError as err:
        raise RuntimeError(
            f"the traced model does not reproduce the eager one on a random input of shape "
            f"{input_shape} (rtol {VERIFY_RTOL}, atol {VERIFY_ATOL}); not written to {str(path)!r}. "
            f"{err}"
        ) from err
    meta = json.dumps(_metadata(net, input_shape, expected, device, max_abs_diff), indent=2)

    def write(tmp: str) -> None:
        with _quiet_jit():
            torch.jit.save(traced, tmp, _extra_files={METADATA_FILE: meta})
            torch.jit.load(tmp, map_location=device)  # the file loads before it replaces anything

    return atomic_write(Path(path), write)


def read_export_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The ``metadata.json`` of an exported file, read from the archive without loading the model."""
    with zipfile.ZipFile(path) as archive:
        names = [n for n in archive.namelist() if n.endswith(f"/extra/{METADATA_FILE}")]
        if not names:
            raise ValueError(
                f"{str(path)!r} has no extra/{METADATA_FILE}; not written by monai_probreg.weights.export?"
            )
        return json.loads(archive.read(names[0]))


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: build the network from a bundle config's ``network_def``, load weights, export."""
    parser = argparse.ArgumentParser(prog="python -m monai_probreg.weights.export", description=main.__doc__)
    parser.add_argument("--model-file", required=True, help="ProbRegNet state_dict (bundle models/model.pt)")
    parser.add_argument(
        "--config", required=True, help="bundle config with a network_def matching the weights (configs/inference.yaml)"
    )
    parser.add_argument("--out", required=True, help="TorchScript file to write (bundle models/model.ts)")
    parser.add_argument(
        "--input-size",
        required=True,
        type=int,
        nargs="+",
        metavar="N",
        help="spatial size the model will accept, e.g. 160 192 160 (input shape (1, 1, *N))",
    )
    parser.add_argument("--device", default="cpu", help="device to trace on, and the only one the file runs on")
    args = parser.parse_args(argv)

    from monai.bundle import ConfigParser

    config = ConfigParser()
    config.read_config(args.config)
    network = load_weights(config.get_parsed_content("network_def"), args.model_file, args.device)
    path = export_torchscript(network, args.input_size, args.out)
    meta = read_export_metadata(path)
    print(
        f"wrote {path}: input {meta['input_shape']} float32 on {meta['device']}, outputs "
        + ", ".join(f"{k} {v}" for k, v in meta["outputs"].items())
        + f"; max |traced - eager| {max(meta['verification']['max_abs_diff'].values()):.2e}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
