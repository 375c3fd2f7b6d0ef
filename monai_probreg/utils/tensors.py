"""Small tensor helpers shared across the package."""

from __future__ import annotations

import numpy as np
from monai.data import MetaTensor
from torch import Tensor

__all__ = ["float_numpy", "plain_tensor", "shape_str"]


def plain_tensor(t: Tensor) -> Tensor:
    """``t`` without MONAI metadata (a plain ``torch.Tensor`` sharing its storage); plain tensors pass through."""
    return t.as_tensor() if isinstance(t, MetaTensor) else t


def float_numpy(t: Tensor) -> np.ndarray:
    """``t`` as a float32 numpy array on the CPU, out of autograd."""
    return t.detach().float().cpu().numpy()


def shape_str(shape: list[int]) -> str:
    """``str(tuple(shape))`` in a form ``torch.jit.script`` compiles, for error messages of scriptable modules:
    ``(1, 2, 3)``, ``(4,)``, ``()``."""
    body = ", ".join([str(n) for n in shape])
    return "(" + body + ("," if len(shape) == 1 else "") + ")"
