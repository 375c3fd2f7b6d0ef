"""Test-time refinement ("instance optimisation") of the posterior mean for the pair at hand.

The network's posterior mean is amortised: one forward pass, whatever the pair. A few gradient steps on the model's
own objective, started from that mean, align the pair at hand better (uniGradICON's instance optimisation; our
measurements: README "Accuracy"). Over the velocity mean ``mu`` on the model's velocity grid we minimise the terms of
the negative ELBO that depend on it (:class:`~monai_probreg.losses.elbo.ProbRegLoss`, ``reduction="mean"``):

    L(mu) = ||fixed - moving o exp(mu)||^2 / (2 sigma^2) / N_image  +  lambda / 2 * mu^T L mu / N_velocity
            + posterior_weight / 2 * mean((mu - mu_net)^2 / sigma_net^2)

with Adam, on the grid the network sees (its ``network_size``, else the input grid). The last term
keeps ``mu`` near the network's estimate in units of the network's posterior std; with it, the refined fields
keep the network's 0 folded voxels where the prior alone lets a few fold. The log-variance stays the
network's, so the uncertainty maps (samples, entropy) are centred on the refined mean. Written by hand: no MONAI or
ITK block optimises a stationary velocity field of a trained model against a pair.

Off by default (``num_iterations = 0``): the bundle's ``refine_iterations`` and the command line's ``--refine``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from monai_probreg.blocks.warp import warp_image
from monai_probreg.losses.elbo import ProbRegLoss
from monai_probreg.networks.probreg_net import ProbRegNet, RegistrationOutput

__all__ = ["RefinementSettings", "refine_registration"]


@dataclass(frozen=True)
class RefinementSettings:
    """How the posterior mean is refined for one pair (values chosen on training pairs, README "Accuracy").

    num_iterations: Adam steps (0 = no refinement, the network's mean as it is).
    learning_rate: Adam's step size, in velocity-grid voxels.
    image_sigma: std of the Gaussian image noise, intensities in [0, 1] (the training value of the shipped model).
    prior_lambda: precision scale of the Laplacian prior, velocity-grid voxel units (larger = smoother, fewer folds).
    posterior_weight: weight of the pull towards the network's mean, in units of its posterior std (0 = none).
    """

    num_iterations: int = 0
    learning_rate: float = 0.1
    image_sigma: float = 0.04
    prior_lambda: float = 1.5
    posterior_weight: float = 1.0

    def __post_init__(self) -> None:
        n = self.num_iterations
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"num_iterations must be an integer >= 0; got {n!r}")
        for name in ("learning_rate", "image_sigma", "prior_lambda"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
                raise ValueError(f"{name} must be a number > 0; got {value!r}")
        w = self.posterior_weight
        if not isinstance(w, (int, float)) or isinstance(w, bool) or not w >= 0:
            raise ValueError(f"posterior_weight must be a number >= 0; got {w!r}")

    @property
    def enabled(self) -> bool:
        return self.num_iterations > 0

    def as_dict(self) -> dict[str, float]:
        """The settings by name, for summaries."""
        return asdict(self)


def _on_grid(image: Tensor, size: tuple[int, ...]) -> Tensor:
    """``image`` resized (linear, align corners) to ``size``, as the network resizes its inputs."""
    if tuple(image.shape[2:]) == size:
        return image
    mode = "trilinear" if image.ndim == 5 else "bilinear"
    return F.interpolate(image, size=size, mode=mode, align_corners=True)


def refine_registration(network: ProbRegNet, moving: Tensor, fixed: Tensor, output: RegistrationOutput,
                        settings: RefinementSettings) -> RegistrationOutput:
    """Refine ``output.velocity_mean`` (from ``network(moving, fixed)`` in eval mode) for this pair.

    Shapes: moving, fixed (B, C, *S) as given to the network; returns a :class:`RegistrationOutput` on the same grids
    with ``velocity = velocity_mean`` = the refined mean and ``displacement``, ``warped`` (and the inverse fields of a
    bidirectional network) recomputed from it; ``velocity_log_var`` is the network's. The network is not changed.
    Gradients are needed, so it cannot run under ``torch.inference_mode()``.
    """
    if not settings.enabled:
        return output
    if torch.is_inference_mode_enabled():
        raise RuntimeError("refine_registration needs gradients; call it outside torch.inference_mode()")
    if moving.shape != fixed.shape:
        raise ValueError(f"moving and fixed must have the same shape; got {tuple(moving.shape)} and "
                         f"{tuple(fixed.shape)}")
    if output.velocity_mean.shape[0] != moving.shape[0]:
        raise ValueError(f"output is for a batch of {output.velocity_mean.shape[0]}; got images of batch "
                         f"{moving.shape[0]}")
    size = tuple(network.network_size or moving.shape[2:])
    loss_fn = ProbRegLoss(image_loss="gaussian", image_sigma=settings.image_sigma, prior_lambda=settings.prior_lambda,
                          spatial_dims=moving.ndim - 2)
    # clones: tensors made under inference_mode cannot enter autograd; the images are constants here
    start = output.velocity_mean.detach().clone().float()
    log_var = output.velocity_log_var.detach().clone().float()
    moving_small, fixed_small = (_on_grid(t.detach().clone().float(), size) for t in (moving, fixed))
    velocity = start.clone().requires_grad_(True)
    optimiser = torch.optim.Adam([velocity], lr=settings.learning_rate)
    with torch.enable_grad():
        for _ in range(settings.num_iterations):
            optimiser.zero_grad(set_to_none=True)
            displacement = network.velocity_to_displacement(velocity, size)
            warped = warp_image(moving_small, displacement, padding_mode=network.padding_mode,
                                fast=network.fast_sampling)
            step = RegistrationOutput(warped, displacement, velocity, velocity, log_var, None, None)
            loss = loss_fn(step, moving_small, fixed_small).total
            if settings.posterior_weight > 0:  # (mu - mu_net)^2 / sigma_net^2, mean over the velocity grid
                pull = ((velocity - start).square() * log_var.neg().exp()).mean()
                loss = loss + 0.5 * settings.posterior_weight * pull
            loss.backward()
            optimiser.step()
    with torch.no_grad():
        mean = velocity.detach()
        full = moving.shape[2:]
        displacement = network.velocity_to_displacement(mean, full)
        warped = warp_image(moving, displacement, padding_mode=network.padding_mode, fast=network.fast_sampling)
        inverse = warped_fixed = None
        if output.inverse_displacement is not None:
            inverse = network.velocity_to_displacement(-mean, full)
            warped_fixed = warp_image(fixed, inverse, padding_mode=network.padding_mode, fast=network.fast_sampling)
    return RegistrationOutput(warped, displacement, mean, mean, output.velocity_log_var, inverse, warped_fixed)
