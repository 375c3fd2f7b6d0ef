"""The calibration's population probe: known deformations of the atlas, registered back on the dataset grid.

Ground truth where it exists. For each subject S (the bundle's validation subjects), random smooth velocity fields v
are drawn by one of two models:

- ``population`` (the fit's): a statistical deformation model of real anatomy. The model's mean velocities of the
  training subjects (never S) -> atlas give a mean and deviations (:func:`population_velocities`); v = -(mean +
  sum_i w_i deviation_i) with w_i ~ N(0, 1/(n-1)), a draw from their empirical Gaussian. Realistic magnitude and
  shape: the deformed atlas looks like a new subject. Optimistic: the fields lie in the span of what the model
  itself predicts.
- ``noise`` (:func:`random_deformation`): white noise on the velocity grid, Gaussian-smoothed
  (:data:`SMOOTHING_VOXELS`), scaled so the displacement RMS in the brain equals a given RMS: out of the training
  distribution, the pessimistic bound (``benchmarks/uncertainty_calibration.py --probe noise``).

With our own integration (:data:`TRUTH_STEPS` squarings at full resolution): moving = R warped by exp(v), fixed = R;
the true displacement of moving onto fixed is exp(-v). The registration is the one users get (:func:`posterior_for`:
the network's mean, refined when the refinement is on; the network's variance and the pair's residual); :func:`case_errors` gives its
first-order std map (:mod:`~monai_probreg.uncertainty.spread`) at a calibration and the answer's error, the arrays
:func:`~monai_probreg.uncertainty.calibration.fit_calibration` takes, on :data:`VOXELS_PER_CASE` subsampled brain
voxels, in voxels; :func:`sampled_case_variance` samples it (the fit's measure of the samples' damping).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import torch
from monai.networks.layers import GaussianFilter

from monai_probreg.blocks.integration import ScalingAndSquaring, resize_displacement
from monai_probreg.blocks.warp import warp_image
from monai_probreg.engines.registration import register_pair
from monai_probreg.uncertainty.calibration import Calibration, calibrate_log_var
from monai_probreg.uncertainty.entropy import sampled_displacement_moments
from monai_probreg.uncertainty.error_model import pair_term
from monai_probreg.uncertainty.samples import sample_log_var
from monai_probreg.uncertainty.spread import displacement_variance
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.tensors import plain_tensor

__all__ = [
    "TRUTH_STEPS",
    "SMOOTHING_VOXELS",
    "VOXELS_PER_CASE",
    "SEED_STRIDE",
    "random_deformation",
    "population_velocities",
    "population_velocity",
    "population_deformation",
    "sample_displacements",
    "PairPosterior",
    "posterior_for",
    "case_velocity_std",
    "displacement_case",
    "case_errors",
    "sampled_case_variance",
    "sampled_case_errors",
    "pool_errors",
]

TRUTH_STEPS = 10  # squarings for the true fields (full resolution; the model uses 7 at half resolution)
SMOOTHING_VOXELS = 6.0  # Gaussian sigma of the random velocity, in velocity-grid voxels (12 mm at 1 mm, /2)
VOXELS_PER_CASE = 400_000  # brain voxels subsampled per case for the displacement metrics (x 3 components)
SEED_STRIDE = 100  # subject n's deformation r is drawn with seed + SEED_STRIDE * n + r (r < SEED_STRIDE)


def random_deformation(
    fixed: torch.Tensor, rms: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A random smooth diffeomorphism on ``fixed``'s grid: (forward displacement exp(v), inverse exp(-v)), both
    (1, 3, *S) voxels, with the forward displacement's RMS in the brain scaled to ``rms``."""
    size = fixed.shape[2:]
    noise = torch.randn((1, 3, *(s // 2 for s in size)), generator=generator)
    velocity = GaussianFilter(3, SMOOTHING_VOXELS)(noise)
    integrate = ScalingAndSquaring(num_steps=TRUTH_STEPS)
    brain = fixed[0, 0] > 0
    for _ in range(2):  # rescale twice: integration is only approximately linear in the velocity
        full = resize_displacement(velocity, size)
        current = integrate(full)[0][:, brain].pow(2).sum(0).mean().sqrt()
        velocity = velocity * (rms / float(current))
    full = resize_displacement(velocity, size)
    return integrate(full), integrate(-full)


def population_velocities(network, dataset) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean (3, *V), deviations (n, 3, *V)) of the model's mean velocities over ``dataset``'s pairs (the training
    subjects -> atlas): the statistical deformation model of the ``population`` probe."""
    velocities = []
    for item in dataset:
        pair = {k: plain_tensor(v)[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
        with torch.inference_mode():
            velocities.append(network.posterior(pair["moving"], pair["fixed"]).mean[0])
    if len(velocities) < 2:
        raise InputError(f"the population probe needs >= 2 training subjects; got {len(velocities)}")
    stacked = torch.stack(velocities)
    mean = stacked.mean(0)
    return mean, stacked - mean


def population_velocity(population: tuple[torch.Tensor, torch.Tensor], generator: torch.Generator) -> torch.Tensor:
    """A draw (1, 3, *V) of the population model, velocity-grid voxels: mean + sum_i w_i deviation_i with
    w_i ~ N(0, 1/(n - 1)), a subject -> atlas velocity (the truth the registration of the deformed atlas aims at)."""
    mean, deviations = population
    weights = torch.randn(len(deviations), generator=generator) / math.sqrt(len(deviations) - 1)
    return (mean + torch.einsum("n,n...->...", weights, deviations))[None]


def population_deformation(fixed: torch.Tensor, subject_to_atlas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The fields of a population draw ``subject_to_atlas`` (1, 3, *V) from :func:`population_velocity` on
    ``fixed``'s grid: (forward exp(v), inverse exp(-v)), both (1, 3, *S) voxels, with -v = ``subject_to_atlas``: the
    moving image, ``fixed`` warped by exp(v), takes the shape of a new subject, and the truth exp(-v) is a
    subject -> atlas field."""
    full = resize_displacement(-subject_to_atlas, fixed.shape[2:])  # velocity grid -> image voxels
    integrate = ScalingAndSquaring(num_steps=TRUTH_STEPS)
    return integrate(full), integrate(-full)


def sample_displacements(network, mean, log_var, size, num_samples, generator):
    """Mean and variance (1, 3, *size) of ``num_samples`` displacements drawn from N(mean, exp(log_var))."""
    with torch.inference_mode():
        return sampled_displacement_moments(
            mean, log_var, lambda z: network.velocity_to_displacement(z, size), num_samples, generator
        )


def _subsample(mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    index = mask.reshape(-1).nonzero()[:, 0]
    keep = torch.randperm(index.numel(), generator=generator)[:VOXELS_PER_CASE]
    return index[keep]


class PairPosterior(NamedTuple):
    """What a registration's maps are sampled from: the velocity ``mean`` and the network's ``log_var``
    (1, 3, *V), and the map the calibration's term weighs, ``residual`` (1, 1, *V), of the registered pair
    (:func:`~monai_probreg.uncertainty.error_model.pair_term`: the error model's prediction, or the residual)."""

    mean: torch.Tensor
    log_var: torch.Tensor
    residual: torch.Tensor


def posterior_for(network, moving, fixed, refinement=None, error_model=None) -> PairPosterior:
    """The posterior a user's registration samples: the network's, with its mean refined for the pair when
    ``refinement`` (evaluate.yaml's ``refinement``) is enabled; the variance stays the network's; the term's map of
    the registered pair (``error_model``: a calibration's, None: the residual)."""
    output = register_pair(network, moving, fixed, refinement)
    pair = (output.warped, fixed, output.velocity_mean, output.velocity_log_var, output.displacement)
    with torch.inference_mode():
        residual = pair_term(error_model, *pair)
    return PairPosterior(output.velocity_mean, output.velocity_log_var, residual)


def displacement_case(
    network, fixed, rms, num_samples, seed, population=None, refinement=None, error_model=None
) -> dict[str, Any]:
    """One synthetic case: the posterior (kept, to re-sample when calibrated), the truth on subsampled voxels.
    ``population`` (from :func:`population_velocities`) draws the field from it; None: smoothed noise of RMS ``rms``.
    ``refinement``: the mean is the refined one; ``error_model``: the term's (:func:`posterior_for`)."""
    generator = torch.Generator().manual_seed(seed)
    if population is not None:
        forward, truth = population_deformation(fixed, population_velocity(population, generator))
    else:
        forward, truth = random_deformation(fixed, rms, generator)
    moving = warp_image(fixed, forward)
    posterior = posterior_for(network, moving, fixed, refinement, error_model)
    voxels = _subsample(fixed[0, 0] > 0, generator)
    with torch.inference_mode():
        registration = network.velocity_to_displacement(posterior.mean, tuple(fixed.shape[2:]))
        # the raw velocity std on the image grid, in its voxels: what sampling would give without any smoothing;
        # the residual term's per unit weight, alike (case_velocity_std)
        velocity_std = resize_displacement((0.5 * posterior.log_var).exp(), tuple(fixed.shape[2:]))
        residual_std = resize_displacement(posterior.residual.sqrt().expand_as(posterior.mean), tuple(fixed.shape[2:]))
    return {
        "mean": posterior.mean,
        "log_var": posterior.log_var,
        "residual": posterior.residual,
        "truth": truth[0].flatten(1)[:, voxels],
        "voxels": voxels,
        "size": tuple(fixed.shape[2:]),
        "seed": seed,
        "answer": registration[0].flatten(1)[:, voxels],
        "displacement_norm": registration[0].flatten(1)[:, voxels].norm(dim=0),
        "velocity_std": velocity_std[0].flatten(1)[:, voxels],
        "residual_std": residual_std[0].flatten(1)[:, voxels],
    }


def case_velocity_std(case: dict[str, Any], residual_weight: float) -> torch.Tensor:
    """(3, N) the velocity std of ``case`` (:func:`displacement_case`) on its voxels with the residual term of
    ``residual_weight`` and no scale: ``sqrt(sigma^2 + residual_weight * residual)``, image-grid voxels."""
    return (case["velocity_std"].square() + residual_weight * case["residual_std"].square()).sqrt()


def _calibrated_log_var(case: dict[str, Any], calibration: Calibration) -> torch.Tensor:
    return calibrate_log_var(
        case["log_var"],
        calibration.std_scale,
        case["mean"],
        calibration.bias_fraction,
        case["residual"],
        calibration.residual_weight,
    )


def case_errors(case: dict[str, Any], calibration: Calibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(std, error, |mean displacement|), each (3, N): per subsampled voxel and component of ``case``
    (:func:`displacement_case`), the first-order std of the posterior calibrated by ``calibration``
    (:func:`~monai_probreg.uncertainty.spread.displacement_variance`) and the answer's error (the mean's displacement
    minus the truth), image-grid voxels."""
    with torch.inference_mode():
        variance = displacement_variance(_calibrated_log_var(case, calibration), case["size"])
    pick = case["voxels"]
    error = case["answer"] - case["truth"]
    norm = case["displacement_norm"].expand_as(error)
    return variance[0].flatten(1)[:, pick].sqrt().numpy(), error.numpy(), norm.numpy()


def sampled_case_variance(network, case: dict[str, Any], calibration: Calibration, num_samples: int) -> np.ndarray:
    """(3, N) the variance of ``num_samples`` displacements sampled from ``case``'s posterior calibrated by
    ``calibration`` (its velocity std widened by ``calibration.sample_gain``; Gaussian, the samples the gain is fitted
    on: the label entropy's are Student-t around them, :mod:`monai_probreg.uncertainty.samples`), per subsampled voxel
    and component, image-grid voxels: what the samples' spread is beside :func:`case_errors`' map."""
    log_var = sample_log_var(_calibrated_log_var(case, calibration), calibration.sample_gain)
    generator = torch.Generator().manual_seed(case["seed"] + 1)
    _, variance = sample_displacements(network, case["mean"], log_var, case["size"], num_samples, generator)
    return variance[0].flatten(1)[:, case["voxels"]].numpy()


def sampled_case_errors(
    network, case: dict[str, Any], calibration: Calibration, num_samples: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`case_errors` with the std of ``num_samples`` samples (:func:`sampled_case_variance`) in place of the map:
    what older bundles' uncertainty maps were (the studies in ``experiments/`` measured it)."""
    _, error, norm = case_errors(case, calibration)
    return np.sqrt(sampled_case_variance(network, case, calibration, num_samples)), error, norm


def pool_errors(errors: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Concatenate the (3, N) arrays of several cases along N."""
    return tuple(np.concatenate([e[i] for e in errors], axis=1) for i in range(len(errors[0])))
