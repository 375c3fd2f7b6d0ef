"""MONAI's local normalised cross-correlation with a rectangular window, its window sums computed faster on a CPU.

Two forms of the same loss (MONAI's formula, zero padding at the borders, ``smooth_nr`` / ``smooth_dr``; tested against
:class:`monai.losses.LocalNormalizedCrossCorrelationLoss` to float rounding, 1-d to 3-d, values and gradients):

- :class:`BoxLNCCLoss`, a drop-in for MONAI's (any pair, autograd): on grids of at least ``POOLED_FROM_VOXELS`` its
  five window sums are taken by ``avg_pool`` along one axis at a time over the stacked tensors (a fixed target's two
  outside autograd), where MONAI's ``separable_filtering`` (a 1-d convolution per axis of each one-channel tensor)
  slows down much more than linearly on a CPU; below it, MONAI's own ``forward`` (``experiments/lncc_speed.py``).
- :class:`FixedImageLNCC`, for a loop that compares many warped images with one fixed image (the test-time
  refinement, :mod:`monai_probreg.engines.refinement`): the fixed image's sums once, three window sums forward and
  three backward with the gradient written by hand, by doubling sums (:func:`box_sum`) in one zero-bordered buffer,
  and optionally only inside the box where a window can add to the loss (:func:`support_box`)
  (``benchmarks/refinement_speed.py`` times each lever against autograd through MONAI's form).

Written by hand for speed only: neither MONAI nor torch offers these forms. (A box filter by cumulative sums was tried
in a scratch check: float32 cancellation put its gradient far from MONAI's on a real brain pair; the doubling sums
add the same terms as the window and cancel nothing.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from monai.losses import LocalNormalizedCrossCorrelationLoss
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from monai_probreg.utils.errors import check_integer

__all__ = [
    "BOX_SUM_PLANES",
    "POOLED_FROM_VOXELS",
    "BoxLNCCLoss",
    "FixedImageLNCC",
    "box_mean",
    "box_sum",
    "padded_box_sum",
    "support_box",
]

# spatial voxels from which BoxLNCCLoss pools its window sums (MONAI's separable convolution below): the crossover
# measured by experiments/lncc_speed.py on a CPU
POOLED_FROM_VOXELS = 800_000

_AVG_POOL = {1: F.avg_pool1d, 2: F.avg_pool2d, 3: F.avg_pool3d}
# output planes of the first spatial axis that padded_box_sum sums at a time: the fastest of 2-16 on a brain's box at
# 1 mm (145 x 178 x 129, three channels) on a 2-core CPU with 32 MB of L3, where one block and its sums stay in cache
BOX_SUM_PLANES = 8


def box_mean(x: Tensor, kernel_size: int) -> Tensor:
    """(B, C, *S) -> the mean of each ``kernel_size``-wide window centred on each voxel (odd size), the voxels
    outside the image counted as zeros: one axis at a time (a box filter is separable)."""
    spatial_dims = x.ndim - 2
    pool = _AVG_POOL[spatial_dims]
    radius = kernel_size // 2
    for axis in range(spatial_dims):
        window = [1] * spatial_dims
        window[axis] = kernel_size
        padding = [0] * spatial_dims
        padding[axis] = radius
        x = pool(x, tuple(window), stride=1, padding=tuple(padding), count_include_pad=True)
    return x


def box_sum(x: Tensor, kernel_size: int) -> Tensor:
    """(B, C, *S) -> the sum of each ``kernel_size``-wide window centred on each voxel (odd size), the voxels outside
    the image counted as zeros, one axis at a time: the sum of ``kernel_size`` shifted copies built by doubling
    (sums of 1, 2, 4, ... neighbours, then the binary digits of the size: 4 additions for 9 instead of 8), which
    is faster than ``avg_pool`` on a CPU and exact in the order of additions (no running sums to cancel). Written by
    hand: torch and MONAI offer the box filter only as pooling or convolution."""
    radius = kernel_size // 2
    return padded_box_sum(F.pad(x, [radius, radius] * (x.ndim - 2)), kernel_size)


def padded_box_sum(padded: Tensor, kernel_size: int, planes: int | None = BOX_SUM_PLANES) -> Tensor:
    """:func:`box_sum` of a tensor already padded: ``padded`` (B, C, *(S + 2 r)), r = ``kernel_size // 2``, holds the
    image in its interior and zeros in its borders; returns (B, C, *S). One zero-bordered buffer can be refilled
    and summed many times (no padding copy per call).

    With 2 or more spatial axes, ``planes`` output planes of the first axis at a time (None: all at once): each
    block's sums along every axis, in the same order, while its data are still in the CPU's cache (a whole 3-d box
    of a brain at 1 mm is several times the cache). The same additions of the same numbers for every voxel, so the
    same bits as all at once."""
    if planes is not None and (isinstance(planes, bool) or not isinstance(planes, int) or planes < 1):
        raise ValueError(f"planes must be a positive integer or None; got {planes!r}")
    size = padded.shape[2] - (kernel_size - 1)
    if planes is None or padded.ndim < 4 or size <= planes:
        for dim in range(2, padded.ndim):
            padded = _window_sum(padded, kernel_size, dim)
        return padded
    out = padded.new_empty((*padded.shape[:2], *(n - (kernel_size - 1) for n in padded.shape[2:])))
    for start in range(0, size, planes):
        count = min(planes, size - start)
        block = padded.narrow(2, start, count + kernel_size - 1)  # the planes and the window's reach around them
        for dim in range(2, padded.ndim):
            block = _window_sum(block, kernel_size, dim)
        out.narrow(2, start, count).copy_(block)
    return out


def _window_sum(padded: Tensor, kernel_size: int, dim: int) -> Tensor:
    size = padded.shape[dim] - (kernel_size - 1)
    # power[i] = sum of padded[i : i + width]; total gathers the binary digits of kernel_size, lowest first
    power, width, offset, remaining = padded, 1, 0, kernel_size
    total: Tensor | None = None
    while True:
        if remaining & 1:
            piece = power.narrow(dim, offset, size)
            total = piece if total is None else total + piece
            offset += width
        remaining >>= 1
        if not remaining:
            return total
        length = power.shape[dim] - width
        power = power.narrow(dim, 0, length) + power.narrow(dim, width, length)
        width *= 2


class BoxLNCCLoss(LocalNormalizedCrossCorrelationLoss):
    """:class:`monai.losses.LocalNormalizedCrossCorrelationLoss` with a rectangular window, window sums by pooling on
    grids of ``pooled_from_voxels`` spatial voxels or more (module docstring; 0: always). Arguments as MONAI's, less
    ``kernel_type``; ``forward(pred, target)`` (B, C, *S), in [-1, 0]."""

    def __init__(
        self,
        spatial_dims: int = 3,
        kernel_size: int = 3,
        reduction: str = "mean",
        smooth_nr: float = 0.0,
        smooth_dr: float = 1e-5,
        pooled_from_voxels: int = POOLED_FROM_VOXELS,
    ) -> None:
        super().__init__(spatial_dims, kernel_size, "rectangular", reduction, smooth_nr, smooth_dr)
        self.pooled_from_voxels = check_integer("pooled_from_voxels", pooled_from_voxels, 0)

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.ndim - 2 != self.ndim:
            raise ValueError(f"expected pred with {self.ndim} spatial dimensions; got shape {tuple(pred.shape)}")
        if target.shape != pred.shape:
            raise ValueError(f"target must have pred's shape {tuple(pred.shape)}; got {tuple(target.shape)}")
        if pred.shape[2:].numel() < self.pooled_from_voxels:
            return super().forward(pred, target)
        channels = pred.shape[1]
        volume = float(self.kernel_size**self.ndim)
        # a fixed target (no gradient, the refinement's fixed image) is pooled outside autograd: its two window sums
        # need no backward pass, about a fifth of the loss's time on a 160 x 192 x 160 grid (same values)
        with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
            target_sums = box_mean(torch.cat([target, target * target], dim=1), self.kernel_size) * volume
        pred_sums = box_mean(torch.cat([pred, pred * pred, target * pred], dim=1), self.kernel_size) * volume
        t_sum, t2_sum = target_sums.split(channels, dim=1)
        p_sum, p2_sum, tp_sum = pred_sums.split(channels, dim=1)
        t_avg, p_avg = t_sum / volume, p_sum / volume
        # MONAI's formula: squared NCC = cross^2 / (var_t var_p), the variances floored at smooth_dr
        floor = torch.as_tensor(self.smooth_dr, dtype=pred_sums.dtype, device=pred_sums.device)
        cross = tp_sum - p_avg * t_sum
        t_var = torch.max(t2_sum - t_avg * t_sum, floor)
        p_var = torch.max(p2_sum - p_avg * p_sum, floor)
        ncc = (cross * cross + self.smooth_nr) / (t_var * p_var)
        if self.reduction == "sum":
            return ncc.sum().neg()
        if self.reduction == "none":
            return ncc.neg()
        if self.reduction == "mean":
            return ncc.mean().neg()
        raise ValueError(f"reduction must be 'mean', 'sum' or 'none'; got {self.reduction!r}")


class _FixedLNCCFunction(torch.autograd.Function):
    """-sum of the local NCC of ``pred`` against a fixed target whose window sums are given, with its gradient by
    hand (see :class:`FixedImageLNCC`). Inputs: pred (B, C, *S); target, t_sum, t_var of the same shape; ``buffer``
    (B, 3 C, *(S + 2 r)) zero-bordered scratch for the window sums; ``weight``: None, or per-voxel weights
    broadcastable to pred (no gradient); returns the sum over every voxel of -ncc (times its weight)."""

    @staticmethod
    def forward(ctx, pred, target, t_sum, t_var, kernel_size, smooth_dr, buffer, weight=None):  # type: ignore[override]
        channels, volume = pred.shape[1], float(kernel_size ** (pred.ndim - 2))
        p_part, p2_part, tp_part = _interior(buffer, kernel_size).split(channels, dim=1)
        p_part.copy_(pred)
        torch.mul(pred, pred, out=p2_part)
        torch.mul(target, pred, out=tp_part)
        p_sum, p2_sum, tp_sum = padded_box_sum(buffer, kernel_size).split(channels, dim=1)
        p_avg = p_sum / volume
        cross = tp_sum - p_avg * t_sum
        p_raw = p2_sum - p_avg * p_sum
        p_var = p_raw.clamp_min(smooth_dr)
        ratio = cross / (t_var * p_var)  # d ncc / d cross = 2 * ratio
        ncc = cross * ratio
        ctx.save_for_backward(pred, target, t_sum, ratio, ncc, p_var, p_avg, p_raw > smooth_dr)
        ctx.kernel_size, ctx.buffer, ctx.weight = kernel_size, buffer, weight
        if weight is None:
            return ncc.sum().neg()
        return (ncc * weight).sum().neg()

    @staticmethod
    @once_differentiable  # the hand-written gradient is not itself differentiable: a double backward is refused
    def backward(ctx, grad_output):  # type: ignore[override]
        pred, target, t_sum, ratio, ncc, p_var, p_avg, p_free = ctx.saved_tensors
        channels, volume = pred.shape[1], float(ctx.kernel_size ** (pred.ndim - 2))
        # per window w: d ncc_w / d (TP, P2, P) = (2 r, -ncc / p_var [p_var not floored], -2 r t_avg - 2 (d/dP2) p_avg)
        # with r = cross / (t_var p_var); a voxel's gradient sums its windows' terms (a box sum: the centred box
        # with zeros outside is its own adjoint): t_i box(d/dTP) + 2 p_i box(d/dP2) + box(d/dP)
        d_tp, d_p2, d_p = _interior(ctx.buffer, ctx.kernel_size).split(channels, dim=1)
        torch.mul(ratio, 2.0, out=d_tp)
        torch.where(p_free, -ncc / p_var, torch.zeros_like(ncc), out=d_p2)
        if ctx.weight is not None:
            # a window's terms count as much as its centre voxel's weight (before the box sums spread them over its
            # voxels); d/dP is linear in the other two, so it follows from them
            d_tp.mul_(ctx.weight)
            d_p2.mul_(ctx.weight)
        torch.sub(-d_tp * (t_sum / volume), 2.0 * d_p2 * p_avg, out=d_p)
        b_tp, b_p2, b_p = padded_box_sum(ctx.buffer, ctx.kernel_size).split(channels, dim=1)
        grad = (target * b_tp + 2.0 * pred * b_p2 + b_p).mul_(grad_output.neg())
        return grad, None, None, None, None, None, None, None


def _interior(buffer: Tensor, kernel_size: int) -> Tensor:
    """The view of a zero-bordered buffer (borders of ``kernel_size // 2``) that holds the image."""
    radius = kernel_size // 2
    return buffer[(slice(None), slice(None), *(slice(radius, n - radius) for n in buffer.shape[2:]))]


class FixedImageLNCC(nn.Module):
    """:class:`BoxLNCCLoss` (``reduction="mean"``, ``smooth_nr`` 0) against one fixed target, for a loop that
    compares many moving images with it (the test-time refinement): the target's two window sums are computed once,
    and the loss's gradient is written by hand (the same formula differentiated on paper: three window sums forward,
    three backward, where autograd through the pooled form takes five forward and three twice as slow backward).
    Same values and gradients as :class:`BoxLNCCLoss` to float rounding (tests/losses/test_lncc.py).

    ``forward(pred, weight=None)`` (the target's shape, or the shape of ``region``'s box when given) -> -mean of the
    local NCC over the target's voxels. ``weight``: per-voxel weights (broadcastable to ``pred``, e.g. (B, 1, *S);
    a cost-function mask, :mod:`monai_probreg.spatial.masks`), no gradient through them: the loss is
    ``-sum(weight * ncc) / N``, N the whole grid's voxel count as without weights (a voxel of weight 1 counts as it
    does unweighted, one of weight 0 not at all, and the image term keeps its scale against the refinement's other
    terms rather than growing as the mask shrinks); None: the unweighted loss, computed exactly as before weights
    existed. In the backward pass each window's derivative terms are multiplied by its centre voxel's weight before
    the box sums.

    ``region``: compare only inside a box of the target (``(starts, stops)`` per spatial axis, from
    :func:`support_box`): a window with no nonzero target voxel adds exactly 0 to the loss and its gradient, so the
    loss over a box that holds every such window (the target's nonzero voxels and twice the window's radius around
    them: ``support_box(target, margin=2 * (kernel_size // 2))``) equals the loss over the whole grid; the mean still
    divides by the whole grid's voxel count. A smaller margin gives another loss (windows cut by the box's edge).
    Written by hand: MONAI's LNCC recomputes the target's sums and differentiates through autograd.
    """

    def __init__(
        self,
        target: Tensor,
        kernel_size: int = 9,
        smooth_dr: float = 1e-5,
        region: tuple[tuple[int, ...], tuple[int, ...]] | None = None,
    ) -> None:
        super().__init__()
        if target.ndim not in (3, 4, 5):
            raise ValueError(f"expected a target (B, C, *S) with 1-3 spatial dims; got shape {tuple(target.shape)}")
        if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be an odd integer >= 1; got {kernel_size!r}")
        self.kernel_size, self.smooth_dr = kernel_size, float(smooth_dr)
        self.num_elements = target.numel()
        target = target.detach()
        if region is not None:
            target = target[_box_slices(target, region)]
        self.region = region
        volume = float(kernel_size ** (target.ndim - 2))
        with torch.no_grad():
            t_sum, t2_sum = box_sum(torch.cat([target, target * target], dim=1), kernel_size).split(
                target.shape[1], dim=1
            )
            t_var = (t2_sum - t_sum / volume * t_sum).clamp_min(self.smooth_dr)
        self.target, self.t_sum, self.t_var = target, t_sum, t_var
        self._buffer: Tensor | None = None  # zero-bordered scratch of the window sums, kept between calls

    def crop(self, image: Tensor) -> Tensor:
        """``image`` on the target's grid (any channels) -> its part inside ``region`` (itself when None)."""
        return image if self.region is None else image[_box_slices(image, self.region)]

    def forward(self, pred: Tensor, weight: Tensor | None = None) -> Tensor:
        if pred.shape[2:] != self.target.shape[2:] or pred.shape[:2] != self.target.shape[:2]:
            raise ValueError(
                f"expected pred of shape {tuple(self.target.shape)} (the target's, inside region); "
                f"got {tuple(pred.shape)}"
            )
        if weight is not None:
            if not _broadcasts_to(weight.shape, pred.shape):
                raise ValueError(
                    f"expected a weight broadcastable to pred's shape {tuple(pred.shape)}, got {tuple(weight.shape)}"
                )
            weight = weight.detach().to(pred.dtype)
        radius = self.kernel_size // 2
        padded = [pred.shape[0], 3 * pred.shape[1], *(n + 2 * radius for n in pred.shape[2:])]
        buffer = self._buffer
        if buffer is None or list(buffer.shape) != padded or (buffer.dtype, buffer.device) != (pred.dtype, pred.device):
            self._buffer = pred.new_zeros(padded)  # the borders stay zero: only the interior is ever written
        total = _FixedLNCCFunction.apply(
            pred,
            self.target,
            self.t_sum,
            self.t_var,
            self.kernel_size,
            self.smooth_dr,
            self._buffer,
            weight,
        )
        return total / self.num_elements


def _broadcasts_to(shape: torch.Size, target: torch.Size) -> bool:
    """Whether a tensor of ``shape`` broadcasts to ``target`` without growing it."""
    try:
        return torch.broadcast_shapes(shape, target) == target
    except RuntimeError:  # torch's word for "cannot broadcast"
        return False


def _box_slices(image: Tensor, region: tuple[tuple[int, ...], tuple[int, ...]]) -> tuple[slice, ...]:
    starts, stops = region
    return (slice(None), slice(None), *(slice(int(a), int(b)) for a, b in zip(starts, stops)))


def support_box(target: Tensor, margin: int) -> tuple[tuple[int, ...], tuple[int, ...]] | None:
    """(starts, stops) of the smallest box holding every nonzero voxel of ``target`` (B, C, *S, any item or channel),
    grown by ``margin`` voxels per side and clipped to the grid; None when the box is the whole grid or the target
    is all zero (nothing to gain)."""
    nonzero = target.detach().ne(0).flatten(0, 1).any(dim=0)
    if not bool(nonzero.any()):
        return None
    starts, stops = [], []
    for axis, size in enumerate(nonzero.shape):
        others = tuple(a for a in range(nonzero.ndim) if a != axis)
        hit = nonzero.any(dim=others) if others else nonzero
        index = hit.nonzero().flatten()
        starts.append(max(int(index[0]) - margin, 0))
        stops.append(min(int(index[-1]) + 1 + margin, size))
    if all(a == 0 for a in starts) and list(stops) == list(nonzero.shape):
        return None
    return tuple(starts), tuple(stops)
