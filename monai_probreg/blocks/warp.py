"""Pull-back warping of images, label maps and displacement fields, built on MONAI's ``Warp``.

Conventions (the package-wide ones, see ``monai_probreg/__init__.py``):

- a displacement field ``ddf`` has shape ``(B, spatial_dims, *S)``; channel ``k`` is the component along
  tensor axis ``2 + k`` and is measured in voxels of the grid it lives on;
- warping pulls back: ``warped[x] = image[x + ddf[x]]``, sampled with ``align_corners=True`` semantics
  (voxel centres at integer indices);
- composition: ``compose_displacements(a, b)`` is the displacement of ``phi_a o phi_b``, i.e.
  ``x -> x + b(x) + a(x + b(x))``.

Speed (``fast=True``, the default; ``fast=False`` runs MONAI's ``Warp.forward`` unchanged, for comparison):

- :func:`sampling_grid` writes ``grid_sample``'s normalised xyz grid straight from the field in one pass, from
  1-D broadcast axes, where MONAI adds a cached identity grid, permutes, normalises each axis in place and flips
  (five passes over a full-size field);
- :func:`split_grid_sample` spreads a single 3-d item over the CPU threads: ATen's CPU ``grid_sample`` for 5-d
  inputs parallelises over the batch only, so one pair ran on one core whatever ``torch.get_num_threads()``.
Both give MONAI's result up to float32 rounding of the sampling coordinates (``tests/blocks/test_warp.py``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import List, Optional

import torch
import torch.nn.functional as F
from monai.networks.blocks import Warp
from monai.networks.utils import meshgrid_ij
from torch import Tensor, nn

from monai_probreg.blocks.grid_coords import index_scale, normalise_index
from monai_probreg.utils.tensors import shape_str

__all__ = [
    "CachedWarp",
    "warp_image",
    "warp_box",
    "warp_labels",
    "warp_one_hot",
    "compose_displacements",
    "identity_grid",
    "sampling_grid",
    "split_grid_sample",
    "SpatialTransformer",
]

# Fewest sampled points worth a thread of their own in split_grid_sample: below this (a 20^3 grid) the extra
# grid_sample calls cost more than they save. The velocity grid's squarings (40 x 48 x 40 points) gain from the split,
# backward most (benchmarks/refinement_speed.py, "the integration's squaring").
MIN_POINTS_PER_THREAD = 8_192


def identity_grid(spatial_shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """Voxel coordinates of a grid, shape ``(1, len(spatial_shape), *spatial_shape)``, channel k = index along axis k."""
    axes = [torch.arange(n, dtype=dtype, device=device) for n in spatial_shape]
    return torch.stack(meshgrid_ij(*axes), dim=0).unsqueeze(0)


def sampling_grid(ddf: Tensor, origin: Optional[List[int]] = None, image_size: Optional[List[int]] = None) -> Tensor:
    """``grid_sample``'s grid for the pull-back ``x -> x + ddf(x)``: (B, *S, D), last axis in its reversed (xyz)
    order, coordinates normalised to [-1, 1] with ``align_corners=True`` (the rule of
    :mod:`monai_probreg.blocks.grid_coords`: voxel i of n -> i * 2 / (n - 1) - 1).

    ``origin`` and ``image_size``: ``ddf`` covers a box of a larger image grid (``image_size`` voxels per axis) whose
    first voxel is index ``origin`` of that grid; the grid then samples that image at ``origin + x + ddf(x)``.
    None: the field covers the image's whole grid (origin 0, the field's own size).

    One pass over the field: each grid component is a broadcast 1-D axis plus the scaled field component, written
    into place (``out=``) when no gradient is needed, stacked otherwise (differentiable in ``ddf``).
    Compiles with ``torch.jit.script``.
    """
    spatial = ddf.shape[2:]
    dims = len(spatial)
    differentiable = torch.is_grad_enabled() and ddf.requires_grad
    grid = ddf.new_empty([0] if differentiable else [ddf.shape[0]] + list(spatial) + [dims])
    components: List[Tensor] = []
    for k in range(dims):
        axis = dims - 1 - k  # grid channel k (x, y, z) samples tensor axis 2 + axis (grid_coords: the flip)
        shape = [1] * (dims + 1)
        shape[1 + axis] = spatial[axis]
        # normalise_index is MONAI's order of operations: the identity grid is bit-identical to MONAI's
        size = spatial[axis] if image_size is None else image_size[axis]
        index = torch.arange(spatial[axis], dtype=ddf.dtype, device=ddf.device)
        if origin is not None:
            index = index + origin[axis]
        line = normalise_index(index, size).view(shape)
        scale = index_scale(size)
        if differentiable:
            components.append(line + ddf[:, axis] * scale)
        else:
            torch.add(line, ddf[:, axis], alpha=scale, out=grid[..., k])
    return torch.stack(components, dim=-1) if differentiable else grid


def _num_splits(image: Tensor, grid: Tensor) -> int:
    """How many pieces :func:`split_grid_sample` cuts a single CPU 3-d item into (1: no split)."""
    if image.device.type != "cpu" or image.ndim != 5 or image.shape[0] != 1:
        return 1
    rows = grid.shape[1] * grid.shape[2]  # pieces are whole rows of the last spatial axis
    most = min(torch.get_num_threads(), math.prod(grid.shape[1:-1]) // MIN_POINTS_PER_THREAD)
    return max([n for n in range(1, max(most, 1) + 1) if rows % n == 0])


def split_grid_sample(
    image: Tensor, grid: Tensor, mode: str = "bilinear", padding_mode: str = "border", num_splits: int | None = None
) -> Tensor:
    """``F.grid_sample(image, grid, mode, padding_mode, align_corners=True)``, a single 3-d CPU item run on all threads.

    ATen's CPU kernel for 5-d inputs loops over the batch in parallel and over the points serially, so batch 1 uses
    one thread. The grid's points are cut into ``n`` batch items (whole rows, a view) against the image expanded
    ``n`` times (stride 0, no copy); each point is sampled exactly as before, so the result is identical.
    ``num_splits``: ``n``, which must divide ``S0 * S1``; None: the torch thread count, at most one piece per
    :data:`MIN_POINTS_PER_THREAD` points, and 1 (a direct call) for batch > 1, 2-d grids or CUDA. Differentiable.
    """
    n = _num_splits(image, grid) if num_splits is None else int(num_splits)
    if n > 1 and (image.ndim != 5 or image.shape[0] != 1 or (grid.shape[1] * grid.shape[2]) % n):
        raise ValueError(
            f"num_splits={n} needs one 3-d item whose grid rows S0 * S1 it divides; got image "
            f"{tuple(image.shape)}, grid {tuple(grid.shape)}"
        )
    if n == 1:
        return F.grid_sample(image, grid, mode=mode, padding_mode=padding_mode, align_corners=True)
    spatial = grid.shape[1:-1]
    pieces = grid.reshape(n, 1, spatial[0] * spatial[1] // n, spatial[2], grid.shape[-1])
    out = F.grid_sample(
        image.expand(n, *image.shape[1:]), pieces, mode=mode, padding_mode=padding_mode, align_corners=True
    )  # (n, C, 1, rows / n, S2)
    return out.transpose(0, 1).reshape(1, image.shape[1], *spatial)


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
        fast: build the sampling grid with :func:`sampling_grid` and sample with :func:`split_grid_sample`
            (module docstring); False: MONAI's ``Warp.forward`` as it is. Same result up to float32 rounding.

    Shapes: ``image`` (B, C, *S), ``ddf`` (B, spatial_dims, *S) in voxels -> (B, C, *S).
    """

    def __init__(self, mode: str = "bilinear", padding_mode: str = "border", fast: bool = True) -> None:
        with warnings.catch_warnings():
            # MONAI warns on every construction that it falls back to torch's grid_sample; that is the
            # path we want (CPU, differentiable, float64 for gradcheck), so the warning is noise here.
            warnings.filterwarnings("ignore", message=".*Using PyTorch native grid_sample.*")
            super().__init__(mode=mode, padding_mode=padding_mode)
        self._grid_key: tuple | None = None
        self.fast = fast

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
        if image.ndim != 4 and image.ndim != 5:
            raise ValueError("image must be (B, C, *S) with 2 or 3 spatial dims; got shape " + shape_str(image.shape))
        expected = [image.shape[0], image.ndim - 2] + list(image.shape[2:])
        if list(ddf.shape) != expected:
            raise ValueError(
                "ddf must have shape "
                + shape_str(expected)
                + " to warp an image of shape "
                + shape_str(image.shape)
                + "; got "
                + shape_str(ddf.shape)
            )
        if torch.jit.is_scripting():  # TorchScript (bundle ckpt_export): the one-pass grid, one grid_sample call
            return F.grid_sample(
                image,
                sampling_grid(ddf),
                mode=self._interp_mode_native,
                padding_mode=self._padding_mode_native,
                align_corners=True,
            )
        return self._eager_forward(image, ddf)

    @torch.jit.unused
    def _eager_forward(self, image: Tensor, ddf: Tensor) -> Tensor:
        if not self.fast or self.jitter or torch.jit.is_tracing():  # a trace must not record this machine's threads
            return super().forward(image, ddf)
        return split_grid_sample(image, sampling_grid(ddf), self._interp_mode_native, self._padding_mode_native)


