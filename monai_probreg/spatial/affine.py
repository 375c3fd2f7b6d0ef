"""Affine pre-alignment of a scan to the fixed image: the dispatcher :func:`align` and the ITK backend (settings and
results: :mod:`monai_probreg.spatial.affine_settings`, re-exported here).

Two backends run the same method (rigid, then affine, Mattes mutual information over a pyramid):
``"torch"`` (the default, :mod:`monai_probreg.spatial.affine_torch`: several times faster, reproducible with any
number of threads) and ``"itk"`` (this module, ITK's v4 framework as antsRegistration uses it, plus the time to load
ITK's registration modules; both timed in docs/speed.md). :func:`align` picks one from the settings.

Two stages, as ``antsRegistration`` runs them (``-t Rigid -t Affine``), each with
``itk.ImageRegistrationMethodv4``:

1. **rigid** (``VersorRigid3DTransform``, 6 parameters), started by ``CenteredTransformInitializer``: centres of
   mass aligned (``"moments"``) or image centres (``"geometry"``);
2. **affine** (``AffineTransform``, 12 parameters), started from the rigid result.

Given an ``initial`` transform (an earlier registration's, ``--initial-transform``), the stages start from it as
``antsRegistration -r`` does: it is ITK's moving initial transform, applied after the optimised one (``A = initial o
S``), and the rigid stage starts from the identity about the fixed image's centre.

Each stage: Mattes mutual information (intensity-scale invariant: raw scanner values need no normalisation), a
multi-resolution pyramid (shrink factors of the fixed grid, Gaussian smoothing in mm), random metric sampling
with a fixed seed, and antsRegistration's optimiser for linear stages: conjugate gradient with a
golden-section line search (``ConjugateGradientLineSearchOptimizerv4``), parameter scales from the physical shift
each parameter causes (``RegistrationParameterScalesFromPhysicalShift``: no hand-tuned rotation/translation
scales), a step estimated once per level so that it moves points by at most ``max_step_mm``, and convergence
when the metric has changed by less than ``convergence`` over a window of 10 iterations.

Reproducibility: a fixed seed is not enough. ITK's Mattes metric merges its per-thread derivative buffers in the
order the threads finish (ITK pull request #6622, open in 5.4), so two multi-threaded runs of the same
registration differ (by a fraction of a millimetre of translation on a native LPBA40 scan).
``deterministic=True`` (the default) computes the metric in one work unit; the image pyramid and everything else
stay multi-threaded.

The result maps a point of the **fixed** space to the **moving** space (LPS mm), ``A(p) = M p + offset``: the
transform ``itk.ResampleImageFilter`` and ``antsApplyTransforms`` use to bring the moving image onto the fixed grid.
"""

from __future__ import annotations

import itk
import numpy as np

from monai_probreg.spatial.affine_settings import (
    BACKENDS,
    AffineResult,
    AffineSettings,
    StageReport,
    rotation_angle_deg,
)
from monai_probreg.spatial.affine_torch import FixedSamples, register_affine_torch
from monai_probreg.spatial.physical import affine_from_itk, affine_to_itk
from monai_probreg.spatial.volume_io import Volume, volume_to_itk

__all__ = [
    "BACKENDS",
    "AffineResult",
    "AffineSettings",
    "StageReport",
    "align",
    "load_itk_modules",
    "register_affine",
    "rotation_angle_deg",
]  # the settings and results re-exported from affine_settings


def _image_type():
    """``itk.Image[itk.F, 3]``, looked up when the ITK backend runs: touching ITK's types at import would load its
    core modules (slow) in every process that imports this module, the torch backend's included."""
    return itk.Image[itk.F, 3]


def load_itk_modules() -> None:
    """Load ITK's lazily imported registration modules now (several seconds on first use), so that a timed
    registration measures the registration and a batch pays the cost once."""
    for name in (
        "ImageRegistrationMethodv4",
        "MattesMutualInformationImageToImageMetricv4",
        "ConjugateGradientLineSearchOptimizerv4Template",
        "RegistrationParameterScalesFromPhysicalShift",
        "VersorRigid3DTransform",
        "AffineTransform",
        "CenteredTransformInitializer",
        "MultiResolutionIterationEvent",
    ):
        getattr(itk, name)


