"""A per-registration quality estimate: a predicted Dice and a probability that the registration failed.

Two small models on the label-free features of :mod:`monai_probreg.uncertainty.quality_features`, clipped to the
range the fit saw (a linear model must not extrapolate: a registration better aligned before the deformable step than
any training pair, e.g. after the command line's full affine, is predicted as the best of them, not beyond) and
standardised with the training set's mean and spread:

- predicted Dice: ridge regression of the actual mean Dice (on the fit's data set's scale: a ranking elsewhere), fitted
  on the pairs with something to register and clipped to their range (``dice_low``, ``dice_high``): a scan onto
  (a near copy of) itself is predicted as the best of them;
- failure probability: L2-regularised logistic regression of "failed", where a registration *failed* when its Dice
  is below the Dice before the deformable step (the affine alone) or below no registration + ``FAILURE_MARGIN``,
  and not within that margin of a perfect overlap (the definition the detector is scored on: :func:`failed`).

Whose features: the *network's* registration, before any test-time refinement (the "witness"). Refinement
(:mod:`monai_probreg.engines.refinement`) maximises the pair's local NCC, so the refined registration looks alike
even when the input was wrong (a scan whose orientation header was turned by 180 degrees), and a fit on refined
registrations' features does not see those failures. The network's own registration, which the refinement starts
from and is pulled towards, still shows the failure; so the models read its features, and are fitted on the outcome
(Dice, failed) of the registration the user gets (the refined one, for the shipped default).

A registration gets a warning when its failure probability is at least the model's ``threshold``, or when the
deformable step the user gets lowered the local similarity of the pair by more than ``lncc_drop_margin``
(``lncc_after < lncc_before - margin`` of the *answer*'s features: the registration moved the images apart, which no
optimiser of its own loss would do). The margin keeps a registration that changes almost nothing (a scan onto a near
copy of itself) from warning or not by the rounding of the UNet's arithmetic (bf16 on CPUs with native bf16, fp32
elsewhere). That rule is not fitted. The failure model has seen such pairs (scans onto themselves and onto near
copies): NCC 1 is inside its range, a pair cannot be more alike, so two such pairs are not clipped to one point and
their probabilities differ (the link has no floor either: :func:`logistic`).

Both models are fitted by ``python -m monai_probreg.fitting`` (:mod:`monai_probreg.fitting.quality_fit`) on *training*
subjects only (normal pairs, a failure set: wrong orientations, cropped field of view, a missing block, heavy noise and
bias, inverted contrast, and pairs with almost nothing to register: a scan onto itself and onto a near copy,
:mod:`monai_probreg.fitting.self_cases`), through both paths that compute the features (the bundle's, on the dataset
grid, and the whole command's, affine stage and model grid included, with headers as they are and turned, and moved onto
the scan itself), and stored next to the weights as ``<weights stem>.quality.json`` with the weights' SHA-256, like the
calibration. The entropy feature is a calibrated one, and the sidecar keeps the calibration it was computed with at the
fit (``entropy_calibration``): every estimate computes it with that one, so a refitted posterior calibration (what the
uncertainty maps show) leaves the estimate as it was validated; an older sidecar without it reads the calibration in
use, and is not used under the raw posterior (:func:`quality_model_for`). The fit
(:func:`~monai_probreg.fitting.quality_fit.fit_quality_model`) is written by hand: ten lines of closed-form ridge and
Newton's method, where scikit-learn would be a dependency for two linear models. How well it predicts and warns, on
validation subjects: ``benchmarks/failure_detection.py``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from monai_probreg.uncertainty.calibration import Calibration, check_calibration
from monai_probreg.uncertainty.quality_features import QualityFeatures
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.utils.sidecars import read_sidecar, sidecar_path, write_sidecar

__all__ = [
    "ENTROPY_CALIBRATION_KEYS",
    "FAILURE_MARGIN",
    "LNCC_DROP_MARGIN",
    "PERFECT_DICE",
    "QualityEstimate",
    "QualityModel",
    "entropy_calibration_record",
    "failed",
    "load_quality_model",
    "logistic",
    "quality_path",
    "quality_record",
    "save_quality_model",
]

QUALITY_SIDECAR = "quality"  # models/model.pt -> models/model.quality.json (utils.sidecars)

# the posterior's numbers the entropy feature depends on (the intervals' dof does not enter an entropy)
ENTROPY_CALIBRATION_KEYS: tuple[str, ...] = ("std_scale", "bias_fraction")
FAILURE_MARGIN = 0.05  # Dice below no registration + this counts as a failure (the definition)
PERFECT_DICE = 1.0  # a label map against itself: a Dice within FAILURE_MARGIN of it has nothing left to gain
DEFAULT_THRESHOLD = 0.5  # failure probability from which a registration is flagged
LNCC_DROP_MARGIN = 0.002  # local-NCC drop beyond which the deformable step "made the images less alike" (module
# docstring): above what bf16 moves, below the failure set's drops (experiments/lncc_margin.py measures both)


def failed(dice: float, dice_before: float, dice_identity: float, margin: float = FAILURE_MARGIN) -> bool:
    """The failure definition: Dice below the affine-only Dice or below no registration + ``margin``, unless within
    ``margin`` of :data:`PERFECT_DICE` (a scan onto a near copy of itself: no registration is already there)."""
    return bool(dice < min(max(dice_before, dice_identity + margin), PERFECT_DICE - margin))


class QualityEstimate(NamedTuple):
    """The estimate of one registration: predicted mean Dice, probability of failure, and the warning (None = no)."""

    predicted_dice: float
    failure_probability: float
    warning: str | None


def quality_record(features: QualityFeatures, estimate: QualityEstimate, answer: QualityFeatures | None = None) -> dict:
    """The estimate and its features as strict JSON (NaN -> null): what ``summary.json``, ``quality.json`` and
    ``scores.json`` store, on the command line and in the bundle alike. ``features``: the network's registration
    (what the models read); ``answer``: the refined registration's, when it differs (``answer_features``, else null)."""

    def finite(v: float) -> float | None:
        return None if math.isnan(v) else float(v)

    return {
        "predicted_dice": finite(estimate.predicted_dice),
        "failure_probability": estimate.failure_probability,
        "warning": estimate.warning,
        "features": {k: finite(v) for k, v in features._asdict().items()},
        "answer_features": None if answer is None else {k: finite(v) for k, v in answer._asdict().items()},
    }


