"""Training-time augmentation: spatial, of the moving scan (a random affine, MONAI ``RandAffined``, or a random smooth
diffeomorphism, :class:`RandDiffeomorphicd`), and intensity, of the network's inputs (:func:`intensity_augmentation`).

Only the moving side is augmented: the fixed image is the atlas, the one space every output lives in, so moving it
would change the task. The moving image and its label map get the *same* random affine (MONAI draws it once per
call for all keys): the image resampled linearly, the labels by nearest neighbour, so no label value is invented.
The transform runs after the cached deterministic chain (``CacheDataset`` caches up to the first random
transform), on the network grid, so an epoch pays only for one small resampling per subject.

Why: the shipped models are trained on 24 subjects; the semi-supervised Dice term fits them noticeably better than
unseen subjects. Small random poses (a few degrees, a few per cent of scale, a few voxels of shift) give the network
more moving anatomy to match without changing what it has to learn. The ranges are the bundle's
``augment_*`` settings; ``augment_prob`` 0 (the default) turns augmentation off.

:class:`RandDiffeomorphicd` is written here because MONAI's ``Rand3DElasticd`` smooths full-resolution noise with
a Gaussian filter (slow at the smoothness a training deformation needs: a large share of a training iteration on a
CPU) and gives no diffeomorphism guarantee. Ours draws the velocity on a coarse control grid, upsamples it (smooth by
construction) and integrates it with the package's own scaling and squaring at half resolution: a smooth invertible
warp at a fraction of that cost.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from monai.transforms import (
    Compose,
    CopyItemsd,
    EnsureTyped,
    MapTransform,
    RandAdjustContrastd,
    RandAffined,
    RandBiasFieldd,
    RandGaussianNoised,
    RandGaussianSmoothd,
    RandomizableTransform,
    ScaleIntensityRangePercentilesd,
)

from monai_probreg.blocks.integration import ScalingAndSquaring, resize_displacement
from monai_probreg.blocks.warp import warp_image, warp_labels
from monai_probreg.data.dataset import IMAGE_KEYS, LABEL_KEYS
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE

__all__ = ["INPUT_SUFFIX", "RandDiffeomorphicd", "intensity_augmentation", "moving_augmentation"]

_MOVING_IMAGE = IMAGE_KEYS[0]
_MOVING_LABEL = LABEL_KEYS[0]
INPUT_SUFFIX = "_input"  # "moving_input"/"fixed_input": what the network sees when they differ from the images
_MAX_AXES = 3  # rotation and shift parameters MONAI reads per axis; a 2-d grid uses the first one (rotation) or two


def _non_negative(name: str, values: float | Sequence[float]) -> tuple[float, ...]:
    # one number applies to every axis: MONAI would otherwise randomise only the first one
    seq = (values,) * _MAX_AXES if isinstance(values, (int, float)) else tuple(values)
    out = tuple(float(v) for v in seq)
    if not out or any(v < 0 for v in out):
        raise ValueError(f"{name} must be one or more non-negative numbers, got {values!r}")
    return out


class RandDiffeomorphicd(RandomizableTransform, MapTransform):
    """Warp ``keys`` (linear) and ``label_keys`` (nearest) by one random smooth diffeomorphism ``exp(v)``.

    The velocity ``v`` is standard normal noise on a control grid of one point per ``control_spacing`` voxels (plus
    one, so the corners are control points), upsampled linearly to the image grid, scaled so that its RMS over the
    grid is ``magnitude`` voxels (the RMS displacement of a field this smooth is within a few per cent of it), and
    integrated with ``num_steps`` squarings on a grid of half the size (then upsampled, as the model's own field).
    Pull-back, as everywhere in the package: ``out[x] = in[x + u(x)]``.

    Shapes: every key (C, *S), 2-d or 3-d, all on the same grid; shapes and dtypes are kept (labels rounded back).

    Args:
        keys: image keys, resampled linearly (border values outside the grid).
        label_keys: integer label keys, resampled by nearest neighbour (0 outside the grid).
        prob: probability that a pair is warped.
        magnitude: RMS of the velocity in voxels of the grid the transform sees.
        control_spacing: voxels between control points: larger = smoother.
        num_steps: scaling-and-squaring steps.
    """

    def __init__(
        self,
        keys: Sequence[str],
        label_keys: Sequence[str] = (),
        prob: float = 1.0,
        magnitude: float = 1.5,
        control_spacing: float = 8.0,
        num_steps: int = 7,
    ) -> None:
        MapTransform.__init__(self, list(keys) + list(label_keys))
        RandomizableTransform.__init__(self, prob)
        if magnitude < 0 or control_spacing < 1:
            raise ValueError(
                f"magnitude must be >= 0 and control_spacing >= 1 voxel; got {magnitude!r}, {control_spacing!r}"
            )
        self.image_keys, self.label_keys = tuple(keys), tuple(label_keys)
        self.magnitude, self.control_spacing = float(magnitude), float(control_spacing)
        self.integrate = ScalingAndSquaring(num_steps=num_steps)
        self._noise: np.ndarray | None = None

    def randomize(self, spatial_size: Sequence[int]) -> None:  # type: ignore[override]
        super().randomize(None)
        control = [int(np.ceil((n - 1) / self.control_spacing)) + 1 for n in spatial_size]
        self._noise = self.R.standard_normal((1, len(spatial_size), *control)).astype(np.float32)

    def displacement(self, spatial_size: Sequence[int], inverse: bool = False) -> torch.Tensor:
        """The displacement (1, D, *S) of the last drawn velocity ``exp(v)`` on ``spatial_size``, in voxels;
        ``inverse``: of ``exp(-v)``, the inverse transform (integrated the same way)."""
        if self._noise is None:
            raise RuntimeError("randomize() must be called before displacement()")
        full = tuple(int(n) for n in spatial_size)
        half = tuple((n + 1) // 2 for n in full)  # integrate at half resolution, as the model does: 2**D x cheaper
        velocity = resize_displacement(torch.from_numpy(self._noise), half)
        rms_full = float(resize_displacement(velocity, full).pow(2).sum(1).mean().sqrt().clamp_min(1e-8))
        with torch.no_grad():
            scale = (-1.0 if inverse else 1.0) * self.magnitude / rms_full
            return resize_displacement(self.integrate(velocity * scale), full)

    def __call__(self, data: dict) -> dict:  # type: ignore[override]
        d = dict(data)
        first = d[self.image_keys[0]] if self.image_keys else d[self.label_keys[0]]
        spatial_size = tuple(first.shape[1:])
        self.randomize(spatial_size)
        if not self._do_transform or self.magnitude == 0:
            return d
        ddf = self.displacement(spatial_size)
        for key in self.key_iterator(d):
            value = d[key]
            if tuple(value.shape[1:]) != spatial_size:
                raise ValueError(
                    f"{key} must be on the grid of {self.keys[0]}: expected spatial shape "
                    f"{spatial_size}, got {tuple(value.shape[1:])}"
                )
            src = torch.as_tensor(value)[None]
            if key in self.label_keys:
                out = warp_labels(src.float(), ddf).to(src.dtype)
            else:
                out = warp_image(src.float(), ddf).to(src.dtype)
            d[key] = value.__class__(out[0], meta=value.meta) if hasattr(value, "meta") else out[0]
        return d


def moving_augmentation(
    prob: float = 0.0,
    rotate_range: float | Sequence[float] = 0.0,
    scale_range: float | Sequence[float] = 0.0,
    translate_range: float | Sequence[float] = 0.0,
    with_labels: bool = False,
    seed: int | None = None,
    deform_magnitude: float = 0.0,
    deform_spacing: float = 8.0,
) -> Compose:
    """Random affine of the moving image (and its label map) about the grid centre, then, if
    ``deform_magnitude`` > 0, a random smooth diffeomorphism (:class:`RandDiffeomorphicd`).

    Args:
        prob: probability that a pair is augmented (0 = identity, 1 = always).
        rotate_range: maximum rotation in radians, per axis (one value for all, or one per rotation axis);
            each angle is drawn uniformly in ``[-r, r]``.
        scale_range: maximum relative scaling per axis; the factor is ``1 + U(-s, s)``.
        translate_range: maximum shift in voxels of the grid the transform sees (the network grid in training).
        with_labels: also transform ``moving_label`` (nearest neighbour; its integer dtype is restored).
        seed: seed of the transform's own random state (``None``: set by MONAI's ``set_determinism``).
        deform_magnitude: RMS of the random velocity in voxels (0: no deformation).
        deform_spacing: control-point spacing of the random velocity in voxels (its smoothness).

    Shapes: ``moving`` (C, *S) and ``moving_label`` (1, *S) keep their shape; out-of-field voxels become 0.

    Raises:
        ValueError: ``prob`` outside [0, 1], a negative range or a negative ``deform_magnitude``.
    """
    if not 0.0 <= float(prob) <= 1.0:
        raise ValueError(f"prob must be in [0, 1], got {prob!r}")
    rotate = _non_negative("rotate_range", rotate_range)
    scale = _non_negative("scale_range", scale_range)
    translate = _non_negative("translate_range", translate_range)
    if deform_magnitude < 0:
        raise ValueError(f"deform_magnitude must be >= 0, got {deform_magnitude!r}")
    keys = [_MOVING_IMAGE] + ([_MOVING_LABEL] if with_labels else [])
    modes = ["bilinear"] + (["nearest"] if with_labels else [])
    affine = RandAffined(
        keys=keys,
        prob=float(prob),
        rotate_range=rotate,
        scale_range=scale,
        translate_range=translate,
        mode=modes,
        padding_mode="zeros",
        cache_grid=False,
    )
    chain: list = [affine]
    if deform_magnitude > 0:  # a second resampling: each step on its own stays a plain, testable transform
        chain.append(
            RandDiffeomorphicd(
                keys=[_MOVING_IMAGE],
                label_keys=keys[1:],
                prob=float(prob),
                magnitude=deform_magnitude,
                control_spacing=deform_spacing,
            )
        )
    chain += [EnsureTyped(keys=[_MOVING_IMAGE], dtype=torch.float32, track_meta=True)]
    if with_labels:
        chain.append(EnsureTyped(keys=[_MOVING_LABEL], dtype=torch.int16, track_meta=True))
    augmentation = Compose(chain)
    if seed is not None:  # after Compose: its constructor re-seeds the transforms it holds
        augmentation.set_random_state(seed=seed)
    return augmentation


def intensity_augmentation(
    prob: float = 0.0,
    bias_coeff: float = 0.2,
    gamma: Sequence[float] = (0.6, 1.6),
    smooth_sigma: Sequence[float] = (0.25, 1.0),
    noise_std: float = 0.03,
    seed: int | None = None,
) -> Compose:
    """Independent random intensity changes of the moving and the fixed image, as *network inputs* only.

    Each image of the pair is copied to ``<key>_input`` (:data:`INPUT_SUFFIX`) and the copy gets, each with
    probability ``prob`` and drawn independently per image: a smooth multiplicative bias field (MONAI
    ``RandBiasFieldd``, degree 3), a gamma change of contrast (``RandAdjustContrastd``), a Gaussian blur (resolution
    loss, ``RandGaussianSmoothd``) and Gaussian noise (``RandGaussianNoised``); it is then scaled to [0, 1] by the
    same percentiles as the preprocessing (:data:`~monai_probreg.spatial.intensity.LOWER_PERCENTILE`), as a scan
    from another scanner would be at inference. The clean images stay under ``moving``/``fixed``:
    :func:`~monai_probreg.engines.training.prepare_registration_batch` feeds the ``_input`` copies to the network
    and :class:`~monai_probreg.engines.training.RegistrationLoss` scores the clean moving image warped by the
    predicted displacement against the clean fixed one. So the likelihood keeps its meaning (one noise level
    ``image_sigma``, the same contrast on both sides) while the network learns not to depend on one scanner's
    intensity profile (the issue "Robust to the scans users bring").

    Args:
        prob: probability of each change, per image (0: no ``_input`` keys are made, training is unchanged).
        bias_coeff: bias-field polynomial coefficients are drawn in ``[0, bias_coeff]``.
        gamma: range of the contrast exponent (1 = unchanged).
        smooth_sigma: range of the blur's standard deviation, voxels of the grid the transform sees.
        noise_std: maximum standard deviation of the noise, in the [0, 1] intensity units.
        seed: seed of the transforms' random state (``None``: set by MONAI's ``set_determinism``).

    Raises:
        ValueError: ``prob`` outside [0, 1], a negative coefficient or noise, or a range not ``(low <= high)``.
    """
    if not 0.0 <= float(prob) <= 1.0:
        raise ValueError(f"prob must be in [0, 1], got {prob!r}")
    if bias_coeff < 0 or noise_std < 0:
        raise ValueError(f"bias_coeff and noise_std must be >= 0, got {bias_coeff!r} and {noise_std!r}")
    for name, pair, low in (("gamma", gamma, 1e-3), ("smooth_sigma", smooth_sigma, 0.0)):
        if len(pair) != 2 or not low <= float(pair[0]) <= float(pair[1]):
            raise ValueError(f"{name} must be a range (low, high) with {low} <= low <= high, got {pair!r}")
    if prob == 0:
        return Compose([])
    chain: list = []
    for key in IMAGE_KEYS:  # one set of transforms per image: independent draws for moving and fixed
        name = key + INPUT_SUFFIX
        sigma = (float(smooth_sigma[0]), float(smooth_sigma[1]))
        chain += [
            CopyItemsd(keys=[key], names=[name]),
            RandBiasFieldd(keys=[name], prob=float(prob), degree=3, coeff_range=(0.0, float(bias_coeff))),
            RandAdjustContrastd(keys=[name], prob=float(prob), gamma=(float(gamma[0]), float(gamma[1]))),
            RandGaussianSmoothd(keys=[name], prob=float(prob), sigma_x=sigma, sigma_y=sigma, sigma_z=sigma),
            RandGaussianNoised(keys=[name], prob=float(prob), mean=0.0, std=float(noise_std)),
            ScaleIntensityRangePercentilesd(
                keys=[name], lower=LOWER_PERCENTILE, upper=UPPER_PERCENTILE, b_min=0.0, b_max=1.0, clip=True
            ),
            EnsureTyped(keys=[name], dtype=torch.float32, track_meta=True),
        ]
    augmentation = Compose(chain)
    if seed is not None:
        augmentation.set_random_state(seed=seed)
    return augmentation