def _run_stage(
    name: str,
    fixed: itk.Image,
    moving: itk.Image,
    transform: itk.Transform,
    iterations: tuple[int, ...],
    settings: AffineSettings,
    moving_initial: itk.Transform | None = None,
) -> StageReport:
    """Optimise ``transform`` in place with one multi-resolution ImageRegistrationMethodv4 run; ``moving_initial``:
    a fixed transform applied after it (module docstring)."""
    metric = itk.MattesMutualInformationImageToImageMetricv4[_image_type(), _image_type()].New()
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

    registration = itk.ImageRegistrationMethodv4[_image_type(), _image_type()].New()
    registration.SetFixedImage(fixed)
    registration.SetMovingImage(moving)
    registration.SetMetric(metric)
    registration.SetOptimizer(optimizer)
    registration.SetInitialTransform(transform)
    if moving_initial is not None:
        registration.SetMovingInitialTransform(moving_initial)
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


def align(
    fixed: Volume,
    moving: Volume,
    settings: AffineSettings | None = None,
    fixed_itk: itk.Image | None = None,
    samples: FixedSamples | None = None,
    initial: np.ndarray | None = None,
) -> AffineResult:
    """Rigid then affine registration of ``moving`` to ``fixed`` with the backend of ``settings`` (module
    docstring). Prepared once for a batch, or None: ``fixed_itk``, ``fixed`` converted for ITK (ITK backend);
    ``samples``, :func:`~monai_probreg.spatial.affine_torch.fixed_samples` of ``fixed`` and ``settings`` (torch).
    ``initial`` (4, 4), fixed LPS -> moving LPS: the transform both stages start from, or None (the initializer)."""
    settings = settings or AffineSettings()
    if settings.backend == "torch":
        return register_affine_torch(fixed, moving, settings, samples, initial)
    return register_affine(
        fixed_itk if fixed_itk is not None else volume_to_itk(fixed), volume_to_itk(moving), settings, initial
    )


def register_affine(
    fixed: itk.Image,
    moving: itk.Image,
    settings: AffineSettings | None = None,
    initial: np.ndarray | None = None,
) -> AffineResult:
    """The ITK backend: rigid then affine registration of ``moving`` to ``fixed`` (``itk.Image[itk.F, 3]`` with
    their geometry), started by the initializer or from ``initial`` (4, 4, fixed LPS -> moving LPS).

    Returns the fixed -> moving transform (module docstring). Deterministic for given inputs and settings.
    """
    settings = settings or AffineSettings.itk_defaults()
    rigid = itk.VersorRigid3DTransform[itk.D].New()
    initializer = itk.CenteredTransformInitializer[type(rigid), _image_type(), _image_type()].New(
        Transform=rigid, FixedImage=fixed, MovingImage=moving
    )
    if settings.initializer == "moments":
        initializer.MomentsOn()
    else:
        initializer.GeometryOn()
    initializer.InitializeTransform()
    moving_initial = None
    if initial is not None:
        # the initializer gave the fixed centre to rotate about; the shift between the centres is the initial
        # transform's business now (module docstring)
        rigid.SetTranslation([0.0, 0.0, 0.0])
        moving_initial = affine_to_itk(initial)
    start = affine_from_itk(rigid) if initial is None else np.asarray(initial, dtype=np.float64)
    stages = [_run_stage("rigid", fixed, moving, rigid, settings.rigid_iterations, settings, moving_initial)]
    result: itk.Transform = rigid
    if not settings.rigid_only:
        affine = itk.AffineTransform[itk.D, 3].New()
        affine.SetCenter(rigid.GetCenter())
        affine.SetMatrix(rigid.GetMatrix())
        affine.SetTranslation(rigid.GetTranslation())
        stages.append(_run_stage("affine", fixed, moving, affine, settings.affine_iterations, settings, moving_initial))
        result = affine
    center = np.asarray(result.GetCenter(), dtype=np.float64)
    if initial is None:
        return AffineResult(affine_from_itk(result), center, start, stages, result)
    # the composition as one matrix; its ITK form is built from it on first use (AffineResult.transform)
    return AffineResult(start @ affine_from_itk(result), center, start, stages)
