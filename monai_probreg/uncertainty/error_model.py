"""The error model: where the registered pair itself says its answer is wrong, as a variance on the velocity grid.

The calibration's residual term (:mod:`monai_probreg.uncertainty.residual`) widens the posterior where the registered
images stay unlike. The pair says more than that: the answer's errors are also larger where its displacement bends
(the data pulled it away from the prior's smoothness, and a smooth truth does not bend there), smaller where the
network's own variance is large (it is large where the image is flat and the refinement moves nothing), and depend on
the image's contrast and on how far inside the brain a voxel lies. The error model predicts the log of the answer's
squared error (mm^2, the components summed) as a linear function of such features of the pair
(:data:`ERROR_FEATURES`, :func:`error_features`, on the image grid), fitted by least squares on synthetic
subjects of training scans whose truth is known (``python -m monai_probreg.fitting``,
:mod:`monai_probreg.fitting.error_cases`); its prediction ``exp(features . coefficients + intercept)``, averaged onto the velocity grid, takes the
residual's place in the calibration's term (:func:`pair_term`, the one rule of which map the term reads):

    sigma^2_calibrated,c = std_scale^2 * (sigma^2_c + residual_weight * e) + (bias_fraction * |mu|)^2

with ``e`` the prediction (or, for a calibration without an error model, the residual ``r``). The features were
chosen by ``experiments/error_model.py`` (docs/uncertainty.md, "An error model of the pair's features"). Written by
hand: no library offers a per-voxel error model of a registration.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from monai_probreg.losses.lncc import box_sum
from monai_probreg.uncertainty.residual import residual_variance, squared_difference

__all__ = [
    "EDGE_LEVEL",
    "ERROR_FEATURES",
    "INSIDE_WINDOW",
    "LOG_FLOOR",
    "check_error_model",
    "error_features",
    "fit_error_model",
    "pair_term",
    "predicted_variance",
    "squared_gradient",
    "squared_laplacian",
]

RESIDUAL_WINDOWS = (9, 3, 15)  # the residual over these boxes (image-grid voxels; the first is the residual term's)
LAPLACIAN_WINDOWS = (5, 9, 15)  # the displacement's squared Laplacian averaged over these boxes (image-grid voxels)
GRADIENT_SMOOTHING = 3  # the fixed image averaged over this box before its gradient (image-grid voxels)
GRADIENT_WINDOW = 9  # the gradient magnitude averaged over this box (image-grid voxels)
INSIDE_WINDOW = 15  # the fraction of the fixed image's foreground in this box: how far inside a voxel lies
EDGE_LEVEL = 0.02  # the foreground: the fixed network input (in [0, 1]) above this
LOG_FLOOR = 1e-12  # added inside every log (an empty residual, a straight field, a flat image)
ERROR_FEATURES = (
    "log residual, 9-voxel box",
    "log residual, 3-voxel box",
    "log residual, 15-voxel box",
    "log squared Laplacian of the mean velocity",
    "log squared Laplacian of the displacement, 5-voxel box",
    "log squared Laplacian of the displacement, 9-voxel box",
    "log squared Laplacian of the displacement, 15-voxel box",
    "log network velocity variance",
    "log displacement length",
    "log fixed gradient magnitude, 9-voxel box",
    "fixed foreground fraction, 15-voxel box",
    "fixed intensity",
)


def _box_mean(x: Tensor, window: int) -> Tensor:
    return box_sum(x, window) / window ** (x.ndim - 2) if window > 1 else x


def squared_laplacian(field: Tensor) -> Tensor:
    """(B, C, *S) -> (B, 1, *S): the squared 2D-neighbour Laplacian (the border replicated), summed over components.
    One component at a time, in place (faster on a CPU than the whole field's slices; docs/uncertainty.md)."""
    dims = field.ndim - 2
    total = None
    for channel in range(field.shape[1]):
        component = field[:, channel : channel + 1]
        padded = F.pad(component, [1, 1] * dims, mode="replicate")
        laplacian = component * (-2 * dims)
        for axis in range(dims):
            for low, high in ((0, -2), (2, None)):
                index = [slice(1, -1)] * dims
                index[axis] = slice(low, high)
                laplacian.add_(padded[(slice(None), slice(None), *index)])
        laplacian.square_()
        total = laplacian if total is None else total.add_(laplacian)
    return total


def squared_gradient(image: Tensor) -> Tensor:
    """(B, 1, *S) -> (B, 1, *S): the squared length of the image's gradient, central differences inside and one-sided
    ones at the borders (``torch.gradient``'s values, one axis at a time in place, faster on a CPU; docs/uncertainty.md)."""
    total = torch.zeros_like(image)
    for axis in range(2, image.ndim):
        n = image.shape[axis]
        if n < 2:
            continue  # a single plane has no gradient along its axis
        step = torch.empty_like(image)
        if n > 2:
            step.narrow(axis, 1, n - 2).copy_(image.narrow(axis, 2, n - 2)).sub_(image.narrow(axis, 0, n - 2)).mul_(0.5)
        step.narrow(axis, 0, 1).copy_(image.narrow(axis, 1, 1)).sub_(image.narrow(axis, 0, 1))
        step.narrow(axis, n - 1, 1).copy_(image.narrow(axis, n - 1, 1)).sub_(image.narrow(axis, n - 2, 1))
        total.addcmul_(step, step)
    return total


def _check_pair(warped: Tensor, fixed: Tensor, mean: Tensor, log_var: Tensor, displacement: Tensor) -> None:
    if warped.shape != fixed.shape or warped.ndim < 3 or warped.shape[:2] != (1, 1):
        raise ValueError(
            f"expected the warped and fixed images (1, 1, *S); got {tuple(warped.shape)} and {tuple(fixed.shape)}"
        )
    dims, size = fixed.ndim - 2, tuple(fixed.shape[2:])
    if mean.shape != log_var.shape or tuple(mean.shape[:2]) != (1, dims):
        raise ValueError(f"expected mean and log_var (1, {dims}, *V); got {tuple(mean.shape)}, {tuple(log_var.shape)}")
    if tuple(displacement.shape) != (1, dims, *size):
        raise ValueError(f"expected a displacement (1, {dims}, *{size}); got {tuple(displacement.shape)}")


def _feature_maps(
    warped: Tensor, fixed: Tensor, mean: Tensor, log_var: Tensor, displacement: Tensor
) -> Iterator[Tensor]:
    """Each feature of :data:`ERROR_FEATURES` in turn, (1, 1, *S) on the image grid (one at a time: a combination
    of them never holds them all). Velocity-grid maps are upsampled as the posterior is (trilinear)."""
    dims, size, grid = fixed.ndim - 2, tuple(fixed.shape[2:]), tuple(mean.shape[2:])

    def upsampled(x: Tensor) -> Tensor:
        return F.interpolate(x, size=size, mode="trilinear" if dims == 3 else "bilinear")

    def logged(x: Tensor) -> Tensor:
        return (x + LOG_FLOOR).log()

    fixed, displacement = fixed.float(), displacement.float()
    squared = squared_difference(warped, fixed)  # the residual's, boxed as residual_variance boxes it
    for window in RESIDUAL_WINDOWS:
        yield logged(upsampled(F.interpolate(_box_mean(squared, window), size=grid, mode="area")))
    del squared
    yield logged(upsampled(squared_laplacian(mean.float())))
    bending = squared_laplacian(displacement)
    for window in LAPLACIAN_WINDOWS:
        yield logged(_box_mean(bending, window))
    del bending
    yield logged(upsampled(log_var.float().exp().mean(1, keepdim=True)))
    # lengths as the root of summed squares: torch's norm over the channel axis is slower on a CPU
    yield logged(displacement.square().sum(1, keepdim=True).sqrt())
    gradient = squared_gradient(_box_mean(fixed, GRADIENT_SMOOTHING)).sqrt_()
    yield logged(_box_mean(gradient, GRADIENT_WINDOW))
    yield _box_mean((fixed > EDGE_LEVEL).float(), INSIDE_WINDOW)
    yield fixed


def error_features(warped: Tensor, fixed: Tensor, mean: Tensor, log_var: Tensor, displacement: Tensor) -> Tensor:
    """(1, len(ERROR_FEATURES), *S): the features of one registered pair on the image grid S. ``warped``, ``fixed``
    (1, 1, *S): the registered images (network inputs, in [0, 1]); ``mean``, ``log_var`` (1, D, *V): the posterior
    (the refined mean) on the velocity grid; ``displacement`` (1, D, *S): the mean's displacement (voxels of the
    image grid). What the error model is fitted on (:mod:`monai_probreg.fitting.error_cases`)."""
    _check_pair(warped, fixed, mean, log_var, displacement)
    with torch.inference_mode():
        return torch.cat(list(_feature_maps(warped, fixed, mean, log_var, displacement)), 1)


def check_error_model(coefficients: Sequence[float] | None) -> None:
    """ValueError unless ``coefficients`` is None or one finite number per :data:`ERROR_FEATURES` and the intercept."""
    if coefficients is None:
        return
    values = list(coefficients)
    if len(values) != len(ERROR_FEATURES) + 1 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in values
    ):
        raise ValueError(
            f"an error model is {len(ERROR_FEATURES) + 1} finite numbers (one per feature of "
            f"uncertainty.error_model.ERROR_FEATURES, then the intercept); got {coefficients!r}"
        )


