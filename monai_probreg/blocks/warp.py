"""Pull-back warping of images, label maps and displacement fields, built on MONAI's ``Warp``.

Conventions (the package-wide ones, see ``monai_probreg/__init__.py``):

- a displacement field ``ddf`` has shape ``(B, spatial_dims, *S)``; channel ``k`` is the component along
  tensor axis ``2 + k`` and is measured in voxels of the grid it lives on;
- warping pulls back: ``warped[x] = image[x + ddf[x]]``, sampled with ``align_corners=True`` semantics
  (voxel centres at integer indices);
- composition: ``compose_displacements(a, b)`` is the displacement of ``phi_a o phi_b``, i.e.
  ``x -> x + b(x) + a(x + b(x))``.
"""

from __future__ import annotations

import warnings

import torch
from monai.networks.blocks import Warp
from monai.networks.utils import meshgrid_ij
from torch import Tensor, nn

__all__ = [
    "CachedWarp",
    "warp_image",
    "warp_labels",
    "warp_one_hot",
    "compose_displacements",
    "identity_grid",
    "SpatialTransformer",
]


def identity_grid(spatial_shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """Voxel coordinates of a grid, shape ``(1, len(spatial_shape), *spatial_shape)``, channel k = index along axis k."""
    axes = [torch.arange(n, dtype=dtype, device=device) for n in spatial_shape]
    return torch.stack(meshgrid_ij(*axes), dim=0).unsqueeze(0)


class CachedWarp(Warp):
    """MONAI :class:`~monai.networks.blocks.Warp` whose reference grid is actually cached.

    MONAI's ``Warp.get_reference_grid`` compares ``ref_grid.shape[1:]`` (channels + spatial) with
    ``ddf.shape[2:]`` (spatial only), so its cache never hits and the grid is rebuilt on every call.
    We key the cache on (spatial shape, dtype, device) and broadcast over the batch instead of
    materialising one grid per batch item. Everything else (pull-back convention, the one flip to
    ``grid_sample``'s xyz order, padding, interpolation) is MONAI's own code.

    Args:
        mode: ``"bilinear"`` (linear in 2D and 3D) or ``"nearest"`` (label maps).
        padding_mode: ``"border"``, ``"zeros"`` or ``"reflection"`` for samples outside the grid.

    Shapes: ``image`` (B, C, *S), ``ddf`` (B, spatial_dims, *S) in voxels -> (B, C, *S).
    """

    def __init__(self, mode: str = "bilinear", padding_mode: str = "border") -> None:
        with warnings.catch_warnings():
            # MONAI warns on every construction that it falls back to torch's grid_sample; that is the
            # path we want (CPU, differentiable, float64 for gradcheck), so the warning is noise here.
            warnings.filterwarnings("ignore", message=".*Using PyTorch native grid_sample.*")
            super().__init__(mode=mode, padding_mode=padding_mode)
        self._grid_key: tuple | None = None

    def get_reference_grid(self, ddf: Tensor, jitter: bool = False, seed: int = 0) -> Tensor:
        if jitter:
            self._grid_key = None  # MONAI stores its jittered grid in ref_grid: never reuse it as ours
            return super().get_reference_grid(ddf, jitter=jitter, seed=seed)
        key = (tuple(ddf.shape[2:]), ddf.dtype, ddf.device)
        if self.ref_grid is None or self._grid_key != key:
            self.ref_grid = identity_grid(key[0], ddf.dtype, ddf.device)
            self._grid_key = key
        return self.ref_grid.expand(ddf.shape[0], *self.ref_grid.shape[1:])

    def forward(self, image: Tensor, ddf: Tensor) -> Tensor:  # type: ignore[override]
        if image.ndim not in (4, 5):
            raise ValueError(f"image must be (B, C, *S) with 2 or 3 spatial dims; got shape {tuple(image.shape)}")
        expected = (image.shape[0], image.ndim - 2, *image.shape[2:])
        if tuple(ddf.shape) != expected:
            raise ValueError(f"ddf must have shape {expected} to warp an image of shape {tuple(image.shape)}; "
                             f"got {tuple(ddf.shape)}")
        return super().forward(image, ddf)


_WARPS: dict[tuple[str, str], CachedWarp] = {}


def _warp_layer(mode: str, padding_mode: str) -> CachedWarp:
    key = (mode, padding_mode)
    if key not in _WARPS:
        _WARPS[key] = CachedWarp(mode=mode, padding_mode=padding_mode)
    return _WARPS[key]


def warp_image(image: Tensor, ddf: Tensor, padding_mode: str = "border") -> Tensor:
    """Linearly resample ``image`` (B, C, *S) at ``x + ddf(x)``; differentiable in both arguments."""
    return _warp_layer("bilinear", padding_mode)(image, ddf)


def warp_labels(labels: Tensor, ddf: Tensor) -> Tensor:
    """Nearest-neighbour warp of an integer label map (B, 1, *S); labels outside the grid become 0.

    Not differentiable: for evaluation (Dice). Use :func:`warp_one_hot` inside a loss.
    """
    if labels.is_floating_point() and not torch.equal(labels, labels.round()):
        raise ValueError("labels must hold integer values; got non-integer floats")
    warped = _warp_layer("nearest", "zeros")(labels.to(ddf.dtype), ddf)
    return warped.round().to(labels.dtype)


def warp_one_hot(one_hot: Tensor, ddf: Tensor) -> Tensor:
    """Differentiable label warp: linear interpolation of a one-hot (or soft) map (B, L, *S)."""
    return _warp_layer("bilinear", "zeros")(one_hot, ddf)


def compose_displacements(outer: Tensor, inner: Tensor, padding_mode: str = "border") -> Tensor:
    """Displacement of ``phi_outer o phi_inner``: ``inner(x) + outer(x + inner(x))``; both (B, D, *S)."""
    return inner + warp_image(outer, inner, padding_mode=padding_mode)


class SpatialTransformer(nn.Module):
    """``nn.Module`` form of :func:`warp_image` / :func:`warp_labels` for use in configs."""

    def __init__(self, mode: str = "bilinear", padding_mode: str = "border") -> None:
        super().__init__()
        self.warp = CachedWarp(mode=mode, padding_mode=padding_mode)

    def forward(self, image: Tensor, ddf: Tensor) -> Tensor:
        return self.warp(image, ddf)
