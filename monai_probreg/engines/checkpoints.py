"""Crash-safe checkpoints and resume, on ignite's public ``Checkpoint`` API only.

- :class:`AtomicCheckpointSaver` takes the arguments of MONAI's ``CheckpointSaver`` that the bundle uses (best key
  metric to a fixed file name, and/or a training state every ``save_interval`` epochs) and writes every file through
  :func:`~monai_probreg.utils.files.atomic_write`: a hidden temporary renamed onto its name once complete. The file a
  new checkpoint replaces (``n_saved``) is deleted only after that. MONAI's saver writes in place and ignite deletes
  the old checkpoint *before* writing the new one, so a kill mid-write there lost the training state. The file names
  are MONAI's: ``<prefix>_checkpoint_epoch=<n>.pt``, or the fixed ``key_metric_filename``.
- :func:`attach_resume` removes the temporaries a kill left and resumes from the newest checkpoint that loads
  (``weights_only=True``; one that would run code is refused, never skipped past).
- :func:`key_metric_tracker` exposes the best-score bookkeeping for the training state, so "best" stays best across
  restarts.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from ignite.engine import Engine, Events
from ignite.handlers import Checkpoint
from ignite.handlers.checkpoint import BaseSaveHandler
from monai.handlers import CheckpointLoader

from monai_probreg.utils.errors import InputError, UntrustedFileError
from monai_probreg.utils.files import atomic_write, remove_partial_files
from monai_probreg.weights.loading import safe_torch_load

__all__ = ["AtomicDiskSaver", "AtomicCheckpointSaver", "latest_checkpoint", "attach_resume", "key_metric_tracker"]

_LOG = logging.getLogger("monai_probreg.train")


class AtomicDiskSaver(BaseSaveHandler):
    """An ignite save handler: ``torch.save`` through :func:`atomic_write` into ``dirname``, under ignite's name or
    the fixed ``filename``. ignite calls :meth:`remove` for the checkpoint being replaced before it saves the new one;
    the removal is deferred until the new file is complete (and skipped when it is the same file)."""

    def __init__(self, dirname: str | os.PathLike, filename: str | None = None) -> None:
        self.dirname, self.filename = Path(dirname), filename
        self._pending: list[str] = []

    def __call__(self, checkpoint: Mapping, filename: str, metadata: Mapping | None = None) -> None:
        name = self.filename or filename
        atomic_write(self.dirname / name, lambda tmp: torch.save(checkpoint, tmp))
        while self._pending:
            old = self._pending.pop(0)
            if old != name:
                (self.dirname / old).unlink(missing_ok=True)

    def remove(self, filename: str) -> None:
        self._pending.append(self.filename or filename)


class AtomicCheckpointSaver:
    """Crash-safe checkpoints of ``save_dict`` into ``save_dir`` (see the module docstring); attach to an engine.

    Args:
        save_dir: folder of the files (created when the first one is written).
        save_dict: name -> object with ``state_dict``; a single object is saved as its bare state dict (ignite).
        file_prefix: prefix of the generated file names.
        save_key_metric: keep the best ``engine.state.metrics[key_metric_name]`` (checked at every epoch end).
        key_metric_name: the metric (default: the engine's key metric).
        key_metric_n_saved: how many best files to keep (1 with a fixed ``key_metric_filename``).
        key_metric_filename: fixed file name of the best checkpoint (e.g. ``model.pt``).
        key_metric_greater_or_equal: an equal score replaces the best (default: only a strictly greater one).
        epoch_level: count ``save_interval`` in epochs (else iterations).
        save_interval: save every that many epochs/iterations (0: never).
        n_saved: interval checkpoints kept (None: all).
    """

    def __init__(
        self,
        save_dir: str | os.PathLike,
        save_dict: Mapping[str, Any],
        file_prefix: str = "",
        save_key_metric: bool = False,
        key_metric_name: str | None = None,
        key_metric_n_saved: int = 1,
        key_metric_filename: str | None = None,
        key_metric_greater_or_equal: bool = False,
        epoch_level: bool = True,
        save_interval: int = 0,
        n_saved: int | None = None,
    ) -> None:
        if not save_dict:
            raise ValueError(f"save_dict must name at least one object to save; got {save_dict!r}")
        if key_metric_filename is not None and key_metric_n_saved != 1:
            raise ValueError(
                f"a fixed key_metric_filename keeps one file: expected key_metric_n_saved=1, got {key_metric_n_saved}"
            )
        if save_interval < 0:
            raise ValueError(f"save_interval must be >= 0; got {save_interval}")
        self.save_dir, self.key_metric_name = Path(save_dir), key_metric_name
        self.epoch_level, self.save_interval = epoch_level, save_interval
        self.key_metric_checkpoint: Checkpoint | None = None
        self.interval_checkpoint: Checkpoint | None = None
        if save_key_metric:
            self.key_metric_checkpoint = Checkpoint(
                dict(save_dict),
                AtomicDiskSaver(save_dir, key_metric_filename),
                filename_prefix=file_prefix,
                score_function=self._key_metric,
                score_name="key_metric",
                n_saved=key_metric_n_saved,
                greater_or_equal=key_metric_greater_or_equal,
            )
        if save_interval > 0:
            self.interval_checkpoint = Checkpoint(
                dict(save_dict),
                AtomicDiskSaver(save_dir),
                filename_prefix=file_prefix,
                score_function=self._step,
                score_name="epoch" if epoch_level else "iteration",
                n_saved=n_saved,
            )

    def _key_metric(self, engine: Engine) -> float:
        name = self.key_metric_name or getattr(engine.state, "key_metric_name", None)
        if name is None or name not in engine.state.metrics:
            raise KeyError(f"key metric {name!r} not in the engine's metrics {sorted(engine.state.metrics)}")
        return float(engine.state.metrics[name])

    def _step(self, engine: Engine) -> int:
        return engine.state.epoch if self.epoch_level else engine.state.iteration

    def attach(self, engine: Engine) -> None:
        if self.key_metric_checkpoint is not None:
            engine.add_event_handler(Events.EPOCH_COMPLETED, self.key_metric_checkpoint)
        if self.interval_checkpoint is not None:
            event = Events.EPOCH_COMPLETED if self.epoch_level else Events.ITERATION_COMPLETED
            engine.add_event_handler(event(every=self.save_interval), self._save_interval)

    def _save_interval(self, engine: Engine) -> None:
        self.interval_checkpoint(engine)
        _LOG.info(f"saved checkpoint {self.interval_checkpoint.last_checkpoint}")


def latest_checkpoint(ckpt_dir: str | os.PathLike, prefix: str = "train_state") -> str | None:
    """Newest ``<prefix>*.pt`` in ``ckpt_dir`` (by modification time) that loads, or None (start from scratch).

    A truncated or corrupt file is skipped with a warning (the next newest is tried); one that
    ``torch.load(weights_only=True)`` refuses raises :class:`~monai_probreg.utils.errors.UntrustedFileError`: a file
    that would run code is never skipped past silently.
    """
    folder = Path(ckpt_dir)
    if not folder.is_dir():
        return None
    found = sorted(folder.glob(f"{prefix}*.pt"), key=lambda p: p.stat().st_mtime_ns)
    for path in reversed(found):
        try:
            safe_torch_load(path, "training checkpoint")
        except UntrustedFileError:
            raise
        except InputError as err:
            _LOG.warning(f"skipping {err}")
            continue
        return str(path)
    return None


def attach_resume(
    engine: Engine,
    ckpt_dir: str | os.PathLike,
    load_dict: dict,
    prefix: str = "train_state",
    map_location: str | torch.device | None = None,
) -> str | None:
    """Attach MONAI's ``CheckpointLoader`` (``weights_only=True``) for the newest usable training state, if any,
    after removing the temporaries of interrupted writes (:func:`~monai_probreg.utils.files.remove_partial_files`).

    Returns the checkpoint path that will be loaded when the engine starts, or None (fresh start).
    """
    remove_partial_files(ckpt_dir)
    path = latest_checkpoint(ckpt_dir, prefix)
    if path is not None:
        CheckpointLoader(load_path=path, load_dict=load_dict, map_location=map_location).attach(engine)
        _LOG.info(f"resuming from {path}")
    return path


class _NoTracker:
    """Stand-in with an empty state when there is no best-metric saver (e.g. a DDP rank without validation)."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state_dict: dict) -> None:
        return None


def key_metric_tracker(saver: AtomicCheckpointSaver | None) -> Any:
    """The best-score bookkeeping (ignite ``Checkpoint``: scores and file names only) of a saver with
    ``save_key_metric=True``, to save and restore in the training state: without it, the first validation after a
    resume would count as a new best and overwrite ``model.pt`` even when worse. A missing saver (a disabled handler)
    or one without a key metric gives an empty stand-in."""
    tracker = getattr(saver, "key_metric_checkpoint", None)
    return tracker if tracker is not None else _NoTracker()
