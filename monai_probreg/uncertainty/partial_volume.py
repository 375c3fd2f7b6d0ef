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
voxel: a cube of one label around the voxel nearest to the sampled point means the whole cell around the point holds
that label (one nearest-neighbour read of a precomputed map gives both), and only the other voxels, those whose point
falls near a boundary, keep their 2^D (label, weight) pairs. Written by hand: no library reads a label map with
interpolation weights per label.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from monai_probreg.blocks.warp import warp_labels
from monai_probreg.uncertainty.entropy import label_entropy
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["LABEL_LIMIT", "PartialVolumeLabels"]

LABEL_LIMIT = (1 << 15) - 1  # labels are kept as int16, the whole reads as label + 1


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
        # entropy() has one column per label present
        present = torch.unique(torch.cat([labels.reshape(-1), labels.new_zeros(1)]))
        rank = torch.zeros(int(present.max()) + 1, dtype=torch.int32, device=labels.device)
        rank[present.long()] = torch.arange(present.numel(), dtype=torch.int32, device=labels.device)
        self._count = present.numel()
        labels = rank[labels.long()]
        # one voxel of label 0 below and two above: every corner of a point clamped to [-1, S] along each axis lies
        # inside the padded grid, and reads label 0 outside the labels' own
        padded = F.pad(labels, (1, 2) * dims)[0, 0]
        self._padded = padded.reshape(-1)
        self._strides = [int(torch.tensor(padded.shape[k + 1 :]).prod()) for k in range(dims)]
        # label + 1 where the cube of 3^D voxels around a voxel (zeros outside the grid) holds one label, else 0: one
        # nearest read of it at a sampled point says whether the cell around the point holds one label, and which
        around = F.pad(labels.float(), (1, 1) * dims)
        pool = F.max_pool3d if dims == 3 else F.max_pool2d
        one_label = pool(around, 3, 1) == -pool(-around, 3, 1)
        self._cube = torch.where(one_label, labels + 1, torch.zeros_like(labels)).to(torch.int32)
        self._pure: list[Tensor] = []  # per sample (*S): the label + 1 read wholly, 0 where the cell holds several
        self._mixed: list[tuple[Tensor, Tensor, Tensor]] = []  # per sample: voxels (n,), labels (2^D, n), weights

    def add(self, displacement: Tensor) -> None:
        """Read the labels at the points of one sampled displacement (1, D, *S)."""
        dims = len(self.shape)
        if tuple(displacement.shape) != (1, dims, *self.shape):
            raise ValueError(
                f"expected a displacement (1, {dims}, {', '.join(map(str, self.shape))}) on the labels' grid; got "
                f"{tuple(displacement.shape)}"
            )
        displacement = plain_tensor(displacement).float()
        pure = warp_labels(self._cube, displacement)[0, 0]
        voxels = (pure == 0).reshape(-1).nonzero()[:, 0]
        # the exact reading where the cell holds several labels (or lies partly outside the grid)
        point = displacement[0].reshape(dims, -1)[:, voxels]
        index = torch.zeros_like(voxels)
        remainder = voxels.clone()
        for k in range(dims - 1, -1, -1):  # voxel coordinates of the flat indices, last axis first
            point[k] += remainder % self.shape[k]
            remainder = remainder // self.shape[k]
        point = torch.stack([point[k].clamp(-1, self.shape[k]) for k in range(dims)])
        base = point.floor()
        fraction = point - base
        for k in range(dims):
            index += (base[k].long() + 1) * self._strides[k]
        labels, weights = [], []
        for corner in range(2**dims):
            upper = [(corner >> (dims - 1 - k)) & 1 for k in range(dims)]
            weight = torch.ones_like(fraction[0])
            for k in range(dims):
                weight = weight * (fraction[k] if upper[k] else 1 - fraction[k])
            labels.append(self._padded[index + sum(u * s for u, s in zip(upper, self._strides))])
            weights.append(weight)
        self._pure.append(pure.to(torch.int16))
        self._mixed.append((voxels, torch.stack(labels).to(torch.int16), torch.stack(weights)))

    def entropy(self) -> Tensor:
        """(*S) float32, nats, of the samples added so far (at least one)."""
        if not self._pure:
            raise ValueError("no sample was added: add() at least one displacement first")
        num = len(self._pure)
        pure = torch.stack(self._pure).reshape(num, -1)  # (K, N): label + 1 read wholly, or 0
        mixed = torch.zeros(pure.shape[1], dtype=torch.bool, device=pure.device)
        for voxels, _, _ in self._mixed:
            mixed[voxels] = True
        entropy = torch.zeros(pure.shape[1], device=pure.device)
        whole = (~mixed).nonzero()[:, 0]  # every sample read one label wholly: the entropy of K labels
        entropy[whole] = label_entropy(pure[:, whole])
        # the others: a histogram over the labels present, the whole reads with weight 1, the mixed ones with theirs
        where = mixed.nonzero()[:, 0]
        position = torch.full((pure.shape[1],), -1, dtype=torch.long, device=pure.device)
        position[where] = torch.arange(where.numel(), device=pure.device)
        count = self._count
        histogram = torch.zeros(where.numel() * count, device=pure.device)
        rows = torch.arange(where.numel(), device=pure.device) * count
        for k, (voxels, corner_labels, weights) in enumerate(self._mixed):
            reads = pure[k, where]
            read = reads > 0
            ones = torch.ones(int(read.sum()), device=pure.device)
            histogram.index_add_(0, rows[read] + (reads[read] - 1), ones)
            at = position[voxels] * count
            for labels, weight in zip(corner_labels, weights):
                histogram.index_add_(0, at + labels, weight)
        p = histogram.view(-1, count) / num
        entropy[where] = (-(p * p.clamp_min(1e-30).log()).sum(1)).clamp_min(0)  # weights summing to 1 + rounding
        return entropy.reshape(self.shape)
