"""Loading trained weights into a network: the one safe way to read a weights or checkpoint file.

:func:`safe_torch_load` is ``torch.load(weights_only=True)``: a pickle that holds anything but tensors and plain
containers (e.g. an object whose ``__reduce__`` calls ``os.system``) raises :class:`~monai_probreg.utils.errors.
UntrustedFileError` and its code is not run; a truncated or corrupt file raises
:class:`~monai_probreg.utils.errors.InputError`. :func:`load_weights` adds the network-settings check
(:mod:`monai_probreg.weights.settings`).
"""

from __future__ import annotations

import os
import pickle
import zlib
from pathlib import Path
from typing import Any

import torch
from torch import nn

from monai_probreg.utils.errors import InputError, UntrustedFileError, first_line
from monai_probreg.weights.settings import check_network_settings

__all__ = ["safe_torch_load", "load_weights"]


def _unpickling_reason(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    useful = [line for line in lines if "GLOBAL" in line or "Unsupported" in line]
    return (useful or lines or [type(err).__name__])[0][:200]


def safe_torch_load(
    path: str | os.PathLike, role: str = "weights file", map_location: str | torch.device | None = "cpu"
) -> Any:
    """``torch.load(path, weights_only=True)`` with one-line errors: :class:`UntrustedFileError` for a pickle that
    needs more than tensors and plain containers (nothing in it is run), InputError for a truncated/corrupt file."""
    where = f"{role} {str(path)!r}"
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        raise UntrustedFileError(
            f"{where}: refused: expected a plain state dict (tensors, numbers, strings, containers), got a pickle "
            f"that asks for more ({_unpickling_reason(err)}); nothing in it was run. Load weights only from sources "
            "you trust, re-saved as a plain state_dict"
        ) from None
    except (RuntimeError, EOFError, OSError, ValueError, zlib.error) as err:
        raise InputError(
            f"{where}: expected a complete torch weights file, got a truncated or corrupt one ({first_line(err)})"
        ) from None


def load_weights(network: nn.Module, model_file: str | os.PathLike, device: str | torch.device = "cpu") -> nn.Module:
    """Load a plain state_dict (``torch.load(weights_only=True)``, strict) into ``network``; move it to ``device``
    and put it in eval mode. A missing file is a one-line ``FileNotFoundError`` naming the path; a file holding more
    than tensors (a pickle that could run code) an ``UntrustedFileError`` (:func:`~monai_probreg.spatial.checks.
    safe_torch_load`: nothing in it is run); a truncated or corrupt one an ``InputError``, and so is a network whose
    settings differ from those recorded next to the file (:mod:`monai_probreg.weights.settings`)."""
    path = Path(model_file)
    if not path.is_file():
        raise FileNotFoundError(
            f"model file {str(path)!r} does not exist (train.yaml writes models/model.pt; or pass --model_file PATH)"
        )
    check_network_settings(path, network)  # network_size etc. leave no trace in the tensors: their JSON sidecar
    network.load_state_dict(safe_torch_load(path, "model file", map_location=device))
    return network.to(device).eval()
