"""Glue between the registration model and MONAI/ignite engines (``SupervisedTrainer``/``SupervisedEvaluator``).

- :func:`prepare_registration_batch` turns a batch dict into ``(moving, targets, (fixed,), {})`` so the engine
  calls ``network(moving, fixed)``; ``targets`` is the batch dict (images and, if present, labels).
- :class:`RegistrationLoss` adapts :class:`~monai_probreg.losses.elbo.ProbRegLoss` to the engine's
  ``loss_function(pred, targets)`` and keeps the last terms for logging.
- :class:`RegistrationMetrics` is an ignite metric: mean Dice of the moving labels warped (nearest neighbour)
  onto the fixed labels at the labels' resolution, and the |J| <= 0 count of the displacement there.
- Crash safety: :class:`AtomicCheckpointSaver` writes every checkpoint to a hidden temporary file renamed onto its
  name when complete, and deletes the one it replaces only then (MONAI's saver writes in place, after ignite has
  deleted the old one); :func:`attach_resume` removes the temporaries a kill left and resumes from the newest
  checkpoint that loads (``weights_only=True``; one that would run code is refused, never skipped past);
  :class:`NonFiniteGuard` stops training at the first NaN/Inf loss or weight, before the epoch's checkpoints.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from ignite.engine import Engine, Events
from ignite.metrics import Metric
from monai.handlers import CheckpointSaver
from torch import Tensor, nn

from monai_probreg.blocks.integration import resize_displacement
from monai_probreg.blocks.warp import warp_labels
from monai_probreg.inference import atomic_write
from monai_probreg.losses.elbo import LossTerms, ProbRegLoss
from monai_probreg.metrics.dice import label_dice
from monai_probreg.metrics.jacobian import jacobian_determinant, jacobian_stats
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.validation import InputError, UntrustedFileError, safe_torch_load

__all__ = ["prepare_registration_batch", "RegistrationLoss", "RegistrationMetrics", "LossTermsLogger",
           "NonFiniteGuard", "AtomicCheckpointSaver", "PARTIAL_FILE", "remove_partial_files", "latest_checkpoint",
           "attach_resume", "key_metric_tracker", "one_hot_labels"]

# The temporary name of monai_probreg.inference.atomic_write: ".<name>.<12 hex>.tmp<suffixes of name>".
PARTIAL_FILE = re.compile(r"\..+\.[0-9a-f]{12}\.tmp(\.[^.]+)*")
_LOG = logging.getLogger("monai_probreg.train")

_KEYS = ("moving", "fixed", "moving_label", "fixed_label")


def prepare_registration_batch(batchdata: dict, device: str | torch.device | None = None,
                               non_blocking: bool = False, **kwargs: Any) -> tuple:
    """Engine ``prepare_batch``: ``(moving, targets, (fixed,), {})`` with every tensor on ``device``."""
    for key in ("moving", "fixed"):
        if key not in batchdata:
            raise KeyError(f"batch has no {key!r} entry; got keys {sorted(batchdata)}")
    targets = {k: batchdata[k].to(device=device, non_blocking=non_blocking, **kwargs)
               for k in _KEYS if isinstance(batchdata.get(k), Tensor)}  # label paths not loaded stay behind
    return targets["moving"], targets, (targets["fixed"],), {}


def one_hot_labels(labels: Tensor, label_values: Sequence[int]) -> Tensor:
    """(B, 1, *S) integer map -> (B, 1 + len(label_values), *S) float one-hot; channel 0 = everything else."""
    lut = torch.zeros(int(max(int(labels.max()), max(label_values))) + 1, dtype=torch.long, device=labels.device)
    lut[torch.as_tensor(list(label_values), device=labels.device)] = torch.arange(1, len(label_values) + 1,
                                                                              device=labels.device)
    idx = lut[labels.long().clamp(min=0)[:, 0]]
    return torch.nn.functional.one_hot(idx, len(label_values) + 1).movedim(-1, 1).float()


class RegistrationLoss(nn.Module):
    """``loss_function(pred, targets)`` for the engines.

    Args:
        loss: the objective (image likelihood + KL [+ Dice]).
        label_values: label ids one-hot encoded for the Dice term (needed only when ``loss.label_weight > 0``;
            the label maps must then be on the network grid).
    """

    def __init__(self, loss: ProbRegLoss, label_values: Sequence[int] | None = None) -> None:
        super().__init__()
        self.loss = loss
        self.label_values = list(label_values) if label_values is not None else None
        self.last_terms: LossTerms | None = None

    def forward(self, pred: RegistrationOutput, targets: dict) -> Tensor:
        moving_oh = fixed_oh = None
        if self.loss.label_weight > 0:
            if self.label_values is None or "moving_label" not in targets:
                raise ValueError("a label term needs label_values and moving_label/fixed_label in the batch")
            moving_oh = one_hot_labels(targets["moving_label"], self.label_values)
            fixed_oh = one_hot_labels(targets["fixed_label"], self.label_values)
        terms = self.loss(pred, targets["moving"], targets["fixed"], moving_oh, fixed_oh)
        self.last_terms = LossTerms(*(t.detach() for t in terms))
        if not torch.isfinite(terms.total):
            raise FloatingPointError(f"non-finite training loss ({terms}); stopping before weights become NaN")
        return terms.total


class LossTermsLogger:
    """Logs the parts of the loss (image, KL, label) every ``interval`` iterations."""

    def __init__(self, loss: RegistrationLoss, interval: int = 10, name: str = "monai_probreg.train") -> None:
        self.loss, self.interval, self.logger = loss, interval, logging.getLogger(name)

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.ITERATION_COMPLETED(every=self.interval), self)

    def __call__(self, engine: Engine) -> None:
        t = self.loss.last_terms
        if t is not None:
            self.logger.info(f"epoch {engine.state.epoch} iter {engine.state.iteration}: total {float(t.total):.4f} "
                             f"image {float(t.image):.4f} kl {float(t.kl):.4f} label {float(t.label):.4f}")


class RegistrationMetrics(Metric):
    """Mean Dice over ``label_values`` (default: non-zero labels of the fixed map) and mean |J| <= 0 count per pair.

    ``compute()`` returns ``{"dice": float, "folding": float}``. Attached as ``name`` (the evaluator's key metric),
    it writes ``state.metrics[name]`` (Dice), ``state.metrics[name + "_folding"]`` and, when ``max_folding`` is set,
    ``state.metrics[name + "_selection"]``: the Dice if fewer than ``max_folding`` voxels fold per pair on average,
    else Dice - 1, so that an epoch which folds ranks below every epoch which does not (and folding epochs still
    rank by Dice among themselves). Point a ``CheckpointSaver``'s ``key_metric_name`` at it to keep the best Dice
    among the epochs that do not fold.
    """

    def __init__(self, label_values: Sequence[int] | None = None, max_folding: float | None = None,
                 output_transform=lambda out: (out["pred"], out["label"])) -> None:
        if max_folding is not None and not (isinstance(max_folding, (int, float)) and max_folding > 0):
            raise ValueError(f"max_folding must be a positive number of voxels per pair or None; got {max_folding!r}")
        self.label_values = list(label_values) if label_values is not None else None
        self.max_folding = None if max_folding is None else float(max_folding)
        super().__init__(output_transform=output_transform)

    def reset(self) -> None:
        self._dice: list[float] = []
        self._folding: list[int] = []

    def update(self, output: tuple[RegistrationOutput, dict]) -> None:
        pred, targets = output
        moving_label, fixed_label = targets["moving_label"], targets["fixed_label"]
        ddf = resize_displacement(pred.displacement.float(), moving_label.shape[2:])
        warped = warp_labels(moving_label, ddf)
        for b in range(ddf.shape[0]):
            dice = label_dice(warped[b], fixed_label[b], self.label_values)
            values = [v for v in dice.values() if v == v]
            self._dice.append(sum(values) / max(len(values), 1))
            self._folding.append(jacobian_stats(jacobian_determinant(ddf[b : b + 1])).num_folding)

    def compute(self) -> dict[str, float]:
        if not self._dice:
            raise RuntimeError("RegistrationMetrics has no data; was the evaluator run on labelled pairs?")
        return {"dice": sum(self._dice) / len(self._dice), "folding": sum(self._folding) / len(self._folding)}

    def completed(self, engine: Engine, name: str) -> None:
        result = self.compute()
        engine.state.metrics[name] = result["dice"]
        engine.state.metrics[f"{name}_folding"] = result["folding"]
        if self.max_folding is not None:
            eligible = result["folding"] < self.max_folding
            engine.state.metrics[f"{name}_selection"] = result["dice"] - (0.0 if eligible else 1.0)


class NonFiniteGuard:
    """Stops training at the first non-finite loss or weight with a ``FloatingPointError`` naming the epoch, the
    iteration and the first bad parameter.

    It runs at ``ITERATION_COMPLETED``, after the optimizer step and before ``EPOCH_COMPLETED`` (validation and the
    checkpoints), so no checkpoint ever holds NaN weights: the newest on disk is the last good epoch's. Checking the
    weights costs one ``isfinite().all()`` per parameter tensor and a single host sync per iteration.

    Args:
        check_weights: also check the trainer's ``network`` parameters (a finite loss can still give Inf gradients).
        output_transform: engine output -> loss tensor (MONAI trainers: ``output["loss"]``).
    """

    def __init__(self, check_weights: bool = True,
                 output_transform: Callable[[Any], Tensor] = lambda output: output["loss"]) -> None:
        self.check_weights, self.output_transform = check_weights, output_transform

    def attach(self, engine: Engine) -> None:
        engine.add_event_handler(Events.ITERATION_COMPLETED, self)

    def __call__(self, engine: Engine) -> None:
        where = f"training stopped at epoch {engine.state.epoch}, iteration {engine.state.iteration}"
        advice = ("no checkpoint of this epoch was written; resume from the last one with a lower learning_rate or "
                  "check the data")
        loss = torch.as_tensor(self.output_transform(engine.state.output)).detach()
        if not bool(torch.isfinite(loss).all()):
            raise FloatingPointError(f"{where}: expected a finite loss, got {loss.flatten()[:4].tolist()}; {advice}")
        network = getattr(engine, "network", None)
        if not self.check_weights or network is None:
            return
        params = [(name, p.detach()) for name, p in network.named_parameters()]
        finite = torch.stack([torch.isfinite(p).all() for _, p in params]) if params else torch.ones(1, dtype=bool)
        if not bool(finite.all()):  # one host sync
            name, p = params[int((~finite).nonzero()[0])]
            bad = int((~torch.isfinite(p)).sum())
            raise FloatingPointError(f"{where}: expected finite weights, got {bad} NaN/Inf values in {name!r} after "
                                     f"the optimizer step; {advice}")


def _make_crash_safe(handler: Any) -> None:
    """Make an ignite ``DiskSaver`` write through :func:`~monai_probreg.inference.atomic_write` and delete the file a
    new checkpoint replaces only once the new one is complete (ignite's ``Checkpoint`` deletes it first, so a kill
    during the write would leave no training state at all)."""
    if not callable(getattr(handler, "_save_func", None)) or not callable(getattr(handler, "remove", None)):
        raise TypeError(f"expected an ignite DiskSaver with _save_func and remove, got {type(handler).__name__}; "
                        "this ignite version is not supported by AtomicCheckpointSaver")
    remove_now, pending = handler.remove, []

    def remove_later(filename: str) -> None:
        pending.append(filename)

    def save(checkpoint: Any, path: Path, func: Callable) -> None:
        atomic_write(path, lambda tmp: func(checkpoint, tmp, **handler.kwargs))
        while pending:
            filename = pending.pop(0)
            if (getattr(handler, "filename", None) or filename) != Path(path).name:  # MONAI's fixed model.pt
                remove_now(filename)

    handler._save_func, handler.remove = save, remove_later


class AtomicCheckpointSaver(CheckpointSaver):
    """MONAI's ``CheckpointSaver`` (same arguments), crash-safe: each file is written to a hidden temporary in
    ``save_dir`` renamed onto its name once complete, and the checkpoint it replaces (``n_saved``) is deleted only
    after that. A crash or SIGKILL at any moment leaves the previous checkpoint intact plus at most a temporary
    (:data:`PARTIAL_FILE`), which :func:`attach_resume` removes. (MONAI's saver writes in place, ``atomic=False``,
    and ignite deletes the old checkpoint before writing the new one.)"""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for checkpoint in (self._final_checkpoint, self._key_metric_checkpoint, self._interval_checkpoint):
            if checkpoint is not None:
                _make_crash_safe(checkpoint.save_handler)


def remove_partial_files(folder: str | Path) -> list[Path]:
    """Delete the temporaries an interrupted atomic write left in ``folder`` (only names matching PARTIAL_FILE)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = [p for p in folder.iterdir() if p.is_file() and PARTIAL_FILE.fullmatch(p.name)]
    for path in removed:
        path.unlink(missing_ok=True)
        _LOG.warning(f"removed {path.name}: a checkpoint whose writing was interrupted")
    return removed


def latest_checkpoint(ckpt_dir: str, prefix: str = "train_state") -> str | None:
    """Newest ``<prefix>*.pt`` in ``ckpt_dir`` (by modification time) that loads, or None (start from scratch).

    A truncated or corrupt file is skipped with a warning (the next newest is tried); one that
    ``torch.load(weights_only=True)`` refuses raises :class:`~monai_probreg.validation.UntrustedFileError`: a file
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


def attach_resume(engine: Engine, ckpt_dir: str, load_dict: dict, prefix: str = "train_state",
                  map_location: str | torch.device | None = None) -> str | None:
    """Attach MONAI's ``CheckpointLoader`` (``weights_only=True``) for the newest usable training state, if any,
    after removing the temporaries of interrupted writes (:func:`remove_partial_files`).

    Returns the checkpoint path that will be loaded when the engine starts, or None (fresh start).
    """
    from monai.handlers import CheckpointLoader

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


def key_metric_tracker(saver: Any) -> Any:
    """The best-score bookkeeping of a MONAI ``CheckpointSaver(save_key_metric=True)``, for the training state.

    MONAI's saver can *load* this state but has no ``state_dict`` to *save* it, so after a resume the first
    validation would always count as a new best and overwrite ``model.pt`` even when worse. Saving its ignite
    ``Checkpoint`` (scores and file names only) in the training state keeps "best" meaning best across restarts.
    """
    tracker = getattr(saver, "_key_metric_checkpoint", None)
    return tracker if tracker is not None else _NoTracker()
