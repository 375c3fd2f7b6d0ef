"""MIND-SSC, the modality independent neighbourhood descriptor (self-similarity context), and the image term that
compares two images by it: for pairs of different contrasts (a T2-weighted scan onto a T1-weighted atlas).

Heinrich et al. (MIND, Med. Image Anal. 2012; its self-similarity context form, MICCAI 2013) describe each voxel
by how alike the patches around its neighbours are *to one another*, not by its intensity: two scans of one anatomy in
different contrasts share the descriptor wherever their tissue boundaries coincide. Here, for a voxel ``x``:

- the neighbours are ``x + p`` for the ``2 D`` offsets ``p = +-dilation * e_k`` (its 6-neighbourhood in 3-d, the 4 in
  2-d, ``dilation`` voxels away); the *pairs* are the neighbours ``(p, q)`` on different axes (a distance of
  ``sqrt(2) dilation``): 12 in 3-d, 4 in 2-d (:func:`mind_pairs`);
- for each pair, the patch distance ``d_pq(x)`` is the mean over the ``(2 radius + 1)^D`` window around ``x`` of
  ``(I(. + p) - I(. + q))^2`` (the image repeated beyond its border, as the published descriptor pads);
- ``m_pq(x) = exp(-(d_pq(x) - min_pq d(x)) / v(x))``, ``v(x)`` the mean over the pairs of ``d_pq(x) - min d(x)``
  (the local variance estimate), kept within ``[VARIANCE_CLAMP^-1, VARIANCE_CLAMP]`` times its mean over the image
  (flat regions would divide by ~0, strong edges make every other one vanish); the largest entry of each voxel is 1.

The image term is the mean over voxels and descriptor channels of ``(m(warped) - m(fixed))^2`` (0 for a perfect
match, at most 1). The descriptor of an image with two intensities does not depend on which two they are (its
distances scale with the squared contrast, and ``v`` with them): the contrast-invariance the tests pin.

Written by hand: neither MONAI nor torch offers MIND; the window means are torch's ``avg_pool`` (one axis at a time).
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from monai_probreg.utils.errors import check_integer

__all__ = ["VARIANCE_CLAMP", "FixedImageMIND", "MINDLoss", "mind_descriptor", "mind_pairs"]

# the local variance estimate v(x) is kept within [mean / VARIANCE_CLAMP, mean * VARIANCE_CLAMP] of its image mean
# (the published descriptor's bounds): a flat region (v ~ 0) or a single strong edge (v large) cannot dominate
VARIANCE_CLAMP = 1000.0

_AVG_POOL = {2: F.avg_pool2d, 3: F.avg_pool3d}


def mind_pairs(spatial_dims: int, dilation: int = 2) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """The neighbour pairs ``(p, q)`` of the descriptor: offsets ``+-dilation * e_k`` on different axes, in a fixed
    order (12 pairs in 3-d, 4 in 2-d)."""
    if spatial_dims not in (2, 3):
        raise ValueError(f"spatial_dims must be 2 or 3; got {spatial_dims!r}")
    offsets = []
    for axis in range(spatial_dims):
        for sign in (-1, 1):
            offset = [0] * spatial_dims
            offset[axis] = sign * dilation
            offsets.append(tuple(offset))
    return [(p, q) for p, q in itertools.combinations(offsets, 2) if [a != 0 for a in p] != [b != 0 for b in q]]


def mind_descriptor(image: Tensor, radius: int = 1, dilation: int = 2) -> Tensor:
    """MIND-SSC of ``image`` (B, C, *S), 2-d or 3-d (module docstring): (B, C * P, *S), channel ``c * P + j`` the
    ``j``-th pair of :func:`mind_pairs` of image channel ``c``. ``radius``: the patch's half-width in voxels (0: a
    single voxel); ``dilation``: how far the neighbours are, in voxels. Differentiable (float32 or float64)."""
    if image.ndim not in (4, 5):
        raise ValueError(f"image must be (B, C, *S) with 2 or 3 spatial dims; got shape {tuple(image.shape)}")
    radius, dilation = check_integer("radius", radius, 0), check_integer("dilation", dilation, 1)
    spatial_dims = image.ndim - 2
    spatial = image.shape[2:]
    padded = F.pad(image, [dilation] * (2 * spatial_dims), mode="replicate")

    def shifted(offset: tuple[int, ...]) -> Tensor:  # I(x + offset) for every x (replicated beyond the border)
        index = [slice(None), slice(None)]
        index += [slice(dilation + o, dilation + o + n) for o, n in zip(offset, spatial)]
        return padded[tuple(index)]

    pairs = mind_pairs(spatial_dims, dilation)
    diffs = torch.stack([(shifted(p) - shifted(q)).square() for p, q in pairs], dim=2)  # (B, C, P, *S)
    distance = diffs.flatten(1, 2)
    if radius > 0:  # the window mean, border repeated, one axis at a time (a box filter is separable)
        pool = _AVG_POOL[spatial_dims]
        for axis in range(spatial_dims):
            window = [1] * spatial_dims
            window[axis] = 2 * radius + 1
            pad = [0] * (2 * spatial_dims)
            pad[2 * (spatial_dims - 1 - axis)] = pad[2 * (spatial_dims - 1 - axis) + 1] = (
                radius  # F.pad: last axis first
            )
            distance = pool(F.pad(distance, pad, mode="replicate"), tuple(window), stride=1)
    distance = distance.unflatten(1, (image.shape[1], len(pairs)))  # (B, C, P, *S)
    distance = distance - distance.amin(dim=2, keepdim=True)
    variance = distance.mean(dim=2, keepdim=True)
    level = variance.mean(dim=tuple(range(3, variance.ndim)), keepdim=True).detach()
    variance = torch.maximum(torch.minimum(variance, level * VARIANCE_CLAMP), level / VARIANCE_CLAMP)
    # an image without any contrast (v = 0 everywhere): every distance is 0 and so is the variance; 0 / tiny -> 1
    variance = variance.clamp_min(torch.finfo(image.dtype).tiny)
    return torch.exp(-distance / variance).flatten(1, 2)


class MINDLoss(nn.Module):
    """``forward(warped, fixed)``: the mean over voxels and descriptor channels of the squared difference of their
    MIND-SSC descriptors (:func:`mind_descriptor` with ``radius`` and ``dilation``), in [0, 1]; for any pair of
    images, of any contrasts. ``reduction``: "mean" or "none" (the per-voxel mean over channels, (B, 1, *S))."""

    def __init__(self, radius: int = 1, dilation: int = 2, reduction: str = "mean") -> None:
        super().__init__()
        self.radius, self.dilation = check_integer("radius", radius, 0), check_integer("dilation", dilation, 1)
        if reduction not in ("mean", "none"):
            raise ValueError(f"reduction must be 'mean' or 'none'; got {reduction!r}")
        self.reduction = reduction

    def forward(self, warped: Tensor, fixed: Tensor) -> Tensor:
        if warped.shape != fixed.shape:
            raise ValueError(
                f"warped and fixed must have the same shape; got {tuple(warped.shape)} and {tuple(fixed.shape)}"
            )
        per_voxel = (
            (mind_descriptor(warped, self.radius, self.dilation) - mind_descriptor(fixed, self.radius, self.dilation))
            .square()
            .mean(dim=1, keepdim=True)
        )
        return per_voxel.mean() if self.reduction == "mean" else per_voxel


class FixedImageMIND(nn.Module):
    """:class:`MINDLoss` against one fixed image, for a loop that compares many warped images with it (the test-time
    refinement): the fixed image's descriptor is computed once. ``forward(warped, weight=None)`` -> the loss;
    ``weight``: per-voxel weights (B, 1, *S), no gradient through them (a cost-function mask): ``sum(weight * d) / N``
    with ``d`` the per-voxel term and N the voxel count (a voxel of weight 1 counts as unweighted, one of 0 not at
    all: the scale of :class:`~monai_probreg.losses.lncc.FixedImageLNCC`'s weights)."""

    def __init__(self, fixed: Tensor, radius: int = 1, dilation: int = 2) -> None:
        super().__init__()
        self.radius, self.dilation = check_integer("radius", radius, 0), check_integer("dilation", dilation, 1)
        self.shape = tuple(fixed.shape)
        with torch.no_grad():
            self.descriptor = mind_descriptor(fixed.detach(), radius, dilation)

    def per_voxel(self, warped: Tensor) -> Tensor:
        """(B, 1, *S): the mean over channels of the squared descriptor difference at each voxel."""
        if tuple(warped.shape) != self.shape:
            raise ValueError(f"expected warped of shape {self.shape} (the fixed image's); got {tuple(warped.shape)}")
        descriptor = mind_descriptor(warped, self.radius, self.dilation)
        return (descriptor - self.descriptor).square().mean(dim=1, keepdim=True)

    def forward(self, warped: Tensor, weight: Tensor | None = None) -> Tensor:
        per_voxel = self.per_voxel(warped)
        if weight is None:
            return per_voxel.mean()
        return (per_voxel * weight.detach()).sum() / per_voxel.numel()
