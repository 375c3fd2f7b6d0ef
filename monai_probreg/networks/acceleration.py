"""Inference speed levers of the velocity UNet: channels-last 3-d memory format and bf16 autocast.

Both apply only when no gradient is recorded (``torch.no_grad`` / ``torch.inference_mode``: evaluation, inference,
export); training always runs the plain float32 path, so a lever can never change what is learnt. The scaling and
squaring and the warp stay in float32 whatever the setting: the UNet's posterior is cast back to float32 before it
leaves :func:`accelerated_posterior`.

- ``channels_last``: activations and conv weights in ``torch.channels_last_3d`` (NDHWC), the layout oneDNN's 3-d
  convolutions are fastest in. The weights are converted per call (about 0.1 M parameters, well under a
  millisecond) and handed to the UNet with ``torch.func.functional_call``: the module's own parameters keep their
  layout, so optimisers, DDP buckets and saved state_dicts never see the change. Same arithmetic, another order of
  summation: float32 rounding only.
- ``precision``: ``"bf16"`` runs the UNet under ``torch.autocast(dtype=torch.bfloat16)`` (convolutions in bf16 with
  float32 accumulation); ``"fp32"`` never; ``"auto"`` (default) only on a CPU with native bf16 arithmetic (AVX512-BF16
  or AMX, :func:`native_bf16_supported`), where it is fast; elsewhere bf16 would be emulated and slower, and on CUDA it
  has not been measured, so ``"auto"`` keeps float32 there. bf16 keeps 8 bits of mantissa: the velocity moves by
  a fraction of a voxel, which ``tests/networks/test_acceleration.py`` bounds and docs/uncertainty.md quantifies on
  LPBA40. The environment variable ``MONAI_PROBREG_UNET_PRECISION`` (:data:`PRECISION_ENV`), ``bf16`` or ``fp32``,
  decides what ``"auto"`` means on every machine: the test suite runs both ways through it (docs/design.md), so a
  result that depends on the arithmetic is caught on any CPU, not only on the one whose default differs.

Measured numbers for each lever: docs/speed.md, ``benchmarks/speed_compare.py``.
"""

from __future__ import annotations

import functools
import os

import torch
from torch import Tensor, nn

from monai_probreg.networks.velocity_unet import VelocityPosterior

__all__ = ["PRECISION_ENV", "UNET_PRECISIONS", "native_bf16_supported", "unet_autocast_dtype", "accelerated_posterior"]

UNET_PRECISIONS = ("auto", "bf16", "fp32")
PRECISION_ENV = "MONAI_PROBREG_UNET_PRECISION"  # "bf16" or "fp32": what "auto" means (unset: the machine decides)


@functools.lru_cache(maxsize=1)
def native_bf16_supported() -> bool:
    """True when this CPU has bf16 arithmetic in hardware (AVX512-BF16 or AMX tiles) and torch has oneDNN."""
    if not torch.backends.mkldnn.is_available():
        return False
    checks = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return any(check() for check in checks if check is not None)


def unet_autocast_dtype(precision: str, device: torch.device | str) -> torch.dtype | None:
    """The autocast dtype ``precision`` means on ``device`` (None: plain float32); see the module docstring."""
    if precision not in UNET_PRECISIONS:
        raise ValueError(f"unet_precision must be one of {list(UNET_PRECISIONS)}; got {precision!r}")
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    forced = os.environ.get(PRECISION_ENV, "")
    if forced:
        if forced not in UNET_PRECISIONS[1:]:
            raise ValueError(f"{PRECISION_ENV} must be one of {list(UNET_PRECISIONS[1:])} or unset; got {forced!r}")
        return unet_autocast_dtype(forced, device)
    return torch.bfloat16 if torch.device(device).type == "cpu" and native_bf16_supported() else None


def accelerated_posterior(
    unet: nn.Module, moving: Tensor, fixed: Tensor, precision: str = "auto", channels_last: bool = True
) -> VelocityPosterior:
    """``unet(moving, fixed)`` with the inference levers; returns contiguous float32 mean and log_var.

    Meant for calls without gradient recording (the caller, :class:`~monai_probreg.ProbRegNet`, checks);
    ``channels_last`` applies to 3-d inputs only (2-d: the UNet runs as it is).
    """
    dtype = unet_autocast_dtype(precision, moving.device)
    call_args = (moving, fixed)
    params = None
    if channels_last and moving.ndim == 5:
        layout = torch.channels_last_3d
        call_args = (moving.contiguous(memory_format=layout), fixed.contiguous(memory_format=layout))
        params = {name: p.contiguous(memory_format=layout) if p.ndim == 5 else p for name, p in unet.named_parameters()}
    with torch.autocast(device_type=moving.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
        if params is None:
            posterior = unet(*call_args)
        else:
            posterior = torch.func.functional_call(unet, params, call_args)
    return VelocityPosterior(*(t.float().contiguous() for t in posterior))
