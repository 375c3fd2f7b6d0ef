"""A subject made from a template by a known transform: the ground truth of ``monai-probreg demo``.

The registration convention (:mod:`monai_probreg.spatial.physical`) maps a point ``p`` of the fixed image to the
moving image, ``phi(p) = p + D(p)``, and stores ``D`` in LPS mm on the fixed grid (``warp.nii.gz``). The template
is the fixed image and the synthetic subject the moving one, so the known answer is

    phi(p) = rho(p + u(p))

with ``u`` the displacement of ``exp(v)`` (a random smooth stationary velocity ``v``,
:class:`~monai_probreg.data.augmentation.RandDiffeomorphicd`) in mm and ``rho`` a rigid turn about the template's
centre of brain mass followed by a shift. The subject is the template pulled back through ``phi``'s inverse:

    subject(q) = template(phi^-1(q)),    phi^-1(q) = a + u_inv(a),   a = rho^-1(q),   u_inv: of exp(-v)

then a smooth multiplicative bias field (MONAI ``RandBiasField``) and Rician noise (MONAI ``RandRicianNoise``), on
the template's grid, stored with its axes in another order (``axcodes``, e.g. a sagittal acquisition's "PIR": the
same voxels, permuted and flipped, with the header that says so), as a scanner would hand it over. ``exp(v)`` and ``exp(-v)`` come from the same scaling and squaring, so ``phi(phi^-1(q)) = q``
only up to its integration error; :attr:`SyntheticSubject.inverse_error_mm` reports it inside the brain (the
floor of any error measured against this truth).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from monai.transforms import RandBiasField, RandRicianNoise
from monai.transforms.utils import create_rotate
from nibabel.orientations import apply_orientation, axcodes2ornt, inv_ornt_aff, io_orientation, ornt_transform

from monai_probreg.data.augmentation import RandDiffeomorphicd
from monai_probreg.spatial.physical import apply_affine, grid_points, voxel_to_mm
from monai_probreg.spatial.point_sampling import sample_linear
from monai_probreg.spatial.volume_io import Volume

__all__ = ["SyntheticSettings", "SyntheticSubject", "brain_mask", "synthesize_subject"]


@dataclass(frozen=True)
class SyntheticSettings:
    """How far and how badly the synthetic subject departs from its template (all drawn per seed).

    Args:
        max_rotation_deg: each of the three rotation angles is uniform in ``[-max, max]`` degrees.
        max_shift_mm: each shift component is uniform in ``[-max, max]`` mm.
        deform_rms_mm: RMS of the random velocity over the template grid, mm (the displacement's is close to it).
        deform_spacing_mm: spacing of the velocity's control points, mm (larger = smoother).
        bias_coeff: coefficients of the degree-3 log-polynomial bias field, drawn in ``[0, bias_coeff]``.
        noise_fraction: standard deviation of the Rician noise, a fraction of the brain's 99th intensity percentile.
        num_steps: scaling-and-squaring steps of ``exp(v)`` and ``exp(-v)``.
        axcodes: the subject's array orientation (nibabel's RAS codes); None = the template's.
    """

    max_rotation_deg: float = 5.0
    max_shift_mm: float = 5.0
    deform_rms_mm: float = 2.5
    deform_spacing_mm: float = 16.0
    bias_coeff: float = 0.15
    noise_fraction: float = 0.03
    num_steps: int = 7
    axcodes: str | None = "PIR"

    def __post_init__(self) -> None:
        if self.axcodes is not None:
            codes = self.axcodes.upper()
            if len(codes) != 3 or sorted(axcodes2ornt(codes, ("LR", "PA", "IS"))[:, 0].tolist()) != [0, 1, 2]:
                raise ValueError(f"axcodes must name each of the three axes once, e.g. 'PIR'; got {self.axcodes!r}")
        for f in dataclasses.fields(self):
            if f.name == "axcodes":
                continue
            value = getattr(self, f.name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{f.name} must be a finite number >= 0; got {value!r}")
        if self.deform_spacing_mm <= 0 or self.num_steps < 1:
            raise ValueError(
                f"deform_spacing_mm must be > 0 and num_steps >= 1; got {self.deform_spacing_mm} and {self.num_steps}"
            )

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class SyntheticSubject(NamedTuple):
    """``image``: the subject, on the template's grid (its axes in ``settings.axcodes`` order). ``true_warp`` (*S, 3): the known ``D(p) = phi(p) - p``, LPS mm
    on the template grid (the convention of ``warp.nii.gz``). ``rigid`` (4, 4): ``rho``, LPS mm.
    ``inverse_error_mm``: median ``|phi(phi^-1(q)) - q|`` inside the brain, the truth's own accuracy."""

    image: Volume
    true_warp: np.ndarray
    rigid: np.ndarray
    rotation_deg: tuple[float, float, float]
    shift_mm: tuple[float, float, float]
    inverse_error_mm: float


