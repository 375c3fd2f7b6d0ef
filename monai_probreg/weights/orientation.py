"""Convert trained weights to a mirrored view of the world: the network that sees every input flipped along some
array axes.

Why: weights trained on images whose header was wrong by a flip (or a 180-degree turn, which is two flips) learnt
anatomy mirrored along those axes. For a UNet of convolutions, mirroring the world along axis ``a`` is the same as
mirroring every kernel along ``a`` and negating the velocity component along ``a`` (a displacement towards higher
indices becomes one towards lower indices); log-variances are even and only their kernels flip. With ``M`` that
mirroring, the converted network ``f'`` satisfies ``f'(M x) = M f(x)`` for every stride-1 layer exactly; stride-2
convolutions on even sizes sample the mirrored grid one voxel off (and no shift repairs it: nearest upsampling
would then be off instead), so the whole UNet is equivariant only approximately: a warm start, to be fine-tuned.
``tests/weights/test_orientation.py`` pins both on a small random network. A trained
network is far more sensitive to that phase: converted weights score well below the original on the turned images and
need a short fine-tuning to recover (the LPBA40 header fix: docs/changelog.md).

No library offers this for arbitrary state dicts (it is written here by hand); it is ``torch.flip`` on every
convolution kernel plus a sign on the velocity head.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import atomic_write
from monai_probreg.weights.loading import safe_torch_load
from monai_probreg.weights.settings import settings_path

__all__ = ["MEAN_HEAD", "mirror_state_dict", "mirror_weight_file", "main"]

MEAN_HEAD = "unet.mean_head"  # the conv whose output channels are velocity components (ProbRegNet's state-dict name)


def mirror_state_dict(
    state: Mapping[str, Tensor], axes: Sequence[int], spatial_dims: int = 3, mean_head: str = MEAN_HEAD
) -> dict[str, Tensor]:
    """The state dict of the network that sees inputs mirrored along array ``axes`` (0-based spatial axes).

    Every convolution kernel (a tensor of ``spatial_dims + 2`` dims) is flipped along those axes; the output channels
    ``axes`` of ``mean_head`` (weight and bias) are negated; everything else is copied. Applying it twice gives the
    original back.
    """
    axes = sorted({int(a) for a in axes})
    if not axes or any(a < 0 or a >= spatial_dims for a in axes):
        raise ValueError(f"axes must be spatial axes in [0, {spatial_dims}); got {list(axes)}")
    if f"{mean_head}.weight" not in state:
        raise KeyError(f"expected the velocity head {mean_head!r} in the state dict; got keys {sorted(state)[:6]} ...")
    out: dict[str, Tensor] = {}
    dims = [2 + a for a in axes]
    for name, value in state.items():
        value = value.clone()
        if value.is_floating_point() and value.ndim == spatial_dims + 2:
            value = torch.flip(value, dims)
        if name in (f"{mean_head}.weight", f"{mean_head}.bias"):
            value[axes] = -value[axes]
        out[name] = value
    return out


def mirror_weight_file(
    source: str | os.PathLike, target: str | os.PathLike, axes: Sequence[int], spatial_dims: int = 3
) -> Path:
    """Read a plain state dict (``weights_only=True``), mirror it, write it atomically to ``target``; the
    network-settings sidecar is copied along (the architecture does not change)."""
    source, target = Path(source), Path(target)
    if source.resolve() == target.resolve():
        raise InputError(f"target {str(target)!r}: expected a file other than the source")
    state = safe_torch_load(source, "weights file")
    mirrored = mirror_state_dict(state, axes, spatial_dims)
    atomic_write(target, lambda tmp: torch.save(mirrored, tmp))
    if settings_path(source).is_file():
        atomic_write(settings_path(target), lambda tmp: shutil.copyfile(settings_path(source), tmp))
    return target


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m monai_probreg.weights.orientation",
        description="Weights for inputs mirrored along array axes (two axes: a turn by 180 degrees about the third).",
    )
    parser.add_argument("source")
    parser.add_argument("target")
    parser.add_argument("--axes", type=int, nargs="+", required=True, help="spatial array axes, e.g. 0 1")
    args = parser.parse_args(argv)
    try:
        print("wrote", mirror_weight_file(args.source, args.target, args.axes))
    except (InputError, ValueError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
