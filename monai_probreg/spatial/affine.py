"""Affine pre-alignment of a scan to the fixed image: settings, result, and the ITK backend.

Two backends run the same method (rigid, then affine, Mattes mutual information over a pyramid):
``"torch"`` (the default, :mod:`monai_probreg.spatial.affine_torch`: about 2-4 s on a native scan, reproducible
with any number of threads) and ``"itk"`` (this module, ITK's v4 framework as antsRegistration uses it: 10-20 s
plus about 7 s to load ITK's registration modules). :func:`align` picks one from the settings.

Two stages, as ``antsRegistration`` runs them (``-t Rigid -t Affine``), each with
``itk.ImageRegistrationMethodv4``:

1. **rigid** (``VersorRigid3DTransform``, 6 parameters), started by ``CenteredTransformInitializer``: centres of
   mass aligned (``"moments"``) or image centres (``"geometry"``);
2. **affine** (``AffineTransform``, 12 parameters), started from the rigid result.

Each stage: Mattes mutual information (intensity-scale invariant: raw scanner values need no normalisation), a
multi-resolution pyramid (shrink factors of the fixed grid, Gaussian smoothing in mm), random metric sampling
with a fixed seed, and antsRegistration's optimiser for linear stages: conjugate gradient with a
golden-section line search (``ConjugateGradientLineSearchOptimizerv4``), parameter scales from the physical shift
each parameter causes (``RegistrationParameterScalesFromPhysicalShift``: no hand-tuned rotation/translation
scales), a step estimated once per level so that it moves points by at most ``max_step_mm``, and convergence
when the metric has changed by less than ``convergence`` over a window of 10 iterations.

Reproducibility: a fixed seed is not enough. ITK's Mattes metric merges its per-thread derivative buffers in the
order the threads finish (ITK pull request #6622, open in 5.4), so two multi-threaded runs of the same
registration differ (measured on a native LPBA40 scan: up to 0.33 mm of translation, Dice 0.5364 to 0.5369).
``deterministic=True`` (the default) computes the metric in one work unit; the image pyramid and everything else
stay multi-threaded.

The result maps a point of the **fixed** space to the **moving** space (LPS mm), ``A(p) = M p + offset``: the
transform ``itk.ResampleImageFilter`` and ``antsApplyTransforms`` use to bring the moving image onto the fixed grid.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import itk
import numpy as np

from monai_probreg.spatial.physical import affine_from_itk
from monai_probreg.spatial.volume_io import Volume, volume_to_itk

__all__ = ["BACKENDS", "AffineResult", "AffineSettings", "StageReport", "align", "load_itk_modules",
           "register_affine", "rotation_angle_deg"]

BACKENDS = ("torch", "itk")

_IMAGE = itk.Image[itk.F, 3]


@dataclass(frozen=True)
class AffineSettings:
    """Settings of the affine pre-alignment; per-level tuples run coarse to fine.

    Defaults: the torch backend, tuned on brain MRI (a native LPBA40 scan onto the LPBA40 atlas: affine-only Dice
    as ANTs ``Affine``'s, in 2-4 s). Levels at 1/4, 1/2 and the full fixed grid with 2, 1 and 0 mm smoothing; 5% of
    each level's voxels sampled; the rigid stage stops at half resolution. :meth:`itk_defaults` gives the ITK
    backend's (two levels at 1/4 and 1/2, 20% sampled, as ``antsRegistrationSyNQuick.sh``'s linear stages stop at
    half resolution).

    Iterations are maxima (both backends stop a level earlier when converged). ITK backend only: ``max_step_mm``,
    ``convergence`` and ``deterministic`` (the line search's step bound, the stopping threshold, and the metric in
    one work unit; the torch backend is reproducible with any number of threads).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    smoothing_sigmas_mm: tuple[float, ...] = (2.0, 1.0, 0.0)
    rigid_iterations: tuple[int, ...] = (30, 15, 0)
    affine_iterations: tuple[int, ...] = (30, 15, 10)
    sampling_percentage: float = 0.05
    histogram_bins: int = 32
    initializer: str = "moments"
    seed: int = 1
    rigid_only: bool = False  # 6 parameters only (same subject, another session)
    backend: str = "torch"
    max_step_mm: float = 1.0
    convergence: float = 1e-6
    deterministic: bool = True  # the metric in one work unit: the same result every run (module docstring)

    @classmethod
    def itk_defaults(cls, **changes) -> AffineSettings:
        """The ITK backend's defaults (class docstring), with ``changes``."""
        return cls(**{"shrink_factors": (4, 2), "smoothing_sigmas_mm": (2.0, 1.0), "rigid_iterations": (100, 50),
                      "affine_iterations": (100, 50), "sampling_percentage": 0.20, "backend": "itk", **changes})

    def __post_init__(self) -> None:
        levels = len(self.shrink_factors)
        for name in ("smoothing_sigmas_mm", "rigid_iterations", "affine_iterations"):
            if len(getattr(self, name)) != levels:
                raise ValueError(f"{name} needs one value per level ({levels}, as shrink_factors); "
                                 f"got {getattr(self, name)}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}; got {self.backend!r}")
        if min(self.rigid_iterations + self.affine_iterations, default=0) < 0:
            raise ValueError(f"iterations must be >= 0; got {self.rigid_iterations}, {self.affine_iterations}")
        if levels == 0 or min(self.shrink_factors) < 1:
            raise ValueError(f"shrink_factors must be >= 1, at least one level; got {self.shrink_factors}")
        if not 0 < self.sampling_percentage <= 1:
            raise ValueError(f"sampling_percentage must be in (0, 1]; got {self.sampling_percentage}")
        if self.initializer not in ("moments", "geometry"):
            raise ValueError(f"initializer must be 'moments' or 'geometry'; got {self.initializer!r}")

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
    """``transform``: the ITK transform (fixed LPS -> moving LPS); ``matrix``: the same as (4, 4); ``initial``:
    the initializer's (4, 4); ``stages``: per-stage reports."""

    transform: itk.Transform
    matrix: np.ndarray
    initial: np.ndarray
    stages: list[StageReport]

    def summary(self) -> dict:
        return {
            "matrix_fixed_to_moving_lps": np.round(self.matrix, 6).tolist(),
            "determinant": float(np.linalg.det(self.matrix[:3, :3])),
            "rotation_deg": rotation_angle_deg(self.matrix),
            "stages": [asdict(s) for s in self.stages],
        }


