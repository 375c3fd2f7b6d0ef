"""Uniform averaging of the weights of several checkpoints of one training run (checkpoint averaging, as in SWA).

Late in a low-learning-rate fine-tune the validation Dice of single epochs wobbles by a few thousandths and the
best epoch is partly luck; the mean of several epochs' weights sits nearer the middle of the basin they explore,
is smoother (fewer folded voxels) and is chosen with less selection on the validation subjects. torch's
``torch.optim.swa_utils.AveragedModel`` averages *during* training; this averages files *after* it, so that the
epochs to average can be picked once their validation numbers are known. Written here because neither MONAI nor
torch offers a file-level averager with the checks below.

Inputs are plain state dicts (``models/model.pt``) or training states with a ``"model"`` entry (``train.yaml``'s
``<state_prefix>_checkpoint_epoch=N.pt``; keep more than the last with ``--checkpoint#saver#n_saved N``), all
loaded with ``weights_only=True``. They must have the same keys and shapes; floating tensors are averaged in
float64 and cast back, any other tensor must be equal in all. The network settings recorded next to an input
(``<name>.network.json``, :mod:`monai_probreg.weights.settings`) must agree and are written next to the output.

    python -m monai_probreg.weights.averaging --out bundle/models/model.pt RUN/state_ep9.pt RUN/...
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import atomic_write, write_text
from monai_probreg.weights.loading import safe_torch_load
from monai_probreg.weights.settings import settings_path

__all__ = ["read_model_state", "average_state_dicts", "average_weight_files", "main"]


def read_model_state(path: str | os.PathLike) -> dict[str, Tensor]:
    """The model state dict in ``path``: the file itself, or its ``"model"`` entry for a training state."""
    state = safe_torch_load(path, "weights file")
    if isinstance(state, Mapping) and isinstance(state.get("model"), Mapping):
        state = state["model"]
    if not (isinstance(state, Mapping) and state and all(isinstance(v, Tensor) for v in state.values())):
        raise InputError(
            f"weights file {str(path)!r}: expected a state dict of tensors or a training state with a "
            f"'model' entry, got {type(state).__name__}"
        )
    return dict(state)


def average_state_dicts(
    states: Sequence[Mapping[str, Tensor]], names: Sequence[str] | None = None
) -> dict[str, Tensor]:
    """The element-wise mean of ``states`` (>= 2 state dicts with the same keys and shapes); ``names`` label them
    in errors (default: their positions)."""
    names = list(names) if names is not None else [f"state {i}" for i in range(len(states))]
    if len(states) < 2:
        raise InputError(f"averaging needs at least 2 weight files; got {len(states)}")
    if len(names) != len(states):
        raise ValueError(f"expected one name per state dict ({len(states)}); got {len(names)}")
    first, reference = states[0], names[0]
    for state, name in zip(states[1:], names[1:]):
        if set(state) != set(first):
            extra, missing = sorted(set(state) - set(first)), sorted(set(first) - set(state))
            raise InputError(
                f"{name} does not hold the same network as {reference}: "
                f"keys only in {name}: {extra[:3]}, keys missing from it: {missing[:3]}"
            )
        for key, tensor in state.items():
            if tensor.shape != first[key].shape:
                raise InputError(
                    f"{name}: {key} has shape {tuple(tensor.shape)}, expected {tuple(first[key].shape)} "
                    f"as in {reference}"
                )
    averaged = {}
    for key, tensor in first.items():
        if tensor.is_floating_point():
            total = sum(state[key].double() for state in states)
            averaged[key] = (total / len(states)).to(tensor.dtype)
        else:
            different = [name for state, name in zip(states, names) if not torch.equal(state[key], tensor)]
            if different:
                raise InputError(
                    f"{key} is not a floating tensor and differs between {reference} and {different[0]}: "
                    "integer buffers cannot be averaged"
                )
            averaged[key] = tensor.clone()
    return averaged


def _recorded_settings(paths: Sequence[Path], extra: Path | None) -> Path | None:
    """The one network-settings JSON of the inputs (and ``extra``), or None when none has one."""
    if extra is not None and not extra.is_file():
        raise FileNotFoundError(f"network settings {str(extra)!r} do not exist")
    found = [p for p in ([settings_path(x) for x in paths] + ([extra] if extra else [])) if p.is_file()]
    texts = {p.read_text() for p in found}
    if len(texts) > 1:
        raise InputError("the inputs record different network settings: " + ", ".join(str(p) for p in found))
    return found[0] if found else None


def average_weight_files(
    inputs: Sequence[str | os.PathLike], out: str | os.PathLike, network_settings: str | os.PathLike | None = None
) -> Path:
    """Average the weights in ``inputs`` into the plain state dict ``out`` (written atomically), with the inputs'
    (or ``network_settings``') network-settings JSON beside it. Returns ``out``."""
    paths = [Path(p) for p in inputs]
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"weights file {str(path)!r} does not exist")
    settings = _recorded_settings(paths, Path(network_settings) if network_settings else None)
    averaged = average_state_dicts([read_model_state(p) for p in paths], [str(p) for p in paths])
    out = Path(out)
    atomic_write(out, lambda tmp: torch.save(averaged, tmp))
    if settings is not None and settings.resolve() != settings_path(out).resolve():
        write_text(settings_path(out), settings.read_text())
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m monai_probreg.weights.averaging",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("inputs", nargs="+", type=Path, help="weights or training-state files of one run (>= 2)")
    ap.add_argument("--out", type=Path, required=True, help="the averaged plain state dict")
    ap.add_argument(
        "--network-settings",
        type=Path,
        default=None,
        help="a <name>.network.json to write beside --out (default: the inputs' own, if any)",
    )
    args = ap.parse_args(argv)
    try:
        out = average_weight_files(args.inputs, args.out, args.network_settings)
    except (InputError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {out}: the mean of {len(args.inputs)} weight files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
