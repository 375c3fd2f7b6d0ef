"""The full probabilistic diffeomorphic registration model (VoxelMorph-diff, Dalca et al. 2018).

Pipeline: ``VelocityUNet`` -> posterior (mean, log_var) on the velocity grid (input / int_downsize)
-> a velocity z (a reparameterised sample in training, the mean in eval) -> scaling and squaring
(``num_steps`` squarings) on the velocity grid -> displacement resized to the image grid
(align-corners scaling) -> MONAI ``Warp`` of the moving image.

Inference speed levers (on by default, each switchable; off while gradients are recorded or under tracing):
``unet_precision`` and ``channels_last`` (:mod:`monai_probreg.networks.acceleration`), ``fast_sampling``
(:mod:`monai_probreg.blocks.warp`: one-pass sampling grids, a single pair spread over the CPU threads).

Which image goes where (MONAI's convention, the published code's, and ours): the **moving** image is
resampled into the **fixed** image's grid, ``warped[x] = moving[x + displacement[x]]``. In the paper's
generative model ``x ~ N(y o phi_z, sigma^2 I)`` the warped image is ``y`` = our ``moving`` and ``x`` = our
``fixed`` (scan-to-atlas training: moving = subject scan, fixed = atlas).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import List, NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from monai_probreg.blocks.integration import ScalingAndSquaring, resize_displacement
from monai_probreg.blocks.sampling import VelocitySampler, sample_velocity
from monai_probreg.blocks.warp import CachedWarp, warp_image
from monai_probreg.networks.acceleration import accelerated_posterior, unet_autocast_dtype
from monai_probreg.networks.velocity_unet import VelocityPosterior, VelocityUNet
from monai_probreg.utils.tensors import shape_str

__all__ = ["RegistrationOutput", "PosteriorSamples", "ProbRegNet"]


class RegistrationOutput(NamedTuple):
    """What ``ProbRegNet.forward`` returns, whatever the flags (fields not computed are ``None``).

    warped: (B, C, *S) moving image resampled into the fixed grid.
    displacement: (B, D, *S) voxels of the image grid, of ``exp(velocity)``; channel k = tensor axis 2 + k.
    velocity: (B, D, *V) the velocity that was integrated (sample in training, mean in eval), velocity-grid voxels.
    velocity_mean, velocity_log_var: (B, D, *V) posterior parameters (log_var is log sigma^2).
    inverse_displacement: (B, D, *S) of ``exp(-velocity)``, or None unless ``bidirectional``.
    warped_fixed: (B, C, *S) fixed image resampled into the moving grid by ``exp(-velocity)``, or None.
    """

    warped: Tensor
    displacement: Tensor
    velocity: Tensor
    velocity_mean: Tensor
    velocity_log_var: Tensor
    inverse_displacement: Optional[Tensor]  # typing.Optional: TorchScript cannot read "Tensor | None" here
    warped_fixed: Optional[Tensor]


class PosteriorSamples(NamedTuple):
    """K posterior samples: displacements (K, B, D, *S) in image voxels, plus the posterior parameters."""

    displacements: Tensor
    velocity_mean: Tensor
    velocity_log_var: Tensor


class ProbRegNet(nn.Module):
    """Probabilistic diffeomorphic registration network.

    Args:
        spatial_dims: 2 or 3.
        in_channels: channels per image (moving and fixed each).
        enc_channels, dec_channels, int_downsize: see :class:`VelocityUNet`.
        num_steps: scaling-and-squaring steps T (paper: 7).
        bidirectional: also return the inverse displacement and the fixed image warped onto the moving one.
        padding_mode: how the moving image is extrapolated outside its grid ("border", "zeros", "reflection").
        network_size: if given, the UNet sees moving and fixed resized (linear, align corners) to this grid, and
            the displacement is resized back to the input grid, so a model trained at reduced resolution
            registers images of any size on their own grid. None: the UNet runs on the input grid.
        unet_precision: ``"auto"`` (bf16 autocast for the UNet on CPUs with native bf16, float32 elsewhere),
            ``"bf16"`` or ``"fp32"``; integration and warp always run in float32. Inference only.
        channels_last: run the 3-d UNet in ``channels_last_3d`` memory format. Inference only.
        fast_sampling: one-pass sampling grids and threaded ``grid_sample`` in the integration and the warps
            (float32 rounding away from MONAI's ``Warp``); False: MONAI's ``Warp.forward`` as it is.
    """

    def __init__(
        self,
        spatial_dims: int = 3,
        in_channels: int = 1,
        enc_channels: Sequence[int] = (16, 32, 32, 32),
        dec_channels: Sequence[int] = (32, 32, 32, 32, 16),
        int_downsize: int = 2,
        num_steps: int = 7,
        bidirectional: bool = False,
        padding_mode: str = "border",
        network_size: Sequence[int] | None = None,
        unet_precision: str = "auto",
        channels_last: bool = True,
        fast_sampling: bool = True,
    ) -> None:
        super().__init__()
        unet_autocast_dtype(unet_precision, "cpu")  # validates the name
        self.unet_precision = unet_precision
        self.channels_last = channels_last
        self.spatial_dims = spatial_dims
        self.bidirectional = bidirectional
        self.padding_mode = padding_mode
        self.network_size = network_size
        self.enc_channels = tuple(int(c) for c in enc_channels)
        self.dec_channels = tuple(int(c) for c in dec_channels)
        self.unet = VelocityUNet(
            spatial_dims=spatial_dims,
            in_channels=2 * in_channels,
            enc_channels=enc_channels,
            dec_channels=dec_channels,
            int_downsize=int_downsize,
        )
        self.sampler = VelocitySampler()
        self.integrate = ScalingAndSquaring(num_steps=num_steps, fast=fast_sampling)
        # the warp of the moving image under torch.jit.script (eager: warp_image's shared layers, same arithmetic)
        self.warp_layer = CachedWarp(mode="bilinear", padding_mode=padding_mode, fast=fast_sampling)

    # Python-only settings: torch.jit.script compiles forward without them (it reads _resize_inputs and
    # _network_grid; never an empty list, whose element type TorchScript could not infer)
    __jit_unused_properties__ = ["fast_sampling", "network_size"]

    @property
    def network_size(self) -> tuple[int, ...] | None:
        """Grid the UNet sees (settable; None: the input grid)."""
        return tuple(self._network_grid) if self._resize_inputs else None

    @network_size.setter
    def network_size(self, value: Sequence[int] | None) -> None:
        grid = [int(n) for n in value] if value is not None else []
        if value is not None and len(grid) != self.spatial_dims:
            raise ValueError(f"network_size must have {self.spatial_dims} entries; got {value}")
        self._resize_inputs = value is not None
        self._network_grid = grid if value is not None else [0]

    @property
    def fast_sampling(self) -> bool:
        """Whether the integration and the warps take the fast sampling path (settable)."""
        return self.integrate.warp_layer.fast

    @fast_sampling.setter
    def fast_sampling(self, value: bool) -> None:
        self.integrate.warp_layer.fast = bool(value)

    def velocity_to_displacement(self, velocity: Tensor, spatial_size: List[int]) -> Tensor:
        """Integrate a velocity (B, D, *V) on its grid and resize the displacement to ``spatial_size``."""
        return resize_displacement(self.integrate(velocity), spatial_size)

    def posterior(self, moving: Tensor, fixed: Tensor) -> VelocityPosterior:
        """q(z | moving, fixed) on the velocity grid, resizing the inputs to ``network_size`` first if set."""
        if moving.shape != fixed.shape:
            raise ValueError(
                "moving and fixed must have the same shape; got "
                + shape_str(moving.shape)
                + " and "
                + shape_str(fixed.shape)
            )
        grid = self._network_grid
        if self._resize_inputs and list(moving.shape[2:]) != grid:
            mode = "trilinear" if self.spatial_dims == 3 else "bilinear"
            moving = F.interpolate(moving, size=grid, mode=mode, align_corners=True)
            fixed = F.interpolate(fixed, size=grid, mode=mode, align_corners=True)
        if torch.jit.is_scripting():  # TorchScript (bundle ckpt_export): the plain float32 path
            return self.unet(moving, fixed)
        if torch.is_grad_enabled() or torch.jit.is_tracing():  # training, export: the plain float32 path
            return self.unet(moving, fixed)
        return self._accelerated_posterior(moving, fixed)

    @torch.jit.unused
    def _accelerated_posterior(self, moving: Tensor, fixed: Tensor) -> VelocityPosterior:
        return accelerated_posterior(self.unet, moving, fixed, self.unet_precision, self.channels_last)

    def forward(self, moving: Tensor, fixed: Tensor) -> RegistrationOutput:
        posterior = self.posterior(moving, fixed)
        velocity = self.sampler(posterior.mean, posterior.log_var)
        size = moving.shape[2:]
        displacement = self.velocity_to_displacement(velocity, size)
        warped = self._warp(moving, displacement)
        inverse: Optional[Tensor] = None
        warped_fixed: Optional[Tensor] = None
        if self.bidirectional:
            inverse = self.velocity_to_displacement(-velocity, size)
            warped_fixed = self._warp(fixed, inverse)
        return RegistrationOutput(
            warped=warped,
            displacement=displacement,
            velocity=velocity,
            velocity_mean=posterior.mean,
            velocity_log_var=posterior.log_var,
            inverse_displacement=inverse,
            warped_fixed=warped_fixed,
        )

    def _warp(self, image: Tensor, ddf: Tensor) -> Tensor:
        if torch.jit.is_scripting():
            return self.warp_layer(image, ddf)
        return warp_image(image, ddf, padding_mode=self.padding_mode, fast=self.fast_sampling)

    @torch.no_grad()
    def sample(
        self,
        moving: Tensor,
        fixed: Tensor,
        num_samples: int,
        generator: torch.Generator | None = None,
        samples_per_batch: int | None = None,
    ) -> PosteriorSamples:
        """Draw ``num_samples`` velocities from q(z | moving, fixed) and integrate them.

        The UNet runs once; all K velocities are drawn at once (so the result does not depend on the batching) and
        integrated ``samples_per_batch`` at a time. None (default): all K in one batch on a GPU, one at a time on a
        CPU, where ``benchmarks/speed_compare.py`` measures the fused batch slower (docs/speed.md). Independent of
        train/eval mode. Shapes: moving, fixed (B, C, *S) -> displacements (K, B, D, *S).
        """
        if samples_per_batch is not None and (
            isinstance(samples_per_batch, bool) or not isinstance(samples_per_batch, int) or samples_per_batch < 1
        ):
            raise ValueError(f"samples_per_batch must be a positive integer or None; got {samples_per_batch!r}")
        posterior = self.posterior(moving, fixed)
        z = sample_velocity(posterior.mean, posterior.log_var, num_samples, generator=generator)
        k, b = z.shape[:2]
        if samples_per_batch is None:
            samples_per_batch = k if moving.device.type == "cuda" else 1
        flat = z.flatten(0, 1)
        step = samples_per_batch * b
        disp = torch.cat(
            [self.velocity_to_displacement(flat[i : i + step], moving.shape[2:]) for i in range(0, k * b, step)]
        )
        return PosteriorSamples(disp.unflatten(0, (k, b)), posterior.mean, posterior.log_var)