def predicted_variance(
    coefficients: Sequence[float], warped: Tensor, fixed: Tensor, mean: Tensor, log_var: Tensor, displacement: Tensor
) -> Tensor:
    """(1, 1, *V): the error model's predicted squared error (mm^2), ``exp(features . coefficients + intercept)`` on
    the image grid (the features of :func:`error_features`, one at a time), averaged onto the velocity grid (area
    averaging, as the residual). ``coefficients``: one per feature, the intercept last."""
    check_error_model(coefficients)
    _check_pair(warped, fixed, mean, log_var, displacement)
    with torch.inference_mode():
        linear = torch.full_like(fixed, float(coefficients[-1]), dtype=torch.float32)
        for weight, feature in zip(coefficients[:-1], _feature_maps(warped, fixed, mean, log_var, displacement)):
            linear.add_(feature, alpha=float(weight))
        return F.interpolate(linear.exp_(), size=tuple(mean.shape[2:]), mode="area")


def pair_term(
    coefficients: Sequence[float] | None,
    warped: Tensor,
    fixed: Tensor,
    mean: Tensor,
    log_var: Tensor,
    displacement: Tensor,
) -> Tensor:
    """(1, 1, *V) the map the calibration's term weighs (``residual_weight``): the error model's prediction with
    ``coefficients`` (a calibration's ``error_model``), or the pair's residual without one (None)."""
    if coefficients is None:
        return residual_variance(warped, fixed, tuple(mean.shape[2:]))
    return predicted_variance(coefficients, warped, fixed, mean, log_var, displacement)


