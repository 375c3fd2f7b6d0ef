"""KL divergence between the diagonal velocity posterior and the Laplacian smoothness prior (paper Eq. 5).

Written here because no library offers it. With the prior ``p(z) = N(0, (lambda L)^-1)``, ``L = D - A``
the graph Laplacian of the 2*spatial_dims-neighbour voxel grid (per velocity component), and
``q(z) = N(mu, diag(sigma^2))``::

    KL = 1/2 [ tr(lambda D Sigma - log Sigma) + mu^T (lambda L) mu ] + const
       = 1/2 sum_{c, j} (lambda D_j sigma_cj^2 - log sigma_cj^2) + lambda/2 sum_c sum_{edges (i, j)} (mu_ci - mu_cj)^2

``D_j`` is voxel j's number of in-bounds neighbours (6 inside a 3D grid, 5 on faces, 4 on edges, 3 at
corners); every undirected edge counts once in the smoothness sum (``mu^T L mu``). The constant
(``-1/2 log|lambda L| - n/2``) does not depend on the network and is dropped. The optimum over sigma
is ``sigma_j^2 = 1 / (lambda D_j)``.

Normalisation (``reduction``): ``"sum"`` is the KL above summed over the batch; ``"mean"`` divides it by
``B * N`` with N the number of voxels of the velocity grid (a per-voxel KL, components summed).

Conversion from the VoxelMorph code (``prior_lambda`` = lambda_v, ``image_sigma`` = sigma_v): its loss is
``mean((x - y)^2) / sigma_v^2 + 1/2 * ndims * (mean(lambda_v D e^s - s) + lambda_v * prec)`` with
``prec = 1/(2 ndims) sum_axes mean(diff^2)``, means over voxels *and* components. Per voxel, its log-variance
term equals ours with ``lambda = lambda_v`` and ``reduction="mean"``; its smoothness term equals ours with
``lambda = lambda_v / (2 * ndims)`` (up to the (n-1)/n edge count per axis); its image term equals our
Gaussian term with ``sigma = sigma_v / sqrt(2)`` (its MSE has no 1/2). No single lambda reproduces both of its
prior terms; ours is the paper's KL exactly.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["neighbour_degree", "laplacian_kl", "LaplacianKLLoss"]

_REDUCTIONS = ("mean", "sum")


def neighbour_degree(
    spatial_shape: Sequence[int], dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Per-voxel neighbour count D_j of the axis-aligned grid graph, shape ``spatial_shape``."""
    ndims = len(spatial_shape)
    degree = torch.zeros(tuple(spatial_shape), dtype=dtype, device=device)
    for axis, n in enumerate(spatial_shape):
        per_axis = torch.full((n,), 2.0, dtype=dtype, device=device)
        per_axis[0] -= 1
        per_axis[-1] -= 1  # n == 1 gives 0: a lone voxel has no neighbour along that axis
        shape = [1] * ndims
        shape[axis] = n
        degree = degree + per_axis.view(shape)
    return degree


def laplacian_kl(mean: Tensor, log_var: Tensor, prior_lambda: float, reduction: str = "mean") -> Tensor:
    """KL[q || p] (up to a constant) for ``mean``, ``log_var`` of shape (B, D, *V); returns a scalar."""
    if mean.shape != log_var.shape:
        raise ValueError(
            f"mean and log_var must have the same shape; got {tuple(mean.shape)} and {tuple(log_var.shape)}"
        )
    if mean.ndim < 3:
        raise ValueError(f"expected (B, D, *V) fields; got shape {tuple(mean.shape)}")
    if prior_lambda <= 0:
        raise ValueError(f"prior_lambda must be > 0; got {prior_lambda}")
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}; got {reduction!r}")
    spatial = mean.shape[2:]
    degree = neighbour_degree(spatial, dtype=mean.dtype, device=mean.device)
    sigma_term = (prior_lambda * degree * torch.exp(log_var) - log_var).sum()
    smooth_term = mean.new_zeros(())
    for axis in range(2, mean.ndim):
        diff = torch.diff(mean, dim=axis)
        smooth_term = smooth_term + (diff * diff).sum()
    kl = 0.5 * (sigma_term + prior_lambda * smooth_term)
    if reduction == "mean":
        kl = kl / (mean.shape[0] * spatial.numel())
    return kl


class LaplacianKLLoss(nn.Module):
    """``nn.Module`` form of :func:`laplacian_kl`.

    Args:
        prior_lambda: lambda, the precision scale of the prior (velocity-grid voxel units).
        reduction: "mean" (per velocity-grid voxel) or "sum".
    """

    def __init__(self, prior_lambda: float, reduction: str = "mean") -> None:
        super().__init__()
        if prior_lambda <= 0:
            raise ValueError(f"prior_lambda must be > 0; got {prior_lambda}")
        if reduction not in _REDUCTIONS:
            raise ValueError(f"reduction must be one of {_REDUCTIONS}; got {reduction!r}")
        self.prior_lambda = float(prior_lambda)
        self.reduction = reduction

    def forward(self, mean: Tensor, log_var: Tensor) -> Tensor:
        return laplacian_kl(mean, log_var, self.prior_lambda, self.reduction)
