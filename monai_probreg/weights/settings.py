"""The network settings a weights file was trained with, in a JSON file next to it, checked when it is loaded.

A ``state_dict`` holds tensors only. Channel counts show in their shapes (a mismatch fails ``load_state_dict``),
but ``network_size``, ``num_steps`` and ``bidirectional`` leave no trace in them: weights trained on an 80x96x80
grid load without complaint into a network built for 160x192x160 and then register worse, silently. So training
writes ``<weights stem>.network.json`` beside the best weights (:class:`NetworkSettingsWriter`, after each
validation that saved them), and :func:`check_network_settings` (called by
:func:`monai_probreg.weights.loading.load_weights`) refuses a network whose settings differ, naming each setting, the
trained value and the configured one. A weights file without the JSON (trained elsewhere) loads as before.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ignite.engine import Engine, Events
from torch import nn

from monai_probreg.utils.errors import InputError

__all__ = [
    "SETTING_NAMES",
    "NetworkSettingsWriter",
    "check_network_settings",
    "network_settings",
    "settings_path",
    "write_network_settings",
]

# ProbRegNet arguments that change what the weights compute (the speed levers and padding do not)
SETTING_NAMES = (
    "spatial_dims",
    "enc_channels",
    "dec_channels",
    "int_downsize",
    "num_steps",
    "bidirectional",
    "network_size",
)
_SUFFIX = ".network.json"


def settings_path(model_file: str | os.PathLike) -> Path:
    """``models/model.pt`` -> ``models/model.network.json``."""
    path = Path(model_file)
    return path.with_name(path.stem + _SUFFIX)


def network_settings(network: nn.Module) -> dict[str, Any]:
    """The :data:`SETTING_NAMES` of a :class:`~monai_probreg.ProbRegNet` as JSON values (tuples as lists)."""
    values = {
        "spatial_dims": network.spatial_dims,
        "enc_channels": network.enc_channels,
        "dec_channels": network.dec_channels,
        "int_downsize": network.unet.int_downsize,
        "num_steps": network.integrate.num_steps,
        "bidirectional": network.bidirectional,
        "network_size": network.network_size,
    }
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in values.items()}


def _settings_text(network: nn.Module) -> str:
    return json.dumps(network_settings(network), indent=2) + "\n"


def write_network_settings(model_file: str | os.PathLike, network: nn.Module, text: str | None = None) -> Path:
    """Write :func:`network_settings` of ``network`` (or its already serialised ``text``) next to ``model_file``,
    atomically; returns the JSON's path."""
    from monai_probreg.utils.files import (
        write_text,  # late: inference imports this module
    )

    return write_text(settings_path(model_file), text if text is not None else _settings_text(network))


def check_network_settings(model_file: str | os.PathLike, network: nn.Module) -> dict[str, Any] | None:
    """Compare ``network`` with the settings recorded next to ``model_file``.

    Returns the recorded settings, or None when there is no JSON (nothing to check).

    Raises:
        InputError: a recorded setting differs from the network's (all differences in one message), or the JSON
            cannot be read.
    """
    path = settings_path(model_file)
    if not path.is_file() or not hasattr(network, "integrate"):
        return None
    try:
        recorded = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(
            f"{str(path)!r} (the network settings of {Path(model_file).name}) cannot be read: {err}"
        ) from None
    if not isinstance(recorded, dict):
        raise InputError(f"{str(path)!r} must hold a JSON object of network settings; got {type(recorded).__name__}")
    actual = network_settings(network)
    wrong = [
        f"{name}: trained with {recorded[name]!r}, the network has {actual[name]!r}"
        for name in SETTING_NAMES
        if name in recorded and recorded[name] != actual[name]
    ]
    if wrong:
        raise InputError(
            f"{str(model_file)!r} does not fit this network ({path.name}): "
            + "; ".join(wrong)
            + ". Set the trained values in the config (e.g. --network_size ...) or use other weights"
        )
    return recorded


class NetworkSettingsWriter:
    """Ignite handler for the validator: after each run, if ``model_file`` exists (the best weights were saved),
    writes the network's settings next to it. Attach it after the checkpoint saver (later in ``val_handlers``)."""

    def __init__(self, model_file: str | os.PathLike, network: nn.Module) -> None:
        self.model_file = Path(model_file)
        self.network = network

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.COMPLETED, self)

    def __call__(self, engine: Engine | None = None) -> None:
        if not self.model_file.is_file():
            return
        path = settings_path(self.model_file)
        text = _settings_text(self.network)
        if not path.is_file() or path.read_text() != text:
            write_network_settings(self.model_file, self.network, text)