def _reoriented(volume: Volume, axcodes: str | None) -> Volume:
    """The same voxels with the axes in ``axcodes`` order and the header that says so (no interpolation)."""
    if axcodes is None:
        return volume
    ornt = ornt_transform(io_orientation(volume.ras_affine), axcodes2ornt(axcodes.upper()))
    index_to_lps = volume.index_to_lps @ inv_ornt_aff(ornt, volume.shape)
    return Volume(np.ascontiguousarray(apply_orientation(volume.array, ornt)), index_to_lps, volume.path)


def brain_mask(template: Volume) -> np.ndarray:
    """The template's brain: its non-zero voxels (a skull-stripped template has an exact zero background)."""
    return np.asarray(template.array) > 0


def _rigid(template: Volume, mask: np.ndarray, rotation_deg: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    """``rho(p) = c + R (p - c) + t`` (4, 4) in LPS mm, ``c`` the intensity-weighted centre of the brain."""
    weights = np.where(mask, np.asarray(template.array, np.float64), 0.0)
    centre_index = (
        np.array(
            [
                (weights.sum(axis=tuple(a for a in range(3) if a != k)) * np.arange(n)).sum()
                for k, n in enumerate(template.shape)
            ]
        )
        / weights.sum()
    )
    centre = template.index_to_lps[:3, :3] @ centre_index + template.index_to_lps[:3, 3]
    rotation = np.asarray(create_rotate(3, np.deg2rad(rotation_deg).tolist()), np.float64)[:3, :3]
    rigid = np.eye(4)
    rigid[:3, :3] = rotation
    rigid[:3, 3] = centre - rotation @ centre + shift_mm
    return rigid


def _velocity_displacements(template: Volume, settings: SyntheticSettings, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(exp(v), exp(-v)) displacements (*S, 3), LPS mm on the template grid, of one seeded random velocity."""
    voxel = float(np.mean(template.spacing))  # the control grid and the RMS in voxels of a (near-)isotropic grid
    draw = RandDiffeomorphicd(
        keys=["image"],
        magnitude=settings.deform_rms_mm / voxel,
        control_spacing=max(settings.deform_spacing_mm / voxel, 1.0),
        num_steps=settings.num_steps,
    )
    draw.set_random_state(seed=seed)
    draw.randomize(template.shape)
    forward, inverse = (draw.displacement(template.shape, inverse=flag)[0].numpy() for flag in (False, True))
    return voxel_to_mm(forward, template.index_to_lps), voxel_to_mm(inverse, template.index_to_lps)


def synthesize_subject(template: Volume, settings: SyntheticSettings | None = None, seed: int = 0) -> SyntheticSubject:
    """The template turned, shifted and deformed by a known ``phi``, with a bias field and noise (module docstring).
    The same template, settings and seed give the same subject."""
    settings = settings or SyntheticSettings()
    mask = brain_mask(template)
    if not mask.any():
        raise ValueError(f"{template.path}: the template has no non-zero voxel (expected a skull-stripped brain)")
    rng = np.random.default_rng(seed)
    rotation = rng.uniform(-settings.max_rotation_deg, settings.max_rotation_deg, 3)
    shift = rng.uniform(-settings.max_shift_mm, settings.max_shift_mm, 3)
    rigid = _rigid(template, mask, rotation, shift)
    forward, inverse = _velocity_displacements(template, settings, seed)
    points = grid_points(template.shape, template.index_to_lps)
    # phi^-1(q) = a + u_inv(a), a = rho^-1(q): u_inv extended by its border value beyond the grid
    pulled = apply_affine(np.linalg.inv(rigid), points)
    pulled += sample_linear(Volume(inverse, template.index_to_lps), pulled, outside="border")
    image = sample_linear(template, pulled, fill=0.0).astype(np.float32)
    # the truth's accuracy: phi(phi^-1(q)) - q where the subject shows brain
    pushed = pulled + sample_linear(Volume(forward, template.index_to_lps), pulled, outside="border")
    round_trip = np.linalg.norm(apply_affine(rigid, pushed) - points, axis=-1)[image > 0]
    true_warp = apply_affine(rigid, points + forward) - points
    brain_level = float(np.percentile(image[image > 0], 99))
    bias = RandBiasField(degree=3, coeff_range=(0.0, settings.bias_coeff), prob=1.0)
    noise = RandRicianNoise(prob=1.0, std=settings.noise_fraction * brain_level, sample_std=False)
    bias.set_random_state(seed=seed)
    noise.set_random_state(seed=seed)
    image = np.asarray(torch.as_tensor(noise(bias(image[None])))[0], np.float32)
    return SyntheticSubject(
        _reoriented(template.with_array(image), settings.axcodes),
        true_warp.astype(np.float32),
        rigid,
        tuple(float(a) for a in rotation),
        tuple(float(t) for t in shift),
        float(np.median(round_trip)) if round_trip.size else 0.0,
    )
