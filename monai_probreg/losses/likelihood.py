"""Image likelihood terms: the paper's Gaussian ``1/(2 sigma^2) ||fixed - warped||^2`` and MONAI's LNCC
(:mod:`monai_probreg.losses.lncc`).

``-log N(fixed; warped, sigma^2 I) = 1/(2 sigma^2) ||fixed - warped||^2 + const`` (paper Eq. 2 and 5, K = 1 sample).
Reduction ``"mean"`` divides the sum by the number of elements (B * C * N), ``"sum"`` keeps it.
"""

from __future__ import annotations

from torch import Tensor, nn

from monai_probreg.losses.lncc import BoxLNCCLoss
from monai_probreg.losses.mind import MINDLoss

__all__ = ["IMAGE_LOSSES", "GaussianImageLoss", "gaussian_image_loss", "make_image_loss"]


def gaussian_image_loss(warped: Tensor, fixed: Tensor, image_sigma: float, reduction: str = "mean") -> Tensor:
    """Negative Gaussian log-likelihood (no constant); ``warped`` and ``fixed`` (B, C, *S)."""
    if warped.shape != fixed.shape:
        raise ValueError(
            f"warped and fixed must have the same shape; got {tuple(warped.shape)} and {tuple(fixed.shape)}"
        )
    if image_sigma <= 0:
        raise ValueError(f"image_sigma must be > 0; got {image_sigma}")
    sq = (fixed - warped).pow(2)
    if reduction == "mean":
        sq_total = sq.mean()
    elif reduction == "sum":
        sq_total = sq.sum()
    else:
        raise ValueError(f"reduction must be 'mean' or 'sum'; got {reduction!r}")
    return sq_total / (2.0 * image_sigma**2)


class GaussianImageLoss(nn.Module):
    """``nn.Module`` form of :func:`gaussian_image_loss`; ``forward(warped, fixed)``.

    Args:
        image_sigma: std of the additive image noise, in the images' intensity units (here [0, 1]).
        reduction: "mean" or "sum".
    """

    def __init__(self, image_sigma: float, reduction: str = "mean") -> None:
        super().__init__()
        if image_sigma <= 0:
            raise ValueError(f"image_sigma must be > 0; got {image_sigma}")
        self.image_sigma = float(image_sigma)
        self.reduction = reduction

    def forward(self, warped: Tensor, fixed: Tensor) -> Tensor:
        return gaussian_image_loss(warped, fixed, self.image_sigma, self.reduction)


IMAGE_LOSSES = ("gaussian", "lncc", "mind")  # the names make_image_loss accepts


def make_image_loss(
    name: str,
    spatial_dims: int = 3,
    image_sigma: float = 0.04,
    lncc_kernel_size: int = 9,
    reduction: str = "mean",
    mind_radius: int = 1,
    mind_dilation: int = 2,
) -> nn.Module:
    """Build the likelihood term by name: ``"gaussian"`` (the paper's), ``"lncc"`` (MONAI's local NCC with a
    rectangular window, in [-1, 0]; its window sums by pooling, :class:`~monai_probreg.losses.lncc.BoxLNCCLoss`) or
    ``"mind"`` (MIND-SSC descriptors compared, for two contrasts, :class:`~monai_probreg.losses.mind.MINDLoss`; its
    "none" reduction is per voxel, (B, 1, *S))."""
    if name == "gaussian":
        return GaussianImageLoss(image_sigma=image_sigma, reduction=reduction)
    if name == "lncc":
        return BoxLNCCLoss(spatial_dims=spatial_dims, kernel_size=lncc_kernel_size, reduction=reduction)
    if name == "mind":
        return MINDLoss(radius=mind_radius, dilation=mind_dilation, reduction=reduction)
    raise ValueError(f"image loss must be one of {IMAGE_LOSSES}; got {name!r}")
