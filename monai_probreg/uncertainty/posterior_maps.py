"""The calibrated uncertainty maps the bundle's inference writes, from one pair's velocity posterior.

- ``velocity_entropy``: entropy of the calibrated q(z) (paper Eq. 8, nats, summed over the 3 components),
  resized to the image grid. Without a bias or residual term, calibration adds ``spatial_dims * log(std_scale)``
  everywhere; the bias term (:mod:`monai_probreg.uncertainty.calibration`) raises it more where the mean velocity is
  long, the residual term (:mod:`monai_probreg.uncertainty.residual`) where the registered images still differ.
- ``displacement_std``: sqrt(sum_c var_c) of the calibrated posterior's displacement, first order (the calibrated
  velocity std resized onto the image grid, :mod:`monai_probreg.uncertainty.spread`; no sampling), in voxels of the
  image grid or mm: the radius-like spread of where each voxel maps. On held-out LPBA40 subjects its coverage is
  reported by ``benchmarks/uncertainty_calibration.py``.
- ``label_entropy`` (when moving labels are given): entropy (nats) of the moving labels read by each of K
  displacements sampled from the calibrated posterior (its velocity std widened by the calibration's
  ``sample_gain``, Student-t with its ``interval_dof``: :mod:`monai_probreg.uncertainty.samples`), with partial
  volume, each sample giving the labels around its point the weights of linear interpolation
  (:mod:`monai_probreg.uncertainty.partial_volume`): 0 where every sample reads one label wholly.

All maps live on the fixed grid, like the rest of the outputs. The K samples use a seeded generator, so the
maps are reproducible.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from monai_probreg.blocks.box_resize import resize_displacement_box
from monai_probreg.blocks.sampling import sample_velocity
from monai_probreg.uncertainty.calibration import calibrate_log_var, check_calibration
from monai_probreg.uncertainty.entropy import velocity_entropy
from monai_probreg.uncertainty.partial_volume import PartialVolumeLabels
from monai_probreg.uncertainty.samples import sample_log_var, sample_scales
from monai_probreg.uncertainty.spread import displacement_variance

__all__ = ["PosteriorMaps", "posterior_maps"]

SAMPLE_CHUNK = 4  # posterior samples integrated at once (memory: chunk x 3 full-resolution fields)


class PosteriorMaps(NamedTuple):
    """(*S) maps on the fixed grid; ``displacement_std`` is None with ``num_samples`` 0, ``label_entropy`` also
    without moving labels. ``displacement_variance`` (D, *S): the first-order variance of each displacement component
    (along the grid's axis of that channel; squared voxels, or mm^2 with ``spacing``), whose sum ``displacement_std``
    is the square root of; None with ``num_samples`` 0."""

    velocity_entropy: Tensor
    displacement_std: Tensor | None
    label_entropy: Tensor | None
    displacement_variance: Tensor | None = None


@torch.inference_mode()
def posterior_maps(
    network: nn.Module,
    velocity_mean: Tensor,
    velocity_log_var: Tensor,
    spatial_size: Sequence[int],
    num_samples: int = 0,
    std_scale: float = 1.0,
    moving_label: Tensor | None = None,
    seed: int = 0,
    bias_fraction: float = 0.0,
    spacing: Sequence[float] | None = None,
    residual: Tensor | None = None,
    residual_weight: float = 0.0,
    sample_gain: float = 1.0,
    interval_dof: float | None = None,
) -> PosteriorMaps:
    """Maps of one pair. ``velocity_mean``, ``velocity_log_var``: (1, D, *V) raw posterior; ``network`` provides
    ``integrate`` (a velocity's displacement on the velocity grid, as ``ProbRegNet``); ``num_samples``: 0 (velocity
    entropy only) or >= 2 (the displacement's maps: its std, which needs no sample, and with ``moving_label`` the label
    entropy of that many samples); ``std_scale`` and ``bias_fraction``: the calibration (1 and 0 = raw); ``moving_label``:
    (1, 1, *S) integer labels on the moving grid, or None; ``spacing``: voxel size per axis of the fixed grid to
    give ``displacement_std`` in mm (the trace of the covariance is rotation-invariant, so per-axis voxel variances
    times spacing^2 give it exactly), or None for voxels; ``residual`` (1, 1, *V) and ``residual_weight``: the
    calibration's residual term (:func:`~monai_probreg.uncertainty.residual.residual_variance` of the pair; None and
    0: none); ``sample_gain``: the calibration's widening of the samples' velocity std (1: none); ``interval_dof``: the
    calibration's Student-t dof, the label entropy's samples drawn from that t (None: Gaussian)."""
    if velocity_mean.shape[0] != 1 or velocity_mean.shape != velocity_log_var.shape:
        raise ValueError(
            f"expected one pair's posterior, mean and log_var (1, D, *V); got "
            f"{tuple(velocity_mean.shape)} and {tuple(velocity_log_var.shape)}"
        )
    if num_samples == 1 or num_samples < 0:
        raise ValueError(f"num_samples must be 0 (no sampling) or >= 2 (a spread needs two); got {num_samples}")
    check_calibration(std_scale, bias_fraction, interval_dof, sample_gain=sample_gain)
    size = tuple(int(s) for s in spatial_size)
    log_var = calibrate_log_var(
        velocity_log_var.float(), std_scale, velocity_mean.float(), bias_fraction, residual, residual_weight
    )
    entropy = velocity_entropy(log_var, size)[0, 0]
    if num_samples == 0:
        return PosteriorMaps(entropy, None, None)
    variance = displacement_variance(log_var, size, spacing)[0]
    std = variance.sum(0).sqrt()
    if moving_label is None:
        return PosteriorMaps(entropy, std, None, variance)
    generator = torch.Generator(device=velocity_mean.device).manual_seed(seed)
    labels = PartialVolumeLabels(moving_label.to(velocity_mean.device))
    sampled, scales = sample_log_var(log_var, sample_gain), sample_scales(num_samples, interval_dof)
    for start in range(0, num_samples, SAMPLE_CHUNK):
        chunk = scales[start : start + SAMPLE_CHUNK]
        z = sample_velocity(velocity_mean.float(), sampled, len(chunk), generator, chunk)
        # network.velocity_to_displacement's field: the resize by one small matrix per axis (blocks.box_resize) gives
        # F.interpolate's values, float rounding apart, and is the faster of the two on a CPU (docs/uncertainty.md);
        # the network itself keeps F.interpolate (blocks.integration.resize_displacement): its TorchScript export
        # and the answer's warp stay as they were, bit for bit
        for disp in resize_displacement_box(network.integrate(z[:, 0]), size, ([0] * len(size), size)):
            labels.add(disp[None])  # each sample's reading of the labels, kept for the entropy
    return PosteriorMaps(entropy, std, labels.entropy(), variance)
