"""Test-time refinement ("instance optimisation") of the posterior mean for the pair at hand.

The network's posterior mean is amortised: one forward pass, whatever the pair. A few gradient steps on the pair's
own objective, started from that mean, align the pair at hand better (uniGradICON's instance optimisation; measured
by ``benchmarks/accuracy_table.py``, docs/accuracy.md). Over the velocity mean ``mu`` on the model's velocity grid we
minimise (:class:`~monai_probreg.losses.elbo.ProbRegLoss`, ``reduction="mean"``, plus a pull towards the network's
mean):

    L(mu) = image_weight * D(moving o exp(mu), fixed)  +  lambda / 2 * mu^T L mu / N_velocity
            + posterior_weight / 2 * mean((mu - mu_net)^2 / sigma_net^2)

with Adam, the velocity on the network's velocity grid or a finer one (``velocity_grid_factor``), the images compared
on the grid the network sees (its ``network_size``, else the input grid) for the first ``coarse_iterations`` steps
and on a grid ``image_grid_factor`` times finer for the rest (coarse to fine: the coarse steps cost a fraction of the
finer ones; ``benchmarks/refinement_speed.py``). ``D`` is MONAI's local
normalised cross-correlation by default (``image_loss="lncc"``, per-voxel mean in [-1, 0]; it does not assume the two
scans share an intensity scale, and it scored better than the alternative on training pairs), or the model's own
Gaussian likelihood ``||fixed - moving o exp(mu)||^2 / (2 sigma^2) / N_image`` (``"gaussian"``: the terms of the
negative ELBO that depend on ``mu``). The second term is the model's Laplacian smoothness prior; the last keeps ``mu``
near the network's estimate in units of the network's posterior std (the network, trained with labels, knows more
than the intensities of one pair: a weaker pull scored worse on training pairs). The log-variance stays the
network's (resized into the finer grid's units with ``velocity_grid_factor`` > 1), so the uncertainty maps (samples,
entropy) are centred on the refined mean. Written by hand: no MONAI or
ITK block optimises a stationary velocity field of a trained model against a pair.

The fold guard: the optimiser is not bound to a diffeomorphic *discrete* field (scaling and squaring of a rough
velocity can fold between voxels, and the displacement, integrated on the velocity grid, is upsampled 5-6 times to a
whole head's output grid, which can fold where the velocity grid does not). When the refined displacement folds on the
output grid, the change is first given up only around the folded voxels (``fold_local_steps``: the network's mean
there, blended into the refined one over 1, 2, 4, ... velocity cells, :func:`local_blend`), then halved as a whole
(``fold_backtracks`` times at most), and the network's registration itself is returned when nothing is fold-free: a
user asking for refinement never gets a folded warp the network alone would not have given. The folds are few and
local (tens of voxels of a head), so halving the whole change threw away much of the gain on whole-head pairs
(``experiments/refinement_levers.py``, docs/accuracy.md).

Cost-function masks (:class:`RefinementMasks`, ``refine_registration``'s ``masks``; the command's ``--fixed-mask``
and ``--moving-mask``): the image term summed only over the fixed mask's voxels whose warped position falls inside
the moving mask, ``sum(w * d) / N``; None: every voxel, the same computation as before masks existed.

``RefinementSettings()`` does not refine (``num_iterations = 0``): the steps come from the bundle's
``refine_iterations`` and the command line's ``--refine`` (the shipped configs refine; 0 gives the network alone).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from monai.networks.layers.factories import Pool
from torch import Tensor

from monai_probreg.blocks.box_resize import resize_displacement_box
from monai_probreg.blocks.integration import resize_displacement
from monai_probreg.blocks.warp import warp_box, warp_image
from monai_probreg.losses.kl import LaplacianKLLoss
from monai_probreg.losses.likelihood import IMAGE_LOSSES, GaussianImageLoss, make_image_loss
from monai_probreg.losses.lncc import FixedImageLNCC, support_box
from monai_probreg.losses.mind import FixedImageMIND, MINDLoss
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.networks.probreg_net import ProbRegNet, RegistrationOutput
from monai_probreg.spatial.masks import MASK_LEVEL  # a mask resampled linearly is inside where it is at least this
from monai_probreg.uncertainty.quality_features import local_ncc
from monai_probreg.utils.errors import check_integer

__all__ = [
    "LATER_SETTINGS",
    "RefinementMasks",
    "RefinementSettings",
    "local_blend",
    "refine_registration",
]


class RefinementMasks(NamedTuple):
    """Cost-function masks of the refinement's image term (:mod:`monai_probreg.spatial.masks`), on the grid of the
    images given to :func:`refine_registration` (B, 1, *S), 1 inside and 0 outside, or None each.

    ``fixed``: the voxels of the fixed grid where the image term is evaluated; ``moving``: the moving image's mask on
    the same grid (before the deformation), warped with the current displacement at every step (linearly, 0 beyond
    the grid; no gradient through it): a voxel whose warped position falls outside it is left out. On the loss's grid
    (coarser or finer than the images') each mask is resampled linearly and thresholded at :data:`~monai_probreg.spatial.masks.MASK_LEVEL`
    (binary there); the warped moving mask is then fractional across its edge. The image term is
    ``sum(w * d) / N`` over the loss's grid, ``w`` the product of the two and ``d`` the per-voxel term (the local NCC
    by :class:`~monai_probreg.losses.lncc.FixedImageLNCC`'s weights): a voxel inside both counts as without masks.
    Not a :class:`RefinementSettings` field: the settings are the method, recorded in fitted sidecars; the masks are
    the pair's data."""

    fixed: Tensor | None = None
    moving: Tensor | None = None

    def on_grid(self, size: tuple[int, ...]) -> RefinementMasks:
        """Both masks on the loss's grid ``size`` (linear, then :data:`~monai_probreg.spatial.masks.MASK_LEVEL`)."""
        return RefinementMasks(
            *(None if m is None else (_on_grid(m.float(), size) >= MASK_LEVEL).float() for m in self)
        )


@dataclass(frozen=True)
class RefinementSettings:
    """How the posterior mean is refined for one pair (values chosen on training pairs: docs/accuracy.md,
    "Test-time refinement").

    num_iterations: Adam steps (0 = no refinement, the network's mean as it is).
    learning_rate: Adam's step size, in velocity-grid voxels.
    image_sigma: std of the Gaussian image noise, intensities in [0, 1] (the training value of the shipped model).
    prior_lambda: precision scale of the Laplacian prior, velocity-grid voxel units (larger = smoother, fewer folds).
    posterior_weight: weight of the pull towards the network's mean, in units of its posterior std (0 = none).
    image_loss: the image term: "lncc" (MONAI's local normalised cross-correlation over ``lncc_kernel_size``, in
        [-1, 0]; the default: it scored better than "gaussian" on training pairs), "gaussian" (the model's own
        likelihood with ``image_sigma``, unused otherwise) or "mind" (the squared difference of the two images' MIND-SSC
        descriptors, :mod:`monai_probreg.losses.mind`, in [0, 1]: for a pair of different contrasts, where a local
        correlation assumes one contrast).
    image_weight: multiplies the image term (20 for "lncc", chosen on training pairs: a larger weight bought no
        Dice and a rougher field; use 1 with "gaussian", whose values are about two orders of magnitude larger).
    lncc_kernel_size: side of LNCC's local window, in voxels of the loss's grid (odd; 9 = 18 mm on the shipped
        network's 2 mm grid, about 9 mm with ``image_grid_factor`` 2).
    fold_backtracks: the fold guard. If the refined field folds (any |J| <= 0 on the output grid), the refinement's
        change to the network's mean is halved (after the local tries of ``fold_local_steps``), at most this many
        times; if it still folds, the network's mean is kept. With both 0 there is no guard (the refined mean as the
        optimiser left it).
    fold_local_steps: the local fold guard, tried before the halving: the refinement's change is kept everywhere but
        around the folded voxels, where it gives way to the network's mean over 1, 2, 4, ... velocity cells (this many
        tries; 0 = none). The folds of a refined field are few and local (they come from upsampling the displacement
        to the output grid), so halving the whole change threw away most of the gain on whole-head pairs.
    velocity_grid_factor: the refined mean lives on a grid this many times finer than the network's velocity grid
        (1: the network's, 4 mm for the shipped weights; 2: twice finer, the paper's 2 mm). The network's mean and
        log-variance are resized onto it (:func:`resize_log_var`) and the returned ones live there; the images of the
        loss are the network's grid, or the velocity grid when that is finer. 2 measured worse and slower on training
        pairs (``experiments/refinement_levers.py``, docs/accuracy.md). The log-variance is then in the finer grid's
        units, so the velocity entropy is shifted (by 3 log 2 nats for 2 in 3-d) and the calibration, fitted on the
        network's grid, does not apply as it is.
    image_grid_factor: the images of the loss live on a grid this many times finer than the network's (1: its
        ``network_size``; 2: twice finer, at most the images' own grid). The velocity grid does not change; the LNCC
        window (``lncc_kernel_size``) is in voxels of that finer grid. 2 scored higher than 1 on training pairs, most
        on whole-head synthetic ones, at several times the cost of a step (``experiments/refinement_levers.py``,
        docs/accuracy.md); the shipped configs use 2 for their last steps (``coarse_iterations``), which their
        calibration and quality model are fitted for. The dataclass default stays 1, the cheaper form.
    coarse_iterations: of the ``num_iterations`` steps, the first this many compare the images on the network's
        grid (``image_grid_factor`` 1, eight times fewer voxels in 3-d), the rest on the ``image_grid_factor`` grid:
        a coarse-to-fine schedule (0: every step on the finer grid). More coarse steps with the last ones finer kept
        the Dice of every finer step on training pairs and left less of the network's invented displacement on a
        scan onto its own copy, at a fraction of the time (``experiments/refinement_levers.py``, docs/speed.md).
    coarse_lncc_kernel_size: the LNCC window of those coarse steps, in voxels of the network's grid (odd; None:
        ``lncc_kernel_size``, a window ``image_grid_factor`` times wider than the finer grid's).
    symmetric_start: start from (and pull towards) ``(mu(moving, fixed) - mu(fixed, moving)) / 2``, the network's
        mean made antisymmetric in the pair by a second pass with the images swapped (``exp(-v)`` is the inverse
        of ``exp(v)``, so the two directions should be opposite velocities): a scan onto a copy of itself then starts
        from the identity instead of what the network invents there; False: the network's mean as it is.
    adam_eps: Adam's epsilon, in the units of the loss's gradient per velocity-grid voxel. Adam scales every
        coordinate's step to about ``learning_rate`` whatever its gradient's size, so a gradient of float rounding or
        of LNCC's variance floor (nearly flat windows, where the images give no evidence) moves the velocity as far
        as a real one: a scan onto a copy of itself then ends displaced. Where the gradient is well below this value
        the step shrinks in proportion (torch's default, 1e-8, leaves no such floor).
    mind_radius: the MIND descriptor's patch half-width, voxels of the loss's grid ("mind" only).
    mind_dilation: how far the MIND descriptor's neighbours are, voxels of the loss's grid ("mind" only).
    similarity_guard: keep no deformation that leaves the images less alike than none: when the registration (after
        the fold guard) has a lower local NCC with the fixed image than the moving image itself has (the quality
        estimate's measure, :func:`~monai_probreg.uncertainty.quality_features.local_ncc`), the deformation is given
        up and the identity returned (zero velocity mean, the affine alone on the command line); with "mind", when
        the MIND term of the registration is larger than the moving image's own. A scan onto a copy of itself has
        nothing to register, and every step there only moves tissue the network invents; on pairs
        with something to register the deformable step always raised the local NCC (``benchmarks/identity_cases.py``,
        ``benchmarks/failure_detection.py``). False: the refined (or fold-guarded) registration whatever it scores.
    """

    num_iterations: int = 0
    learning_rate: float = 0.1
    image_sigma: float = 0.04
    prior_lambda: float = 1.5
    posterior_weight: float = 1.0
    image_loss: str = "lncc"
    image_weight: float = 20.0
    lncc_kernel_size: int = 9
    fold_backtracks: int = 4
    fold_local_steps: int = 4
    velocity_grid_factor: int = 1
    image_grid_factor: int = 1
    coarse_iterations: int = 0
    symmetric_start: bool = False
    coarse_lncc_kernel_size: int | None = None
    adam_eps: float = 1e-8
    similarity_guard: bool = False
    mind_radius: int = 1
    mind_dilation: int = 2

    def __post_init__(self) -> None:
        for name in ("num_iterations", "fold_backtracks", "fold_local_steps", "coarse_iterations"):
            check_integer(name, getattr(self, name), minimum=0)
        check_integer("velocity_grid_factor", self.velocity_grid_factor, minimum=1)
        check_integer("image_grid_factor", self.image_grid_factor, minimum=1)
        check_integer("lncc_kernel_size", self.lncc_kernel_size, minimum=3)
        check_integer("mind_radius", self.mind_radius, minimum=0)
        check_integer("mind_dilation", self.mind_dilation, minimum=1)
        if self.lncc_kernel_size % 2 == 0:
            raise ValueError(f"lncc_kernel_size must be an odd integer >= 3; got {self.lncc_kernel_size!r}")
        for name in ("learning_rate", "image_sigma", "prior_lambda", "adam_eps"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
                raise ValueError(f"{name} must be a number > 0; got {value!r}")
        for name in ("posterior_weight", "image_weight"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value >= 0:
                raise ValueError(f"{name} must be a number >= 0; got {value!r}")
        if self.coarse_lncc_kernel_size is not None:
            check_integer("coarse_lncc_kernel_size", self.coarse_lncc_kernel_size, minimum=3)
            if self.coarse_lncc_kernel_size % 2 == 0:
                raise ValueError(f"coarse_lncc_kernel_size must be odd; got {self.coarse_lncc_kernel_size!r}")
        for name in ("symmetric_start", "similarity_guard"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False; got {getattr(self, name)!r}")
        if self.coarse_iterations > self.num_iterations:
            raise ValueError(
                f"coarse_iterations must be at most num_iterations ({self.num_iterations}); "
                f"got {self.coarse_iterations!r}"
            )
        if self.image_loss not in IMAGE_LOSSES:
            raise ValueError(f"image_loss must be one of {IMAGE_LOSSES}; got {self.image_loss!r}")

    @property
    def enabled(self) -> bool:
        return self.num_iterations > 0

    def with_iterations(self, num_iterations: int) -> RefinementSettings:
        """These settings with ``num_iterations`` steps in all, the schedule's finer steps kept last: as many finer
        steps as now (fewer if ``num_iterations`` is smaller), the rest coarse (the command's ``--refine N``)."""
        check_integer("num_iterations", num_iterations, minimum=0)
        fine = self.num_iterations - self.coarse_iterations
        return replace(self, num_iterations=num_iterations, coarse_iterations=max(num_iterations - fine, 0))

    def with_fields(self, **fields: object) -> RefinementSettings:
        """``dataclasses.replace`` of these settings, except that a ``num_iterations`` given without
        ``coarse_iterations`` keeps the schedule's finer steps last (:meth:`with_iterations`): the one way the
        command, the fitting and the benchmarks change a number of steps."""
        if "num_iterations" in fields and "coarse_iterations" not in fields:
            return replace(self.with_iterations(fields.pop("num_iterations")), **fields)
        return replace(self, **fields)

    def as_dict(self) -> dict[str, float | int | str]:
        """The settings by name, for summaries."""
        return asdict(self)

    def differences(self, record: dict) -> dict[str, list]:
        """These settings where they differ from ``record`` (another run's :meth:`as_dict`, e.g. the one a quality
        model was fitted with): name -> [recorded value, this value]; {} when they match. An empty record stands for
        no refinement (``RefinementSettings()``); a setting the record lacks is recorded as None, so it differs, but
        for the settings of :data:`LATER_SETTINGS`, added with a default that runs the refinement as before they
        existed: a record made before them ran that default. When neither refines (0 iterations both), the other
        settings are unused: {}; when one of them refines, every setting that differs is named (what the refining side
        would change)."""
        recorded = {**LATER_SETTINGS, **record} if record else RefinementSettings().as_dict()
        if not self.enabled and not recorded.get("num_iterations"):
            return {}
        return {
            name: [recorded.get(name), value] for name, value in self.as_dict().items() if recorded.get(name) != value
        }


# settings added after records of fitted sidecars existed, each with the default that runs the refinement exactly as
# it ran before the setting existed (RefinementSettings.differences reads a record without them as these)
LATER_SETTINGS = {
    "coarse_iterations": 0,
    "symmetric_start": False,
    "coarse_lncc_kernel_size": None,
    "adam_eps": 1e-8,
    "similarity_guard": False,
    "mind_radius": 1,
    "mind_dilation": 2,
}


def _on_grid(image: Tensor, size: tuple[int, ...]) -> Tensor:
    """``image`` resized (linear, align corners) to ``size``, as the network resizes its inputs."""
    if tuple(image.shape[2:]) == size:
        return image
    mode = "trilinear" if image.ndim == 5 else "bilinear"
    return F.interpolate(image, size=size, mode=mode, align_corners=True)


def _folded(displacement: Tensor) -> Tensor:
    """(B, 1, *S) bool: the voxels whose Jacobian determinant is <= 0."""
    return (jacobian_determinant(displacement) <= 0).unsqueeze(1)


def local_blend(folds: Tensor, grid: Sequence[int], radius: int) -> Tensor:
    """Weights (B, 1, *grid) in [0, 1] of the network's mean for the local fold guard: 1 on every velocity-grid cell
    that holds a folded voxel of ``folds`` (B, 1, *S, any finer grid over the same extent) and within ``radius``
    cells of one, falling linearly (per axis) to 0 beyond ``3 * radius`` cells. Written by hand: no MONAI or torch block
    blends two fields around a mask (the pooling layers are MONAI's ``Pool`` factory's)."""
    spatial_dims = folds.ndim - 2
    core = Pool[Pool.ADAPTIVEMAX, spatial_dims](tuple(int(n) for n in grid))(folds.float())
    grown = Pool[Pool.MAX, spatial_dims](kernel_size=4 * radius + 1, stride=1, padding=2 * radius)(core)  # dilated
    ramp = Pool[Pool.AVG, spatial_dims](kernel_size=2 * radius + 1, stride=1, padding=radius, count_include_pad=False)
    return ramp(grown)


def _without_folds(
    network: ProbRegNet, start: Tensor, refined: Tensor, size: Sequence[int], backtracks: int, local_steps: int
) -> tuple[Tensor, Tensor] | None:
    """The fold guard: (mean, its displacement on ``size``) with no |J| <= 0 voxel, else None (keep the network's
    registration). First the refined mean itself; then, ``local_steps`` times, the change kept everywhere but around
    the folded voxels, where it gives way to the network's mean (:func:`local_blend`, radius 1, 2, 4, ... velocity
    cells, around every fold seen so far); then ``start + t * (refined - start)`` for t = 1/2, ..., 1/2**backtracks.
    Unguarded (t = 1) when both are 0."""
    displacement = network.velocity_to_displacement(refined, size)
    if backtracks == 0 and local_steps == 0:
        return refined, displacement
    change = refined - start
    folds = _folded(displacement)
    if not bool(folds.any()):
        return refined, displacement
    for step in range(local_steps):
        weight = local_blend(folds, change.shape[2:], radius=2**step)
        mean = start + (1.0 - weight) * change
        displacement = network.velocity_to_displacement(mean, size)
        now = _folded(displacement)
        if not bool(now.any()):
            return mean, displacement
        folds = folds | now
    for fraction in [0.5**k for k in range(1, backtracks + 1)]:
        mean = start + fraction * change
        displacement = network.velocity_to_displacement(mean, size)
        if not bool(_folded(displacement).any()):
            return mean, displacement
    return None


class _ImageTerm:
    """The refinement's image term ``D(moving o exp(mu), fixed)`` as a function of the displacement on the loss's
    grid (:meth:`displacement`: the integrated field resized there, on ``region`` only when set). LNCC (with the
    network's one-pass sampling, ``fast_sampling``) is :class:`FixedImageLNCC`: the fixed image's window sums once per
    pair, and the moving image warped and compared only inside the box around the fixed image's nonzero voxels where a
    window can add to the loss (:func:`support_box`; the same value as over the whole grid, the background of a
    skull-stripped fixed image adding exactly 0), the displacement resized onto that box alone
    (:func:`resize_displacement_box`). MIND is :class:`FixedImageMIND` (the fixed image's descriptor once per pair)
    over the whole grid. Otherwise the warp and the loss of :func:`make_image_loss` over the whole grid."""

    def __init__(
        self,
        network: ProbRegNet,
        moving: Tensor,
        fixed: Tensor,
        settings: RefinementSettings,
        kernel_size: int,
        masks: RefinementMasks | None = None,
    ) -> None:
        self.network, self.moving = network, moving
        self.grid = tuple(int(n) for n in fixed.shape[2:])
        self.lncc = self.mind = None
        self.region = None  # the box of the loss's grid the displacement is needed on (None: the whole grid)
        self.masks = masks if masks is not None and (masks.fixed is not None or masks.moving is not None) else None
        if settings.image_loss == "mind":  # the fixed image's descriptor once per pair
            self.mind = FixedImageMIND(fixed, settings.mind_radius, settings.mind_dilation)
        elif settings.image_loss == "lncc" and network.fast_sampling:
            # windows with no nonzero fixed voxel add 0: the box holds the nonzero voxels and every window that
            # reaches them (one radius) with whole windows of their own (a second radius)
            region = support_box(fixed, margin=2 * (kernel_size // 2))
            self.lncc = FixedImageLNCC(fixed, kernel_size, region=region)
            self.region = region
        else:
            self.fixed = fixed
            # with masks, the per-voxel term (weighted below); without, the loss as it always was
            reduction = "mean" if self.masks is None or settings.image_loss == "gaussian" else "none"
            self.loss = make_image_loss(
                settings.image_loss, moving.ndim - 2, settings.image_sigma, kernel_size, reduction
            )
            self.image_sigma = settings.image_sigma

    def displacement(self, field: Tensor) -> Tensor:
        """The integrated displacement ``field`` (B, D, *V, on the velocity grid) on the loss's grid, on
        :attr:`region`'s box only when set (what :meth:`__call__` takes)."""
        if self.region is None:
            return resize_displacement(field, self.grid)
        return resize_displacement_box(field, self.grid, self.region)

    def _weight(self, displacement: Tensor, crop: bool) -> Tensor | None:
        """The masks' per-voxel weight for ``displacement`` (on the box of the LNCC's region when ``crop``): the fixed
        mask times the moving mask warped by the displacement (no gradient through either); None without masks."""
        if self.masks is None:
            return None
        fixed, moving = self.masks
        weight = None if fixed is None else (self.lncc.crop(fixed) if crop else fixed)
        if moving is not None:
            with torch.no_grad():  # the mask says which voxels count; it is not a term to optimise
                if crop:
                    origin = self.lncc.region[0]
                    warped = warp_box(moving, displacement.detach(), origin, padding_mode="zeros")
                else:
                    warped = warp_image(moving, displacement.detach(), padding_mode="zeros")
            weight = warped if weight is None else weight * warped
        return weight

    def __call__(self, displacement: Tensor) -> Tensor:
        net = self.network
        if self.mind is not None:
            warped = warp_image(self.moving, displacement, padding_mode=net.padding_mode, fast=net.fast_sampling)
            return self.mind(warped, self._weight(displacement, crop=False))
        if self.lncc is None:
            warped = warp_image(self.moving, displacement, padding_mode=net.padding_mode, fast=net.fast_sampling)
            if self.masks is None:
                return self.loss(warped, self.fixed)
            if isinstance(self.loss, GaussianImageLoss):  # its per-voxel term: the squared difference / (2 sigma^2)
                per_voxel = (self.fixed - warped).square() / (2.0 * self.image_sigma**2)
            else:
                per_voxel = self.loss(warped, self.fixed)
            return (per_voxel * self._weight(displacement, crop=False)).sum() / per_voxel.numel()
        if self.lncc.region is None:
            warped = warp_image(self.moving, displacement, padding_mode=net.padding_mode)
            return self.lncc(warped) if self.masks is None else self.lncc(warped, self._weight(displacement, False))
        origin = self.lncc.region[0]  # the displacement is already the box's (displacement())
        warped = warp_box(self.moving, displacement, origin, padding_mode=net.padding_mode)
        return self.lncc(warped) if self.masks is None else self.lncc(warped, self._weight(displacement, True))


def refine_registration(
    network: ProbRegNet,
    moving: Tensor,
    fixed: Tensor,
    output: RegistrationOutput,
    settings: RefinementSettings,
    masks: RefinementMasks | None = None,
) -> RegistrationOutput:
    """Refine ``output.velocity_mean`` (from ``network(moving, fixed)`` in eval mode) for this pair.

    Shapes: moving, fixed (B, C, *S) as given to the network; returns a :class:`RegistrationOutput` with
    ``velocity = velocity_mean`` = the refined mean and ``displacement``, ``warped`` (and the inverse fields of a
    bidirectional network) recomputed from it on the same image grids; ``velocity_log_var`` is the network's, on the
    velocity grid of the refined mean (the network's, or ``velocity_grid_factor`` times finer, resized by
    :func:`resize_log_var`). ``output`` itself when the fold guard finds no fold-free fraction of the change. The
    network is not changed. ``masks``: the image term's cost-function masks (:class:`RefinementMasks`, on the images'
    grid; the similarity guard compares inside them too), or None: every voxel, exactly as without the argument.
    Gradients are needed, so it cannot run under ``torch.inference_mode()``.
    """
    if not settings.enabled:
        return output
    if torch.is_inference_mode_enabled():
        raise RuntimeError("refine_registration needs gradients; call it outside torch.inference_mode()")
    if moving.shape != fixed.shape:
        raise ValueError(
            f"moving and fixed must have the same shape; got {tuple(moving.shape)} and {tuple(fixed.shape)}"
        )
    for name, mask in zip(RefinementMasks._fields, masks or ()):
        if mask is not None and (
            mask.shape[0] != moving.shape[0] or mask.shape[1] != 1 or mask.shape[2:] != moving.shape[2:]
        ):
            raise ValueError(
                f"masks.{name}: expected shape {(moving.shape[0], 1, *moving.shape[2:])} (the images' grid), got "
                f"{tuple(mask.shape)}"
            )
    if output.velocity_mean.shape[0] != moving.shape[0]:
        raise ValueError(
            f"output is for a batch of {output.velocity_mean.shape[0]}; got images of batch {moving.shape[0]}"
        )
    coarse = tuple(int(n) for n in (network.network_size or moving.shape[2:]))
    size = tuple(min(n * settings.image_grid_factor, int(m)) for n, m in zip(coarse, moving.shape[2:]))
    kl_loss = LaplacianKLLoss(settings.prior_lambda, reduction="mean")
    # clones: tensors made under inference_mode cannot enter autograd; the images are constants here
    start = output.velocity_mean.detach().clone().float()
    if settings.symmetric_start:  # the antisymmetric part of the network's two directions: 0 for a pair of copies
        with torch.no_grad():
            start = 0.5 * (start - network.posterior(fixed, moving).mean.float())
    log_var = output.velocity_log_var.detach().clone().float()
    if settings.velocity_grid_factor > 1:
        grid = [int(n) * settings.velocity_grid_factor for n in start.shape[2:]]
        start, log_var = resize_displacement(start, grid), resize_log_var(log_var, grid)
        size = tuple(max(int(s), g) for s, g in zip(size, grid))
        coarse = tuple(max(int(s), g) for s, g in zip(coarse, grid))
    # the image term of each (grid, window) of the schedule, built once (the coarse grid can be the finer one)
    terms: dict[tuple[tuple[int, ...], int], _ImageTerm] = {}
    velocity = start.clone().requires_grad_(True)
    optimiser = torch.optim.Adam([velocity], lr=settings.learning_rate, eps=settings.adam_eps)
    with torch.enable_grad():
        for iteration in range(settings.num_iterations):
            is_coarse = iteration < settings.coarse_iterations
            grid = coarse if is_coarse else size
            kernel = (settings.coarse_lncc_kernel_size if is_coarse else None) or settings.lncc_kernel_size
            if (grid, kernel) not in terms:
                images = (_on_grid(t.detach().clone().float(), grid) for t in (moving, fixed))
                on_grid = None if masks is None else masks.on_grid(grid)
                terms[grid, kernel] = _ImageTerm(network, *images, settings, kernel, on_grid)
            optimiser.zero_grad(set_to_none=True)
            term = terms[grid, kernel]
            displacement = term.displacement(network.integrate(velocity))
            loss = settings.image_weight * term(displacement) + kl_loss(velocity, log_var)
            if settings.posterior_weight > 0:  # (mu - mu_net)^2 / sigma_net^2, mean over the velocity grid
                pull = ((velocity - start).square() * log_var.neg().exp()).mean()
                loss = loss + 0.5 * settings.posterior_weight * pull
            loss.backward()
            optimiser.step()
    with torch.no_grad():
        full = moving.shape[2:]
        guarded = _without_folds(
            network, start, velocity.detach(), full, settings.fold_backtracks, settings.fold_local_steps
        )
        if guarded is None:  # no fold-free fraction of the change: the network's registration as it was
            return output
        mean, displacement = guarded
        warped = warp_image(moving, displacement, padding_mode=network.padding_mode, fast=network.fast_sampling)
        if settings.similarity_guard:
            mean, displacement, warped = _similarity_guard(moving, fixed, mean, displacement, warped, masks, settings)
        inverse = warped_fixed = None
        if output.inverse_displacement is not None:
            inverse = network.velocity_to_displacement(-mean, full)
            warped_fixed = warp_image(fixed, inverse, padding_mode=network.padding_mode, fast=network.fast_sampling)
    return RegistrationOutput(
        warped, displacement, mean, mean, log_var.to(output.velocity_log_var.dtype), inverse, warped_fixed
    )


def _similarity_guard(
    moving: Tensor,
    fixed: Tensor,
    mean: Tensor,
    displacement: Tensor,
    warped: Tensor,
    masks: RefinementMasks | None = None,
    settings: RefinementSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """(mean, displacement, warped) with the identity (zeros, the moving image itself) for every item of the batch
    whose ``warped`` is less alike ``fixed`` than ``moving`` is (:func:`local_ncc` of the first channel; with
    ``settings.image_loss`` "mind", the MIND term of the first channel, lower is more alike), compared inside the masks
    when given (the fixed mask and the moving mask, unwarped before, warped after): an artefact the masks leave out
    must not decide the guard either."""
    if settings is not None and settings.image_loss == "mind":
        before = _mind_similarity(moving, fixed, settings, masks, None)
        after = _mind_similarity(warped, fixed, settings, masks, displacement)
    elif masks is None or (masks.fixed is None and masks.moving is None):
        before = local_ncc(moving[:, :1], fixed[:, :1])
        after = local_ncc(warped[:, :1], fixed[:, :1])
    else:
        fixed_mask = (
            torch.ones_like(fixed[:, :1], dtype=torch.bool) if masks.fixed is None else masks.fixed >= MASK_LEVEL
        )
        moving_before = moving_after = fixed_mask
        if masks.moving is not None:
            moving_before = fixed_mask & (masks.moving >= MASK_LEVEL)
            warped_mask = warp_image(masks.moving.float(), displacement, padding_mode="zeros")
            moving_after = fixed_mask & (warped_mask >= MASK_LEVEL)
        before = local_ncc(moving[:, :1], fixed[:, :1], moving_before)
        after = local_ncc(warped[:, :1], fixed[:, :1], moving_after)
    give_up = (after < before).to(mean.device)
    if not bool(give_up.any()):
        return mean, displacement, warped

    def keep(t: Tensor, instead: Tensor) -> Tensor:
        return torch.where(give_up.view(-1, *[1] * (t.ndim - 1)), instead.to(t.dtype), t)

    return keep(mean, torch.zeros_like(mean)), keep(displacement, torch.zeros_like(displacement)), keep(warped, moving)


def _mind_similarity(
    image: Tensor,
    fixed: Tensor,
    settings: RefinementSettings,
    masks: RefinementMasks | None,
    displacement: Tensor | None,
) -> Tensor:
    """(B,): minus the MIND term of ``image`` against ``fixed`` (first channels; larger is more alike, as the local
    NCC), the mean over the voxels inside the masks (the moving mask warped by ``displacement`` when given)."""
    per_voxel = MINDLoss(settings.mind_radius, settings.mind_dilation, reduction="none")(image[:, :1], fixed[:, :1])
    inside = torch.ones_like(per_voxel, dtype=torch.bool)
    if masks is not None and masks.fixed is not None:
        inside = inside & (masks.fixed >= MASK_LEVEL)
    if masks is not None and masks.moving is not None:
        moving_mask = masks.moving.float()
        if displacement is not None:
            moving_mask = warp_image(moving_mask, displacement, padding_mode="zeros")
        inside = inside & (moving_mask >= MASK_LEVEL)
    counts = inside.flatten(1).sum(1).clamp_min(1)
    return -(per_voxel * inside).flatten(1).sum(1) / counts


def resize_log_var(log_var: Tensor, spatial_size: Sequence[int]) -> Tensor:
    """A velocity log-variance (B, D, *V) on another grid over the same extent, in that grid's voxel units: the
    variance of channel k scales with the square of :func:`resize_displacement`'s factor for axis k."""
    source = list(log_var.shape[2:])
    spatial_size = [int(m) for m in spatial_size]
    if log_var.ndim not in (4, 5) or log_var.shape[1] != len(source) or len(spatial_size) != len(source):
        raise ValueError(
            f"expected a (B, D, *V) log-variance and D target sizes; got {tuple(log_var.shape)} and {spatial_size}"
        )
    if min(source + spatial_size) < 2:
        raise ValueError(f"both grids need at least 2 voxels per axis; got {source} -> {spatial_size}")
    scale = torch.tensor([(m - 1) / (n - 1) for n, m in zip(source, spatial_size)], dtype=log_var.dtype)
    shift = 2.0 * scale.log().view([1, -1] + [1] * len(source)).to(log_var.device)
    mode = "trilinear" if log_var.ndim == 5 else "bilinear"
    return F.interpolate(log_var, size=list(spatial_size), mode=mode, align_corners=True) + shift
