"""Small tensor helpers shared across the package."""

from __future__ import annotations

from monai.data import MetaTensor
from torch import Tensor

__all__ = ["plain_tensor"]


def plain_tensor(t: Tensor) -> Tensor:
    """``t`` without MONAI metadata (a plain ``torch.Tensor`` sharing its storage); plain tensors pass through."""
    return t.as_tensor() if isinstance(t, MetaTensor) else t