def logistic(x: np.ndarray) -> np.ndarray:
    """The failure model's link, exp(-log(1 + exp(-x))): no overflow, and no clip of ``x`` (a clip would give every
    logit beyond it one probability: pairs far on the good side, a scan onto a near copy of itself, would tie)."""
    return np.exp(-np.logaddexp(0.0, -x))


@dataclass
class QualityModel:
    """Standardisation and the two linear models; :meth:`estimate` applies them to :class:`QualityFeatures`."""

    feature_names: list[str]
    low: list[float]  # per feature: the training range, features are clipped to it
    high: list[float]
    mean: list[float]
    scale: list[float]
    dice_coef: list[float]
    dice_intercept: float
    failure_coef: list[float]
    failure_intercept: float
    threshold: float = DEFAULT_THRESHOLD
    lncc_drop_margin: float = LNCC_DROP_MARGIN
    dice_range: list[float] = field(default_factory=lambda: [0.0, 1.0])  # the fit's Dice range: predictions stay in it
    # per feature: the range of the Dice regression's own registrations (those with something to register: not a scan
    # onto itself), where its input is clipped; [] (older sidecars): low and high
    dice_low: list[float] = field(default_factory=list)
    dice_high: list[float] = field(default_factory=list)
    weights_file: str = ""
    weights_sha256: str = ""
    fitted_on: list[str] = field(default_factory=list)
    refinement: dict = field(default_factory=dict)  # the fit's outcomes: RefinementSettings.as_dict() ({}: network)
    # the posterior calibration {"std_scale", "bias_fraction"} of the fit's entropy feature ({}: the one in use)
    entropy_calibration: dict = field(default_factory=dict)
    definition: str = (
        f"failed = Dice < Dice before the deformable step, or Dice < no registration + {FAILURE_MARGIN}; never when "
        f"Dice >= {PERFECT_DICE} - {FAILURE_MARGIN}"
    )

    def __post_init__(self) -> None:
        n = len(self.feature_names)
        if list(self.feature_names) != list(QualityFeatures._fields):
            raise ValueError(f"feature_names must be {list(QualityFeatures._fields)}; got {self.feature_names}")
        for name in ("low", "high", "mean", "scale", "dice_coef", "failure_coef"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have {n} values (one per feature); got {len(getattr(self, name))}")
        if any(not s > 0 for s in self.scale):
            raise ValueError(f"scale must be positive; got {self.scale}")
        if any(not lo <= hi for lo, hi in zip(self.low, self.high)):
            raise ValueError(f"low must be <= high per feature; got {self.low} and {self.high}")
        dice_low, dice_high = self.dice_low, self.dice_high
        if (dice_low or dice_high) and not (
            len(dice_low) == len(dice_high) == n and all(lo <= hi for lo, hi in zip(dice_low, dice_high))
        ):
            raise ValueError(
                f"dice_low and dice_high must be [] or {n} values, low <= high; got {dice_low}, {dice_high}"
            )
        if len(self.dice_range) != 2 or not 0.0 <= self.dice_range[0] <= self.dice_range[1] <= 1.0:
            raise ValueError(f"dice_range must be [low, high] within [0, 1]; got {self.dice_range}")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold must be in (0, 1); got {self.threshold}")
        if not 0.0 <= self.lncc_drop_margin < 1.0:
            raise ValueError(f"lncc_drop_margin must be in [0, 1); got {self.lncc_drop_margin}")
        if self.entropy_calibration:
            if set(self.entropy_calibration) != set(ENTROPY_CALIBRATION_KEYS):
                raise ValueError(
                    f"entropy_calibration must be {{}} or have the keys {list(ENTROPY_CALIBRATION_KEYS)}; got "
                    f"{sorted(self.entropy_calibration)}"
                )
            check_calibration(**self.entropy_calibration)

    def feature_calibration(self, std_scale: float, bias_fraction: float) -> Calibration:
        """The calibration the entropy feature is computed with: the fit's, or (a sidecar that does not record it)
        the one in use, ``std_scale`` and ``bias_fraction``."""
        if self.entropy_calibration:
            return Calibration(**{k: float(v) for k, v in self.entropy_calibration.items()})
        return Calibration(float(std_scale), float(bias_fraction))

    def _standardise(self, features: Sequence[QualityFeatures], low: list[float], high: list[float]) -> np.ndarray:
        x = np.asarray([list(f) for f in features], dtype=np.float64).reshape(len(features), len(self.mean))
        return (np.clip(x, np.asarray(low), np.asarray(high)) - np.asarray(self.mean)) / np.asarray(self.scale)

    def predict(self, features: Sequence[QualityFeatures]) -> tuple[np.ndarray, np.ndarray]:
        """Predicted Dice and failure probability of each registration (arrays of len(features))."""
        z = self._standardise(features, self.dice_low or self.low, self.dice_high or self.high)
        dice = np.clip(z @ np.asarray(self.dice_coef) + self.dice_intercept, *self.dice_range)
        z = self._standardise(features, self.low, self.high)
        probability = logistic(z @ np.asarray(self.failure_coef) + self.failure_intercept)
        return dice, probability

    def estimate(self, features: QualityFeatures, answer: QualityFeatures | None = None) -> QualityEstimate:
        """The estimate of one registration, with a one-line warning when it probably failed. ``features``: of the
        network's registration (the models' input); ``answer``: of the registration the user gets when it differs
        (refined), read by the local-NCC drop rule (None: ``features``)."""
        answer = features if answer is None else answer
        if not all(math.isfinite(v) for v in (*features, *answer)):
            return QualityEstimate(
                math.nan,
                1.0,
                "the registration's quality features are not finite "
                "(an empty or constant image?): do not trust this registration",
            )
        dice, probability = (float(a[0]) for a in self.predict([features]))
        warning = None
        if probability >= self.threshold:
            warning = (
                f"this registration probably failed (estimated probability {probability:.2f}, predicted Dice "
                f"{dice:.2f}): check the QC figure, the input's orientation header, field of view and contrast"
            )
        elif answer.lncc_after < answer.lncc_before - self.lncc_drop_margin:
            warning = (
                f"the deformable step made the images less alike (local NCC {answer.lncc_before:.3f} -> "
                f"{answer.lncc_after:.3f}): it probably did worse than the affine alone (affine.tfm); check "
                "the QC figure"
            )
        return QualityEstimate(dice, probability, warning)


def entropy_calibration_record(calibration: Calibration) -> dict[str, float]:
    """What a quality sidecar and failure_detection's records store of ``calibration``: the numbers an entropy depends
    on (:data:`ENTROPY_CALIBRATION_KEYS`; the intervals' dof does not enter it)."""
    return {k: float(getattr(calibration, k)) for k in ENTROPY_CALIBRATION_KEYS}


def quality_model_for(model: QualityModel | None, calibrate: bool) -> QualityModel | None:
    """``model`` where it can be used with the posterior in use (``calibrate``: the weights' calibration; False: the raw
    posterior), else None: a model that does not record its entropy's calibration reads the calibration in use, and
    it was fitted on a calibrated one."""
    if model is not None and not calibrate and not model.entropy_calibration:
        return None
    return model


def quality_path(weights_file: str | os.PathLike) -> Path:
    """``models/model.pt`` -> ``models/model.quality.json``."""
    return sidecar_path(weights_file, QUALITY_SIDECAR)


def save_quality_model(
    model: QualityModel, weights_file: str | os.PathLike, path: str | os.PathLike | None = None
) -> Path:
    """Write ``model`` as the sidecar of ``weights_file`` (atomically), stamped with the weights' SHA-256; ``path``:
    where (default: next to the weights, :func:`quality_path`)."""
    model.weights_file, model.weights_sha256 = Path(weights_file).name, file_sha256(weights_file)
    return write_sidecar(weights_file, QUALITY_SIDECAR, asdict(model), path)


def load_quality_model(weights_file: str | os.PathLike) -> QualityModel | None:
    """The sidecar of ``weights_file``, or None when it has none; refuses one fitted for other weights."""
    path = quality_path(weights_file)
    if not path.is_file():
        return None
    data = read_sidecar(weights_file, QUALITY_SIDECAR, "quality model")
    try:
        return QualityModel(**data)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: not a quality model ({err})") from None
