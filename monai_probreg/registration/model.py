"""The trained network as the MONAI bundle describes it: settings from a config, weights from a state_dict file.

Defaults follow the bundle layout: ``BUNDLE/configs/inference.yaml`` (its ``network_def`` and ``divisor``: the
values the weights were trained with; the weights file does not record them) and its ``model_file`` (a plain
``ProbRegNet`` state_dict, loaded with ``weights_only=True``), ``BUNDLE`` being the ``bundle/`` folder next to the
installed package (the repository checkout for an editable install) unless given.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from monai.bundle import ConfigParser
from torch import nn

import monai_probreg
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.spatial.contrast import check_contrast_match_bins
from monai_probreg.uncertainty.calibration import RAW, Calibration, calibration_record_for
from monai_probreg.uncertainty.quality import QualityModel, load_quality_model, quality_model_for
from monai_probreg.utils.errors import InputError, first_line
from monai_probreg.utils.provenance import file_sha256
from monai_probreg.weights.loading import load_weights

__all__ = ["default_bundle_root", "LoadedModel", "load_model"]


def default_bundle_root() -> Path:
    """``bundle/`` next to the installed package (the repository checkout for an editable install)."""
    return Path(monai_probreg.__file__).resolve().parents[1] / "bundle"


@dataclass
class LoadedModel:
    """``network`` in eval mode on ``device``; ``divisor``: the padding multiple of the bundle's preprocessing."""

    network: nn.Module
    divisor: int
    device: torch.device
    model_file: Path
    config_file: Path
    # the posterior calibration of these weights in use (monai_probreg.uncertainty.calibration; 1, 0 and Gaussian
    # intervals: the raw posterior), whole: the scale, the bias term and the intervals' Student-t dof
    calibration: Calibration = RAW
    refinement: RefinementSettings = field(default_factory=RefinementSettings)  # the config's ``refinement``
    weights_sha256: str = ""  # of model_file: which weights made a result (summary.json's reproducibility record)
    quality: QualityModel | None = None  # the weights' quality estimate (<weights stem>.quality.json), None without
    # the refinement settings the calibration was fitted around ({}: the network's mean); None: raw, or not recorded
    calibration_refinement: dict | None = None
    # the refinement's fields replaced for a pair of two contrasts (the config's ``other_contrast``; register
    # --contrast other): {} where the config has none
    other_contrast: dict = field(default_factory=dict)
    # --match-contrast: the moving image mapped onto the fixed image's contrast over this many bins (the config's
    # ``contrast_match_bins``; 0: not mapped, also where the config has none)
    contrast_match_bins: int = 0

    @property
    def std_scale(self) -> float:
        return self.calibration.std_scale

    @property
    def bias_fraction(self) -> float:
        return self.calibration.bias_fraction

    @property
    def interval_dof(self) -> float | None:
        return self.calibration.interval_dof


def load_model(
    bundle_root: str | os.PathLike | None = None,
    model_file: str | os.PathLike | None = None,
    config_file: str | os.PathLike | None = None,
    device: str = "cpu",
    calibrate: bool = True,
    quality: bool = True,
) -> LoadedModel:
    """The trained network: settings from ``configs/inference.yaml``'s ``network_def`` (and ``divisor``), weights
    from the config's ``model_file``, both under ``bundle_root`` unless given; InputError with one line if unusable.
    ``calibrate``: use the weights' calibration sidecar (``<weights stem>.calibration.json``); False = raw. The quality
    estimate (``<weights stem>.quality.json``) computes its entropy feature with the calibration of its own fit, which
    its sidecar records, so it works with the raw posterior too; an older sidecar that does not record it was fitted
    on the calibrated posterior, and is used only with it. ``quality=False`` leaves it out
    (:mod:`monai_probreg.fitting` while it fits a new one)."""
    root = Path(bundle_root) if bundle_root is not None else default_bundle_root()
    config = Path(config_file) if config_file is not None else root / "configs" / "inference.yaml"
    if not config.is_file():
        raise InputError(
            f"--config {str(config)!r}: no such file (the bundle's configs/inference.yaml; pass "
            "--bundle-root or --config)"
        )
    parser = ConfigParser()
    parser.read_config(str(config))
    parser["bundle_root"] = str(root)
    if model_file is None:  # the config's own default weights (models/<the shipped default>), relative to the bundle
        model_file = parser.get_parsed_content("model_file") if "model_file" in parser else root / "models" / "model.pt"
    weights = Path(model_file)
    if not weights.is_file():
        raise InputError(f"--model-file {str(weights)!r}: no such file (train the bundle, or pass --model-file)")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"--device {device}: CUDA is not available on this machine; use --device cpu")
    try:
        network = parser.get_parsed_content("network_def")
        divisor = int(parser.get("divisor", 16))
    except Exception as err:  # noqa: BLE001 - any config error becomes one line
        raise InputError(
            f"--config {str(config)!r}: cannot build the network from 'network_def' ({first_line(err)})"
        ) from None
    try:
        refinement = parser.get_parsed_content("refinement") if "refinement" in parser else RefinementSettings()
    except Exception as err:  # noqa: BLE001 - any config error becomes one line
        raise InputError(f"--config {str(config)!r}: bad 'refinement' settings ({first_line(err)})") from None
    other_contrast = _other_contrast(parser, refinement, config)
    contrast_match_bins = _contrast_match_bins(parser, config)
    try:
        load_weights(network, weights, device)
    except InputError as err:  # untrusted (a pickle that could run code), truncated or corrupt: its own message
        raise type(err)(str(err).replace("model file", "--model-file", 1)) from None
    except (RuntimeError, KeyError, ValueError) as err:
        raise InputError(
            f"--model-file {str(weights)!r}: does not fit the network of {str(config)!r} ({first_line(err)})"
        ) from None
    try:
        record = calibration_record_for(weights, calibrate)  # the sidecar read and checked once
        quality_model = quality_model_for(load_quality_model(weights), calibrate) if quality else None
    except ValueError as err:  # a sidecar of other weights, or corrupt
        raise InputError(f"--model-file {str(weights)!r}: {err}") from None
    return LoadedModel(
        network,
        divisor,
        torch.device(device),
        weights,
        config,
        RAW if record is None else record.calibration(),
        refinement=refinement,
        weights_sha256=file_sha256(weights),
        quality=quality_model,
        calibration_refinement=None if record is None else record.refinement,
        other_contrast=other_contrast,
        contrast_match_bins=contrast_match_bins,
    )


def _other_contrast(parser, refinement: RefinementSettings, config: Path) -> dict:
    """The config's ``other_contrast`` (RefinementSettings fields by name), checked against ``refinement``: {} when
    the config has none; one line naming the config and the bad field otherwise."""
    if "other_contrast" not in parser:
        return {}
    try:
        fields = dict(parser.get_parsed_content("other_contrast"))
        refinement.with_fields(**fields)
    except Exception as err:  # noqa: BLE001 - any config error becomes one line
        raise InputError(f"--config {str(config)!r}: bad 'other_contrast' settings ({first_line(err)})") from None
    return fields


def _contrast_match_bins(parser, config: Path) -> int:
    """The config's ``contrast_match_bins``: 0 when the config has none; one line naming the config otherwise unless
    it is 0 or an integer >= 2."""
    value = parser.get_parsed_content("contrast_match_bins") if "contrast_match_bins" in parser else 0
    try:
        return check_contrast_match_bins(value)
    except ValueError:
        raise InputError(
            f"--config {str(config)!r}: bad 'contrast_match_bins': expected 0 (none) or an integer >= 2, got {value!r}"
        ) from None