def load_itk_modules() -> None:
    """Load ITK's lazily imported registration modules now (several seconds on first use), so that a timed
    registration measures the registration and a batch pays the cost once."""
    for name in ("ImageRegistrationMethodv4", "MattesMutualInformationImageToImageMetricv4",
                 "ConjugateGradientLineSearchOptimizerv4Template", "RegistrationParameterScalesFromPhysicalShift",
                 "VersorRigid3DTransform", "AffineTransform", "CenteredTransformInitializer",
                 "MultiResolutionIterationEvent"):
        getattr(itk, name)


def rotation_angle_deg(matrix: np.ndarray) -> float:
    """Angle of the rotation closest to ``matrix[:3, :3]`` (polar decomposition), in degrees."""
    u, _, vt = np.linalg.svd(matrix[:3, :3])
    rotation = u @ vt
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


def _run_stage(name: str, fixed: itk.Image, moving: itk.Image, transform: itk.Transform,
               iterations: tuple[int, ...], settings: AffineSettings) -> StageReport:
    """Optimise ``transform`` in place with one multi-resolution ImageRegistrationMethodv4 run."""
    metric = itk.MattesMutualInformationImageToImageMetricv4[_IMAGE, _IMAGE].New()
    metric.SetNumberOfHistogramBins(settings.histogram_bins)
    metric.SetUseMovingImageGradientFilter(False)  # gradients on the fly at the samples, as antsRegistration does
    metric.SetUseFixedImageGradientFilter(False)
    if settings.deterministic:  # thread-order reduction of its derivative otherwise (module docstring)
        metric.SetMaximumNumberOfWorkUnits(1)

    scales = itk.RegistrationParameterScalesFromPhysicalShift[type(metric)].New()
    scales.SetMetric(metric)
    optimizer = itk.ConjugateGradientLineSearchOptimizerv4Template[itk.D].New()
    optimizer.SetLowerLimit(0.0)  # golden-section line search over [0, 2] x the estimated step, as antsRegistration
    optimizer.SetUpperLimit(2.0)
    optimizer.SetEpsilon(0.2)
    optimizer.SetScalesEstimator(scales)
    optimizer.SetDoEstimateLearningRateOnce(True)
    optimizer.SetMaximumStepSizeInPhysicalUnits(settings.max_step_mm)
    optimizer.SetLearningRate(1.0)
    optimizer.SetNumberOfIterations(int(iterations[0]))
    optimizer.SetMinimumConvergenceValue(settings.convergence)
    optimizer.SetConvergenceWindowSize(10)

    registration = itk.ImageRegistrationMethodv4[_IMAGE, _IMAGE].New()
    registration.SetFixedImage(fixed)
    registration.SetMovingImage(moving)
    registration.SetMetric(metric)
    registration.SetOptimizer(optimizer)
    registration.SetInitialTransform(transform)
    registration.SetInPlace(True)
    registration.SetNumberOfLevels(len(settings.shrink_factors))
    registration.SetShrinkFactorsPerLevel([int(s) for s in settings.shrink_factors])
    registration.SetSmoothingSigmasPerLevel([float(s) for s in settings.smoothing_sigmas_mm])
    registration.SetSmoothingSigmasAreSpecifiedInPhysicalUnits(True)
    registration.SetMetricSamplingStrategy(itk.ImageRegistrationMethodv4Enums.MetricSamplingStrategy_RANDOM)
    registration.SetMetricSamplingPercentage(float(settings.sampling_percentage))
    registration.MetricSamplingReinitializeSeed(int(settings.seed))

    report = StageReport(name)

    def start_level() -> None:  # fired after a level is set up, before its optimisation starts
        level = int(registration.GetCurrentLevel())
        if level > 0:
            report.iterations.append(int(optimizer.GetCurrentIteration()))
        optimizer.SetNumberOfIterations(int(iterations[level]))

    registration.AddObserver(itk.MultiResolutionIterationEvent(), start_level)
    registration.Update()
    report.iterations.append(int(optimizer.GetCurrentIteration()))
    report.metric = float(optimizer.GetValue())
    report.stop_condition = str(optimizer.GetStopConditionDescription()).strip()
    return report


