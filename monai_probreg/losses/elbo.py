"""The training objective: negative ELBO (image likelihood + KL to the Laplacian prior), optionally a label term.

``total = image_weight * image + kl + label_weight * label`` where

- ``image`` is the likelihood term of the warped moving image against the fixed one; in bidirectional
  mode it is ``0.5 * L(warped, fixed) + 0.5 * L(warped_fixed, moving)`` (the journal extension's weights);
- ``kl`` is :func:`~monai_probreg.losses.kl.laplacian_kl` on the posterior parameters;
- ``label`` (semi-supervised variant) is MONAI's ``DiceLoss`` between the moving one-hot labels warped with
  linear interpolation and the fixed one-hot labels; 0 when no labels are given or ``label_weight == 0``.

Reductions: with ``reduction="mean"`` the image term is a per-image-voxel mean and the KL a per-velocity-
voxel mean, so relative to the summed ELBO the KL is weighted by ``int_downsize ** spatial_dims``; use
``"sum"`` for the exact ELBO. Either way sigma and lambda are tuned for the reduction in use.
"""

from __future__ import annotations

from typing import NamedTuple

from monai.losses import DiceLoss
from torch import Tensor, nn

from monai_probreg.blocks.warp import warp_one_hot
from monai_probreg.losses.kl import LaplacianKLLoss
from monai_probreg.losses.likelihood import make_image_loss
from monai_probreg.networks.probreg_net import RegistrationOutput

__all__ = ["LossTerms", "ProbRegLoss"]


class LossTerms(NamedTuple):
    """Scalars: ``total`` to back-propagate, and its parts (unweighted) for logging."""

    total: Tensor
    image: Tensor
    kl: Tensor
    label: Tensor


class ProbRegLoss(nn.Module):
    """Negative ELBO of the probabilistic registration model.

    Args:
        image_loss: "gaussian" (paper) or "lncc" (MONAI local normalised cross-correlation).
        image_sigma: Gaussian noise std (intensity units); ignored for "lncc".
        prior_lambda: precision scale lambda of the Laplacian prior.
        The defaults (sigma 0.04, lambda 10) are the bundle's first choice for LPBA40-like T1 scans in [0, 1] with an
        80x96x80 network grid and ``reduction="mean"``; the paper's sigma = 0.035, lambda = 70000 belong to another
        integration convention and normalisation and are not comparable (see ``kl.py`` for conversions).
        image_weight: multiplies the image term (1 for the paper's Gaussian; tune it for LNCC).
        label_weight: weight of the Dice term (0 = unsupervised, as in the paper).
        spatial_dims, lncc_kernel_size, reduction: see the module docstring.
    """

    def __init__(
        self,
        image_loss: str = "gaussian",
        image_sigma: float = 0.04,
        prior_lambda: float = 10.0,
        image_weight: float = 1.0,
        label_weight: float = 0.0,
        spatial_dims: int = 3,
        lncc_kernel_size: int = 9,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        if label_weight < 0 or image_weight < 0:
            raise ValueError(f"weights must be >= 0; got image_weight={image_weight}, label_weight={label_weight}")
        self.image_loss = make_image_loss(image_loss, spatial_dims, image_sigma, lncc_kernel_size, reduction)
        self.kl_loss = LaplacianKLLoss(prior_lambda, reduction)
        self.dice_loss = DiceLoss(include_background=False, reduction="mean")
        self.image_weight = float(image_weight)
        self.label_weight = float(label_weight)

    def forward(
        self,
        output: RegistrationOutput,
        moving: Tensor,
        fixed: Tensor,
        moving_one_hot: Tensor | None = None,
        fixed_one_hot: Tensor | None = None,
    ) -> LossTerms:
        image = self.image_loss(output.warped, fixed)
        if output.warped_fixed is not None:
            image = 0.5 * image + 0.5 * self.image_loss(output.warped_fixed, moving)
        kl = self.kl_loss(output.velocity_mean, output.velocity_log_var)
        label = image.new_zeros(())
        if self.label_weight > 0:
            if moving_one_hot is None or fixed_one_hot is None:
                raise ValueError("label_weight > 0 needs moving_one_hot and fixed_one_hot (B, L, *S)")
            if moving_one_hot.shape != fixed_one_hot.shape:
                raise ValueError(
                    f"one-hot label maps must match; got {tuple(moving_one_hot.shape)} and {tuple(fixed_one_hot.shape)}"
                )
            label = self.dice_loss(warp_one_hot(moving_one_hot, output.displacement), fixed_one_hot)
        total = self.image_weight * image + kl + self.label_weight * label
        return LossTerms(total=total, image=image, kl=kl, label=label)
