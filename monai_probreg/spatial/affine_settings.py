"""Settings and results of the affine pre-alignment, shared by its two backends (:mod:`monai_probreg.spatial.affine`:
ITK and the dispatcher :func:`~monai_probreg.spatial.affine.align`; :mod:`monai_probreg.spatial.affine_torch`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import itk
import numpy as np

from monai_probreg.spatial.physical import affine_to_itk

__all__ = [
    "BACKENDS",
    "INITIALIZERS",
    "LOCAL_STAGE",
    "AffineResult",
    "AffineSettings",
    "StageReport",
    "rotation_angle_deg",
]

BACKENDS = ("torch", "itk")
# the start: centres of mass, or grid centres (ITK's CenteredTransformInitializer)
INITIALIZERS = ("moments", "geometry")
# when the local-correlation step runs after the mutual-information stages (monai_probreg.spatial.affine_local):
# never, for a pair of two contrasts only (--contrast other; the default), or always
LOCAL_STAGE = ("never", "other-contrast", "always")


@dataclass(frozen=True)
class AffineSettings:
    """Settings of the affine pre-alignment; per-level tuples run coarse to fine.

    Defaults: the torch backend, tuned on brain MRI (a native LPBA40 scan onto the LPBA40 atlas: affine-only Dice
    as ANTs ``Affine``'s, in seconds). Levels at 1/4, 1/2 and the full fixed grid with 2, 1 and 0 mm smoothing; 5% of
    each level's voxels sampled; the rigid stage stops at half resolution. :meth:`itk_defaults` gives the ITK
    backend's (two levels at 1/4 and 1/2, 20% sampled, as ``antsRegistrationSyNQuick.sh``'s linear stages stop at
    half resolution).

    ``max_samples`` caps the sample points of a level (torch backend): 5% of the full-resolution level is eight
    times the half-resolution level's points, for the same alignment. The cap trades affine-only Dice for time:
    ``experiments/affine_levers.py`` measures both for each cap and for dropping the full-resolution level.

    ``local_stage`` (one of :data:`LOCAL_STAGE`): when the result is refined by the squared local correlation
    (:mod:`monai_probreg.spatial.affine_local`, after either backend): by default for a pair of two contrasts
    (``--contrast other``), where mutual information between a head and a skull-stripped brain can prefer a
    shrunken head; ``local_starts``: the initializers the mutual-information stages run from before it (the
    result it scores best is refined; an ``initial`` transform is the only start); ``local_levels_mm``,
    ``local_kernels`` and ``local_iterations``: its levels (voxel size in mm, coarse to fine), window (level voxels)
    and iterations per level.

    Iterations are maxima (both backends stop a level earlier when converged). ITK backend only: ``max_step_mm``,
    ``convergence`` and ``deterministic`` (the line search's step bound, the stopping threshold, and the metric in
    one work unit; the torch backend is reproducible with any number of threads).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    smoothing_sigmas_mm: tuple[float, ...] = (2.0, 1.0, 0.0)
    rigid_iterations: tuple[int, ...] = (30, 15, 0)
    affine_iterations: tuple[int, ...] = (30, 15, 10)
    sampling_percentage: float = 0.05
    max_samples: int | None = 50_000  # at most this many sample points per level (None: no cap); torch backend only
    histogram_bins: int = 32
    initializer: str = "moments"
    seed: int = 1
    rigid_only: bool = False  # 6 parameters only (same subject, another session)
    backend: str = "torch"
    max_step_mm: float = 1.0
    convergence: float = 1e-6
    deterministic: bool = True  # the metric in one work unit: the same result every run (module docstring)
    local_stage: str = "other-contrast"
    local_starts: tuple[str, ...] = ("moments", "geometry")
    local_levels_mm: tuple[float, ...] = (4.0, 2.0)
    local_kernels: tuple[int, ...] = (3, 5)  # windows of 12 and 10 mm
    local_iterations: tuple[int, ...] = (20, 20)

    @classmethod
    def itk_defaults(cls, **changes) -> AffineSettings:
        """The ITK backend's defaults (class docstring), with ``changes``."""
        return cls(
            **{
                "shrink_factors": (4, 2),
                "smoothing_sigmas_mm": (2.0, 1.0),
                "rigid_iterations": (100, 50),
                "affine_iterations": (100, 50),
                "sampling_percentage": 0.20,
                "max_samples": None,
                "backend": "itk",
                **changes,
            }
        )

    def __post_init__(self) -> None:
        levels = len(self.shrink_factors)
        for name in ("smoothing_sigmas_mm", "rigid_iterations", "affine_iterations"):
            if len(getattr(self, name)) != levels:
                raise ValueError(
                    f"{name} needs one value per level ({levels}, as shrink_factors); got {getattr(self, name)}"
                )
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}; got {self.backend!r}")
        if min(self.rigid_iterations + self.affine_iterations, default=0) < 0:
            raise ValueError(f"iterations must be >= 0; got {self.rigid_iterations}, {self.affine_iterations}")
        if levels == 0 or min(self.shrink_factors) < 1:
            raise ValueError(f"shrink_factors must be >= 1, at least one level; got {self.shrink_factors}")
        if self.max_samples is not None and self.max_samples < 1:
            raise ValueError(f"max_samples must be >= 1 or None (no cap); got {self.max_samples}")
        if not 0 < self.sampling_percentage <= 1:
            raise ValueError(f"sampling_percentage must be in (0, 1]; got {self.sampling_percentage}")
        if self.local_stage not in LOCAL_STAGE:
            raise ValueError(f"local_stage must be one of {LOCAL_STAGE}; got {self.local_stage!r}")
        if not self.local_starts or not set(self.local_starts) <= set(INITIALIZERS):
            raise ValueError(f"local_starts must be one or more of {INITIALIZERS}; got {self.local_starts}")
        local = (self.local_levels_mm, self.local_kernels, self.local_iterations)
        if len({len(part) for part in local}) != 1 or not self.local_levels_mm:
            raise ValueError(
                "local_levels_mm, local_kernels and local_iterations need one value per level each, at least one "
                "level; got "
                f"{self.local_levels_mm}, {self.local_kernels}, {self.local_iterations}"
            )
        if not all(float(mm) > 0 for mm in self.local_levels_mm):
            raise ValueError(f"local_levels_mm must be > 0; got {self.local_levels_mm}")
        if not all(int(k) == k and k >= 3 and k % 2 == 1 for k in self.local_kernels):
            raise ValueError(f"local_kernels must be odd integers >= 3; got {self.local_kernels}")
        if min(self.local_iterations, default=0) < 0:
            raise ValueError(f"local_iterations must be >= 0; got {self.local_iterations}")
        if self.initializer not in INITIALIZERS:
            raise ValueError(f"initializer must be one of {INITIALIZERS}; got {self.initializer!r}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class StageReport:
    """What one stage did: iterations per level, final Mattes MI value (lower is better), stop reason."""

    name: str
    iterations: list[int] = field(default_factory=list)
    metric: float = float("nan")
    stop_condition: str = ""


@dataclass
class AffineResult:
    """``matrix``: fixed LPS -> moving LPS (4, 4); ``center``: the centre of its ITK form (LPS mm: the file's
    ``FixedParameters``; the map itself does not depend on it); ``initial``: the initializer's (4, 4); ``stages``:
    per-stage reports. :attr:`transform`: the same map as an ITK ``AffineTransform``, built on first use (the ITK
    backend passes its own): loading ITK's transform modules is slow, and the torch backend's command
    path does not need them (affine.tfm is written from the matrix and centre)."""

    matrix: np.ndarray
    center: np.ndarray
    initial: np.ndarray
    stages: list[StageReport]
    itk_transform: itk.Transform | None = field(default=None, repr=False)

    @property
    def transform(self) -> itk.Transform:
        if self.itk_transform is None:
            self.itk_transform = affine_to_itk(self.matrix, self.center)
        return self.itk_transform

    def summary(self) -> dict:
        return {
            "matrix_fixed_to_moving_lps": np.round(self.matrix, 6).tolist(),
            "determinant": float(np.linalg.det(self.matrix[:3, :3])),
            "rotation_deg": rotation_angle_deg(self.matrix),
            "stages": [asdict(s) for s in self.stages],
        }


def rotation_angle_deg(matrix: np.ndarray) -> float:
    """Angle of the rotation closest to ``matrix[:3, :3]`` (polar decomposition), in degrees."""
    u, _, vt = np.linalg.svd(matrix[:3, :3])
    rotation = u @ vt
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))