def align(fixed: Volume, moving: Volume, settings: AffineSettings | None = None,
          fixed_itk: itk.Image | None = None) -> AffineResult:
    """Rigid then affine registration of ``moving`` to ``fixed`` with the backend of ``settings`` (module
    docstring); ``fixed_itk``: ``fixed`` already converted for ITK (prepared once for a batch), or None."""
    settings = settings or AffineSettings()
    if settings.backend == "torch":
        from monai_probreg.spatial.affine_torch import register_affine_torch

        return register_affine_torch(fixed, moving, settings)
    return register_affine(fixed_itk if fixed_itk is not None else volume_to_itk(fixed), volume_to_itk(moving),
                           settings)


def register_affine(fixed: itk.Image, moving: itk.Image, settings: AffineSettings | None = None) -> AffineResult:
    """The ITK backend: rigid then affine registration of ``moving`` to ``fixed`` (``itk.Image[itk.F, 3]`` with
    their geometry).

    Returns the fixed -> moving transform (module docstring). Deterministic for given inputs and settings.
    """
    settings = settings or AffineSettings.itk_defaults()
    rigid = itk.VersorRigid3DTransform[itk.D].New()
    initializer = itk.CenteredTransformInitializer[type(rigid), _IMAGE, _IMAGE].New(
        Transform=rigid, FixedImage=fixed, MovingImage=moving)
    if settings.initializer == "moments":
        initializer.MomentsOn()
    else:
        initializer.GeometryOn()
    initializer.InitializeTransform()
    initial = affine_from_itk(rigid)
    stages = [_run_stage("rigid", fixed, moving, rigid, settings.rigid_iterations, settings)]
    result: itk.Transform = rigid
    if not settings.rigid_only:
        affine = itk.AffineTransform[itk.D, 3].New()
        affine.SetCenter(rigid.GetCenter())
        affine.SetMatrix(rigid.GetMatrix())
        affine.SetTranslation(rigid.GetTranslation())
        stages.append(_run_stage("affine", fixed, moving, affine, settings.affine_iterations, settings))
        result = affine
    return AffineResult(result, affine_from_itk(result), initial, stages)
