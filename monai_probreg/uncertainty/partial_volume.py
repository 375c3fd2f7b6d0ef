"""The label entropy of posterior samples, each sample's label read with partial volume.

Pulling a label map through a displacement reads the label at a point between voxels. Nearest-neighbour reading
(:func:`~monai_probreg.uncertainty.entropy.label_entropy` of K warped label maps) gives each sample one whole label, so
a voxel whose label changes in a few percent of the posterior shows no entropy in most sets of K = 16 samples, and
ties with the certain voxels at 0. Read with partial volume instead, a sample gives the 2^D voxels around its point the
weights of linear interpolation, and the label distribution of a voxel is

    p_l(x) = 1/K sum_k sum_c w_kc(x) [labels(corner_kc(x)) = l]

(corners outside the grid read label 0, as the nearest-neighbour warp's zero padding does). Its entropy ranks the
wrongly propagated voxels of LPBA40's validation pairs better at the same K (``experiments/label_entropy_ranking.py``,
docs/uncertainty.md).

:class:`PartialVolumeLabels` accumulates it sample by sample, exactly and without a histogram of every label at every
voxel:

- one nearest-neighbour read, half a voxel below the sampled point p, of a precomputed map of the cells (each indexed
  by its lowest corner) that hold one label finds p's own cell, the one at floor(p); where it holds one label the
  sample reads that label wholly;
- elsewhere precomputed tables give the cell's labels: where it holds two (most of the rest: a boundary between two
  structures), its lower and higher label, two (label, weight) pairs, the higher label's weight summed over the
  corners a precomputed bit mask names;
- only cells of three labels or more keep their 2^D (label, weight) pairs.

The entropy is then 0 where every sample read the same label wholly; the voxels where the samples read two-label
cells or disagree sort their 2K (label, weight) pairs and add the weights of each run of one label; the few voxels a
sample read in a cell of three labels or more take a histogram over the labels present. Written by hand: no library
reads a label map with interpolation weights per label.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from monai_probreg.blocks.warp import sampling_grid, split_grid_sample
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["LABEL_LIMIT", "PartialVolumeLabels"]

LABEL_LIMIT = (1 << 15) - 1  # labels are kept as int16, the whole reads as label + 1


def _run_entropy(labels: Tensor, weights: Tensor, num: int) -> Tensor:
    """Entropy (nats) of p_l = 1/num sum_j weights[:, j] [labels[:, j] = l] in each row of (M, J): in closed form
    where a row holds at most two labels (a boundary between two structures, most rows), else by sorting the row."""
    low, high = torch.aminmax(labels, dim=1)
    is_high = labels == high[:, None]
    two = (is_high | (labels == low[:, None])).all(1)
    p = (weights * is_high).sum(1) / num
    entropy = -torch.xlogy(p, p) - torch.xlogy(1 - p, 1 - p)
    entropy = torch.where(low == high, 0.0, entropy).clamp_min(0)  # one label: p = 1
    rows = (~two).nonzero()[:, 0]
    entropy[rows] = _sorted_entropy(labels[rows], weights[rows], num)
    return entropy


def _sorted_entropy(labels: Tensor, weights: Tensor, num: int) -> Tensor:
    """:func:`_run_entropy` of rows sorted by label: the weights of each run of one label added up."""
    ordered, order = labels.sort(dim=1)
    start = torch.ones_like(ordered, dtype=torch.bool)  # the first pair of each run of one label
    start[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
    run = start.cumsum(1) - 1
    p = torch.zeros_like(weights).scatter_add_(1, run, weights.gather(1, order)) / num
    return (-torch.xlogy(p, p).sum(1)).clamp_min(0)  # weights summing to 1 + rounding


class PartialVolumeLabels:
    """The partial-volume label distribution of ``labels`` (1, 1, *S) integer labels (2-d or 3-d) pulled by posterior
    samples: :meth:`add` each sample's displacement (1, D, *S) (voxels of S, pull-back: voxel x reads
    ``labels`` at x + displacement[x]), then :meth:`entropy` (*S) in nats: 0 where every sample reads one label
    wholly, at most log of the number of labels."""

    def __init__(self, labels: Tensor) -> None:
        labels = plain_tensor(labels)
        if labels.ndim not in (4, 5) or labels.shape[:2] != (1, 1):
            raise ValueError(f"expected labels (1, 1, *S), 2-d or 3-d; got shape {tuple(labels.shape)}")
        if labels.is_floating_point():  # a label map loaded as floats, as warp_labels takes it
            if not torch.equal(labels, labels.round()):
                raise ValueError("labels must hold integer values; got non-integer floats")
            labels = labels.round().long()
        if int(labels.min()) < 0 or int(labels.max()) >= LABEL_LIMIT:
            raise ValueError(f"labels must lie in [0, {LABEL_LIMIT}); got [{int(labels.min())}, {int(labels.max())}]")
        self.shape = tuple(int(n) for n in labels.shape[2:])
        dims = len(self.shape)
        # the labels as their rank among those present (0 stays 0: it is present in the padding): the histogram of
        # entropy() has one column per label present; found by a count per value (labels lie in [0, LABEL_LIMIT)),
        # no sort of the whole grid as torch.unique makes
        counts = torch.bincount(labels.reshape(-1).long())
        counts[0] += 1
        present = counts.nonzero()[:, 0]
        rank = torch.zeros(int(present.max()) + 1, dtype=torch.int16, device=labels.device)
        rank[present.long()] = torch.arange(present.numel(), dtype=torch.int16, device=labels.device)
        self._count = present.numel()
        labels = rank[labels.long()]
        # one voxel of label 0 below and two above: every corner of a point clamped to [-1, S] along each axis lies
        # inside the padded grid, and reads label 0 outside the labels' own
        padded = F.pad(labels, (1, 2) * dims)[0, 0]
        self._padded = padded.reshape(-1)
        self._strides = [int(torch.tensor(padded.shape[k + 1 :]).prod()) for k in range(dims)]
        self._corners = [[(corner >> (dims - 1 - k)) & 1 for k in range(dims)] for corner in range(2**dims)]
        self._low, self._high, self._upper = self._cell_tables(padded)
        # bit c of a mask (rows) as a float per corner c (columns)
        self._bits = ((torch.arange(256)[:, None] >> torch.arange(2**dims)) & 1).float().to(labels.device)
        # label + 1 where the cell whose lowest corner is a voxel holds one label, else 0, for the cells from -1 to S
        # along each axis (corners outside the grid read 0): one nearest read of it half a voxel below a sampled
        # point p reads the cell of floor(p) (at a tie, p on a voxel, a cell with p as a corner: the same label), so it
        # says whether p's cell holds one label, and which; beyond the table the outermost cell is read (the border),
        # which holds one label only where every cell further out holds label 0 too
        outer = tuple(slice(0, n + 2) for n in self.shape)
        low, high = (table.view(padded.shape)[outer] for table in (self._low, self._high))
        self._whole = torch.where((low == high) & (low >= 0), low + 1, 0).float()[None, None]
        self._shifted: Tensor | None = None  # each sample's displacement minus half a voxel
        self._range: tuple[Tensor, Tensor] | None = None  # the lowest and highest of the whole reads (+ 1) so far
        self._pure: list[Tensor] = []  # per sample (*S) int16: the label + 1 read wholly, 0 where the cell held more
        # per sample, the voxels whose cell held several labels (n,), its lower and higher label (-1: three or more)
        # and the higher one's weight
        self._pairs: list[tuple[Tensor, Tensor, Tensor, Tensor]] = []
        self._many: list[tuple[Tensor, Tensor, Tensor]] = []  # per sample: the voxels of three labels or more (m,),
        # the labels (2^D, m) and weights of their corners

    def _cell_tables(self, padded: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Per cell of ``padded`` (indexed by its lowest corner, flat): its lower and higher label (int16; -1 and -1
        where it holds three labels or more) and a mask of the corners holding the higher one (uint8, bit c for
        corner c). The last plane of each axis starts no clamped point's cell: -1 there."""
        views = [padded[tuple(slice(u, n - 1 + u) for u, n in zip(upper, padded.shape))] for upper in self._corners]
        low, high = views[0].clone(), views[0].clone()
        for view in views[1:]:
            torch.minimum(low, view, out=low)
            torch.maximum(high, view, out=high)
        two = torch.ones_like(low, dtype=torch.bool)
        upper = torch.zeros_like(low, dtype=torch.uint8)
        for corner, view in enumerate(views):
            is_high = view == high
            two &= is_high | (view == low)
            upper |= is_high.to(torch.uint8) << corner
        inner = tuple(slice(0, n - 1) for n in padded.shape)
        tables = []
        for table, value in ((low, -1), (high, -1), (upper, 0)):
            whole = torch.full(padded.shape, value, dtype=table.dtype, device=padded.device)
            whole[inner] = torch.where(two, table, torch.full_like(table, value))
            tables.append(whole.reshape(-1))
        return tables[0], tables[1], tables[2]

    def add(self, displacement: Tensor) -> None:
        """Read the labels at the points of one sampled displacement (1, D, *S)."""
        dims = len(self.shape)
        if tuple(displacement.shape) != (1, dims, *self.shape):
            raise ValueError(
                f"expected a displacement (1, {dims}, {', '.join(map(str, self.shape))}) on the labels' grid; got "
                f"{tuple(displacement.shape)}"
            )
        displacement = plain_tensor(displacement).float()
        if self._shifted is None:  # one buffer for every sample: a fresh field of this size costs its page faults
            self._shifted = torch.empty_like(displacement)
        torch.sub(displacement, 0.5, out=self._shifted)
        # the table's voxel 1 is the grid's voxel 0 (the cell from -1)
        grid = sampling_grid(self._shifted, [1] * dims, [n + 2 for n in self.shape])
        pure = split_grid_sample(self._whole, grid, "nearest", "border")[0, 0].to(torch.int16)
        del grid
        coordinates = (pure == 0).nonzero()  # (n, D): the voxels whose cell holds several labels (or read at a tie)
        voxels = coordinates[:, 0]
        for k in range(1, dims):
            voxels = voxels * self.shape[k] + coordinates[:, k]
        flat = displacement[0].reshape(dims, -1)
        point = [(flat[k][voxels] + coordinates[:, k]).clamp(-1, self.shape[k]) for k in range(dims)]
        base = [p.floor() for p in point]
        index = sum((b.long() + 1) * s for b, s in zip(base, self._strides))
        # (a cell of one label here, read at a tie on the cell below, gives two pairs of the same label: exact too)
        low, high = self._low[index], self._high[index]
        weights = torch.ones(1, voxels.numel(), device=voxels.device)  # (2^D, n) linear interpolation's, per corner
        for k in range(dims):
            fraction = point[k] - base[k]
            weights = (weights[:, None] * torch.stack([1 - fraction, fraction])[None]).reshape(2 ** (k + 1), -1)
        higher = (weights * self._bits[self._upper[index].long()].T).sum(0)
        many = (low < 0).nonzero()[:, 0]
        corners = [
            self._padded[index[many] + sum(u * s for u, s in zip(upper, self._strides))] for upper in self._corners
        ]
        if self._range is None:
            self._range = (pure.clone(), pure.clone())
        else:
            torch.minimum(self._range[0], pure, out=self._range[0])
            torch.maximum(self._range[1], pure, out=self._range[1])
        self._pure.append(pure.view(-1))
        self._pairs.append((voxels, low, high, higher))
        self._many.append((voxels[many], torch.stack(corners), weights[:, many]))

    def entropy(self) -> Tensor:
        """(*S) float32, nats, of the samples added so far (at least one)."""
        if self._range is None:
            raise ValueError("no sample was added: add() at least one displacement first")
        low, high = (r.view(-1) for r in self._range)
        size = low.numel()
        many = torch.zeros(size, dtype=torch.bool, device=low.device)
        for voxels, _, _ in self._many:
            many[voxels] = True
        entropy = torch.zeros(size, device=low.device)  # 0 where every sample read one label wholly, the same
        rows = (((low != high) | (low == 0)) & ~many).nonzero()[:, 0]
        entropy[rows] = self._pair_entropy(rows)
        rows = many.nonzero()[:, 0]
        entropy[rows] = self._histogram_entropy(rows)
        return entropy.reshape(self.shape)

    @staticmethod
    def _position(rows: Tensor, size: int) -> Tensor:
        """Each voxel's row among ``rows``, or len(rows) (a spare row) for the others."""
        position = torch.full((size,), rows.numel(), dtype=torch.long, device=rows.device)
        position[rows] = torch.arange(rows.numel(), device=rows.device)
        return position

    def _pair_entropy(self, rows: Tensor) -> Tensor:
        """The entropy at ``rows``, where no sample read a cell of three labels or more: two (label, weight) pairs a
        sample per voxel."""
        num, count, device = len(self._pure), rows.numel(), rows.device
        labels = torch.empty(num, 2, count + 1, dtype=torch.int16, device=device)
        for k, pure in enumerate(self._pure):  # the label read wholly (-1 where the cell held several)
            labels[k, :, :count] = pure[rows] - 1
        weights = torch.zeros(num, 2, count + 1, device=device)
        weights[:, 0] = 1
        position = self._position(rows, self._pure[0].numel())
        for k, (voxels, low, high, higher) in enumerate(self._pairs):
            at = position[voxels]
            labels[k, 0, at], labels[k, 1, at] = low, high
            weights[k, 0, at], weights[k, 1, at] = 1 - higher, higher
        labels = labels[:, :, :count].permute(2, 0, 1).reshape(count, 2 * num)
        weights = weights[:, :, :count].permute(2, 0, 1).reshape(count, 2 * num)
        return _run_entropy(labels, weights, num)

    def _histogram_entropy(self, rows: Tensor) -> Tensor:
        """The entropy at ``rows``, where some sample read a cell of three labels or more: a histogram over the
        labels present."""
        num, count, device = len(self._pure), self._count, rows.device
        position = self._position(rows, self._pure[0].numel())
        histogram = torch.zeros((rows.numel() + 1) * count, device=device)  # the spare row last
        for k, pure in enumerate(self._pure):
            reads = pure[rows].long()
            at = torch.where(reads > 0, torch.arange(rows.numel(), device=device), rows.numel())
            histogram.index_add_(0, at * count + (reads - 1).clamp_min(0), torch.ones_like(at, dtype=torch.float))
            voxels, low, high, higher = self._pairs[k]
            at = torch.where(low >= 0, position[voxels], rows.numel()) * count
            histogram.index_add_(0, at + low.clamp_min(0), 1 - higher)
            histogram.index_add_(0, at + high.clamp_min(0), higher)
            voxels, corner_labels, weights = self._many[k]
            at = position[voxels] * count
            for labels, weight in zip(corner_labels, weights):
                histogram.index_add_(0, at + labels, weight)
        p = histogram.view(-1, count)[:-1] / num
        return (-torch.xlogy(p, p).sum(1)).clamp_min(0)  # weights summing to 1 + rounding