_WARPS: dict[tuple[str, str, bool], CachedWarp] = {}


def _warp_layer(mode: str, padding_mode: str, fast: bool = True) -> CachedWarp:
    key = (mode, padding_mode, fast)
    if key not in _WARPS:
        _WARPS[key] = CachedWarp(mode=mode, padding_mode=padding_mode, fast=fast)
    return _WARPS[key]


def warp_image(image: Tensor, ddf: Tensor, padding_mode: str = "border", fast: bool = True) -> Tensor:
    """Linearly resample ``image`` (B, C, *S) at ``x + ddf(x)``; differentiable in both arguments.
    ``fast``: see :class:`CachedWarp`."""
    return _warp_layer("bilinear", padding_mode, fast)(image, ddf)


def warp_box(image: Tensor, ddf: Tensor, origin: Sequence[int], padding_mode: str = "border") -> Tensor:
    """:func:`warp_image` (the one-pass grid) of a box of the output grid only: ``ddf`` (B, D, *s) is the field on the
    box whose first voxel is index ``origin`` of ``image``'s grid (B, C, *S); returns (B, C, *s), the box of what
    ``warp_image(image, ddf_on_the_whole_grid)`` gives. Differentiable in both arguments."""
    if len(origin) != ddf.ndim - 2:
        raise ValueError(f"expected {ddf.ndim - 2} origin indices (the field's spatial dims); got {list(origin)}")
    grid = sampling_grid(ddf, [int(i) for i in origin], [int(n) for n in image.shape[2:]])
    return split_grid_sample(image, grid, "bilinear", padding_mode)


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
