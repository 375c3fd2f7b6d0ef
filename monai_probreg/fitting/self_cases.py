"""The quality model's cases with (almost) nothing to register: a training subject onto itself.

Users register follow-up scans of one subject and images that are already aligned. Without such pairs in the fit,
every one of them lies beyond the training range on the same corner (NCC and local NCC near 1, almost no
displacement), the clipping of :mod:`monai_probreg.uncertainty.quality` maps them all to one point, and unrelated
pairs get the same estimate to many digits. So each *training* subject (never a validation one) is also registered
onto itself, on the bundle path (:func:`~monai_probreg.fitting.quality_cases.cases_for`):

- ``self``: the scan itself, unchanged: no registration has Dice 1 and the NCC before is 1, the corner itself;
- ``near_copy``: a near copy of the scan (:func:`near_copy`): a small smooth deformation of image and labels, a mild
  bias field and mild noise, seeded: the pairs between that corner and the normal pairs;

and through the whole command (:mod:`~monai_probreg.fitting.command_cases`, ``command_self``): onto itself with its
header moved by a small rigid motion (:func:`rigid_motion`, the voxels untouched) that the affine stage undoes, what
``benchmarks/identity_cases.py`` measures on a validation subject and the template. Their "no registration" Dice is
:data:`SELF_DICE` (the same voxels and labels); a registration that keeps it within the failure margin did not fail
(:func:`~monai_probreg.uncertainty.quality.failed`).

They enter the failure model and the features' range (``low``/``high``), not the Dice regression
(:func:`~monai_probreg.fitting.quality_fit.fit_on_records`): one linear Dice model cannot rank the normal pairs and
reach Dice 1 at this corner too. With four real ones (S12 and S13, ``self`` and ``near_copy``) added to the shipped
fit's records, its Spearman on the normal validation pairs fell from 0.650 to 0.140 (AUROC 0.945 either way); fitted
without them it stays 0.646. So the Dice regression's input is clipped to its own records' range (``dice_low``,
``dice_high``) and a pair at the corner gets its best prediction, while its failure probability is the failure
model's, which has seen the corner (NCC 1, the most alike a pair can be, is inside its range: no clip ties two pairs).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from monai.transforms import ScaleIntensityRangePercentiles

from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.fitting.population_probe import random_deformation
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE
from monai_probreg.uncertainty.quality import PERFECT_DICE

__all__ = [
    "SELF",
    "NEAR_COPY",
    "COMMAND_SELF",
    "SELF_NAMES",
    "SELF_DICE",
    "NEAR_COPY_RMS_VOXELS",
    "NEAR_COPY_BIAS_STD",
    "NEAR_COPY_NOISE_STD",
    "SELF_TURN_DEGREES",
    "SELF_SHIFT_MM",
    "SELF_PERTURBATIONS",
    "near_copy",
    "rigid_motion",
]

SELF = "self"  # the subject onto itself, unchanged
NEAR_COPY = "near_copy"  # the subject onto a near copy of itself
COMMAND_SELF = "command_self"  # through the whole command onto itself, its header moved (command_cases)
SELF_NAMES = (SELF, NEAR_COPY, COMMAND_SELF)  # the perturbation names of every self case
SELF_DICE = PERFECT_DICE  # the Dice of no registration of a scan onto itself: its labels against themselves
# RMS displacement in the brain of the near copy's deformation, dataset-grid voxels (1 mm for LPBA40): from about what
# the network invents on a copy of a scan to the smallest mean displacement of a normal training pair (1.8 mm)
NEAR_COPY_RMS_VOXELS = (0.5, 2.0)
NEAR_COPY_BIAS_STD = 0.05  # std of the log bias field (a gain of about +-5%): a tenth of the failure set's noise_bias
NEAR_COPY_NOISE_STD = (0.012, 0.02)  # Gaussian noise, of the [0, 1] range: a tenth of the failure set's noise_bias
BIAS_CONTROL_POINTS = 3  # per axis: the bias field is this coarse grid, smoothly upsampled (as noise_bias's)
SELF_TURN_DEGREES = (2.0, 8.0)  # the whole-command case's turn about a random axis: a head moved between two scans
SELF_SHIFT_MM = (2.0, 8.0)  # and its shift along a random direction (identity_cases.py's 4 degrees / 4 mm inside)

Pair = tuple[torch.Tensor, torch.Tensor]
_rescale = ScaleIntensityRangePercentiles(LOWER_PERCENTILE, UPPER_PERCENTILE, 0.0, 1.0, clip=True)


def _uniform(g: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=g))


def near_copy(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    """A near copy of ``image`` and ``label`` ((1, 1, *S), intensities in [0, 1]): both warped by a random smooth
    diffeomorphism (:func:`~monai_probreg.fitting.population_probe.random_deformation`, RMS in
    :data:`NEAR_COPY_RMS_VOXELS`), the image then under a mild bias field and mild noise, re-scaled to [0, 1]."""
    forward, _ = random_deformation(image, _uniform(g, *NEAR_COPY_RMS_VOXELS), g)
    warped = warp_image(image.float(), forward)
    moved_label = warp_labels(label, forward)
    coarse = torch.randn((1, 1, *[BIAS_CONTROL_POINTS] * (image.ndim - 2)), generator=g) * NEAR_COPY_BIAS_STD
    bias = torch.nn.functional.interpolate(coarse, size=image.shape[2:], mode="trilinear", align_corners=True).exp()
    noisy = warped * bias + torch.randn(image.shape, generator=g) * _uniform(g, *NEAR_COPY_NOISE_STD)
    return torch.as_tensor(_rescale(noisy[0]))[None].float(), moved_label


SELF_PERTURBATIONS: dict[str, Callable[[torch.Tensor, torch.Tensor, torch.Generator], Pair]] = {
    SELF: lambda i, lab, g: (i, lab),
    NEAR_COPY: near_copy,
}


def rigid_motion(g: torch.Generator, centre: np.ndarray) -> np.ndarray:
    """(4, 4) world transform: a turn by :data:`SELF_TURN_DEGREES` about a random axis through ``centre`` (world,
    3 values), then a shift of :data:`SELF_SHIFT_MM` along a random direction (Rodrigues' formula), seeded by ``g``."""
    axis, direction = (torch.randn(3, generator=g, dtype=torch.float64).numpy() for _ in range(2))
    axis, direction = axis / np.linalg.norm(axis), direction / np.linalg.norm(direction)
    angle = math.radians(_uniform(g, *SELF_TURN_DEGREES))
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
    motion = np.eye(4)
    motion[:3, :3] = rotation
    motion[:3, 3] = centre - rotation @ centre + _uniform(g, *SELF_SHIFT_MM) * direction
    return motion
