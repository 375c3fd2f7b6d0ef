"""What one registration is asked to do: :class:`RegistrationOptions` (samples, seed, which outputs, the affine
stage's settings, the refinement) and an earlier registration's affine to start from or to use
(:class:`InitialTransform`, ``--initial-transform``)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.spatial.affine import AffineSettings
from monai_probreg.spatial.contrast import check_contrast_match_bins
from monai_probreg.spatial.transform_files import read_initial_transform
from monai_probreg.utils.errors import InputError

__all__ = ["CONTRASTS", "INITIAL_TRANSFORM_USES", "InitialTransform", "RegistrationOptions"]

# --contrast: "same", both scans of one contrast; "other", two contrasts (the refinement's image term set for them, and
# no quality estimate: its models were fitted on pairs of one contrast, where another contrast is a failure)
CONTRASTS = ("same", "other")

INITIAL_TRANSFORM_USES = ("start", "as-affine")  # the affine stage starts from it / it is the affine (no stage)


@dataclass(frozen=True, eq=False)
class InitialTransform:
    """An earlier registration's affine (``--initial-transform``, ANTs' ``--initial-moving-transform``): ``matrix``
    (4, 4), fixed LPS -> moving LPS, ITK's and ANTs' convention, as ``affine.tfm``; ``center``: its file's centre
    (LPS mm; kept so that ``as-affine`` writes the file's own parameters back); ``use``: ``"start"``, the affine
    stage starts from it (:func:`~monai_probreg.spatial.affine.align`'s ``initial``), or ``"as-affine"``, it is the
    affine and no stage runs. Compared by identity (it holds arrays)."""

    path: str
    matrix: np.ndarray
    center: np.ndarray
    use: str = INITIAL_TRANSFORM_USES[0]

    def __post_init__(self) -> None:
        if self.use not in INITIAL_TRANSFORM_USES:
            raise ValueError(f"use: expected one of {INITIAL_TRANSFORM_USES}, got {self.use!r}")

    @classmethod
    def read(
        cls, path: str | os.PathLike, use: str = INITIAL_TRANSFORM_USES[0], role: str = "--initial-transform"
    ) -> InitialTransform:
        """The transform of an ITK (``.tfm``, ``.txt``) or ANTs (``.mat``) affine file; InputError (one line) for a
        missing, unreadable, non-affine, not 3-D or singular one
        (:func:`~monai_probreg.spatial.transform_files.read_initial_transform`)."""
        affine = read_initial_transform(path, role)
        return cls(str(path), affine.matrix, affine.center, use)

    def summary(self) -> dict:
        return {
            "path": str(Path(self.path).resolve()),
            "use": self.use,
            "matrix_fixed_to_moving_lps": np.round(self.matrix, 6).tolist(),
        }


@dataclass(frozen=True)
class RegistrationOptions:
    """``samples``: the std map with K >= 2 (0 = none; first order, :mod:`monai_probreg.uncertainty.spread`: the same
    map for every K); ``seed``: the RNG seed of posterior samples (the command line gives the same seed to
    ``affine.seed``);
    ``affine``: settings of the ITK pre-alignment, or None to skip it (the identity: scans already aligned to the
    fixed image, as the paper assumes); ``refinement``: test-time refinement of the posterior mean, or None for the
    model's own (its config's ``refinement``: the default path, as ``monai-probreg register`` runs it);
    ``inverse``: compute and write the inverse field and the fixed labels in moving space; ``maps``: write the
    Jacobian, entropy and std maps (their statistics stay in the summary either way); ``initial``: an earlier
    registration's affine that the affine stage starts from (``use="start"``, with ``affine`` settings) or that is
    the affine (``use="as-affine"``, with ``affine=None``), or None; ``contrast_match_bins``: 0, the moving scan as it
    is; N >= 2, its intensities mapped onto the fixed image's contrast over N bins before the network, the refinement
    and the quality estimate read it (:func:`~monai_probreg.spatial.contrast.match_contrast`; ``--match-contrast``);
    ``contrast``: one of :data:`CONTRASTS` (``--contrast``; the refinement's settings for it are the caller's): under
    "other" no quality estimate is made (:func:`~monai_probreg.registration.quality_estimate.why_no_quality`);
    ``error_features``: hand the pair's error-model features (:func:`~monai_probreg.uncertainty.error_model.
    error_features`) to a caller's check (:class:`~.scan.Registered`), for fitting the error model.
    """

    samples: int = 0
    seed: int = 0
    qc: bool = True
    inverse: bool = True
    maps: bool = True
    affine: AffineSettings | None = field(default_factory=AffineSettings)
    refinement: RefinementSettings | None = None
    initial: InitialTransform | None = None
    contrast_match_bins: int = 0
    contrast: str = "same"
    error_features: bool = False

    def __post_init__(self) -> None:
        check_contrast_match_bins(self.contrast_match_bins)
        if self.contrast not in CONTRASTS:
            raise ValueError(f"contrast must be one of {CONTRASTS}; got {self.contrast!r}")
        if self.samples == 1 or self.samples < 0:
            raise InputError(
                f"--samples must be 0 (no sampling) or >= 2 (a standard deviation needs two); got {self.samples}"
            )
        if self.initial is not None and (self.initial.use == "start") != (self.affine is not None):
            # settings recorded for a stage that does not run, or a start for a stage that is not there
            raise ValueError(
                f"initial transform used as {self.initial.use!r}: expected affine settings "
                f"{'for the stage it starts' if self.initial.use == 'start' else 'None (no stage runs)'}, got "
                f"{self.affine}"
            )