def fit_error_model(
    features: Sequence[np.ndarray], squared_errors: Sequence[np.ndarray], floor: float
) -> tuple[float, ...]:
    """Least squares of ``log(squared error + floor)`` on the features and a constant: the coefficients (intercept
    last). ``features``: per case (N, len(ERROR_FEATURES)); ``squared_errors``: per case (N,) mm^2, the components
    summed; ``floor`` > 0 (mm^2) keeps an exact voxel's log finite."""
    if len(features) != len(squared_errors) or not features:
        raise ValueError(
            f"expected one features array per squared-error array; got {len(features)} and {len(squared_errors)}"
        )
    design = np.concatenate([np.asarray(f, np.float64) for f in features])
    target = np.log(np.concatenate([np.asarray(e, np.float64) for e in squared_errors]) + floor)
    if design.ndim != 2 or design.shape[1] != len(ERROR_FEATURES) or design.shape[0] != target.shape[0]:
        raise ValueError(
            f"expected features (N, {len(ERROR_FEATURES)}) and N squared errors; got {design.shape} and {target.shape}"
        )
    if not (np.isfinite(design).all() and np.isfinite(target).all()):
        raise ValueError("the features and squared errors must be finite (squared errors >= 0)")
    coefficients, *_ = np.linalg.lstsq(np.c_[design, np.ones(len(design))], target, rcond=None)
    return tuple(float(c) for c in coefficients)
