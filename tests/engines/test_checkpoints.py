"""Tests of the crash-safe checkpoint saver (ignite's public Checkpoint API) and the key-metric tracker."""

from __future__ import annotations

import pytest
import torch
from ignite.engine import Engine, Events

from monai_probreg.engines.checkpoints import AtomicCheckpointSaver, AtomicDiskSaver, key_metric_tracker


def _engine_with_scores(scores):
    """An engine whose epoch e ends with metrics {"dice": scores[e - 1]}."""
    engine = Engine(lambda e, b: None)

    @engine.on(Events.EPOCH_COMPLETED)
    def score(e):
        e.state.metrics["dice"] = scores[e.state.epoch - 1]

    return engine


def test_best_key_metric_goes_to_the_fixed_file_and_stays_best(tmp_path):
    net = torch.nn.Linear(2, 1)
    scores = [0.5, 0.7, 0.6]
    saved = []
    engine = _engine_with_scores(scores)
    saver = AtomicCheckpointSaver(
        tmp_path, {"model": net}, save_key_metric=True, key_metric_name="dice", key_metric_filename="model.pt"
    )
    engine.add_event_handler(Events.EPOCH_STARTED, lambda e: torch.nn.init.constant_(net.bias, e.state.epoch))
    saver.attach(engine)
    engine.add_event_handler(
        Events.EPOCH_COMPLETED,
        lambda e: saved.append(float(torch.load(tmp_path / "model.pt", weights_only=True)["bias"])),
    )
    engine.run([0], max_epochs=3)
    assert saved == [1.0, 2.0, 2.0]  # epoch 3 (0.6) is worse than epoch 2 (0.7): model.pt keeps epoch 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]
    state = key_metric_tracker(saver).state_dict()
    assert [priority for priority, _ in next(iter(state.values()))] == [0.7]


def test_interval_checkpoints_use_monais_names_and_keep_n_saved(tmp_path):
    net = torch.nn.Linear(2, 1)
    engine = Engine(lambda e, b: None)
    AtomicCheckpointSaver(
        tmp_path, {"model": net, "trainer": engine}, file_prefix="train_state", save_interval=1, n_saved=2
    ).attach(engine)
    engine.run([0, 0], max_epochs=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "train_state_checkpoint_epoch=2.pt",
        "train_state_checkpoint_epoch=3.pt",
    ]
    state = torch.load(tmp_path / "train_state_checkpoint_epoch=3.pt", weights_only=True)
    assert state["trainer"]["iteration"] == 6 and set(state["model"]) == {"weight", "bias"}


def test_the_replaced_checkpoint_is_deleted_only_after_the_new_one_is_complete(tmp_path):
    handler = AtomicDiskSaver(tmp_path)
    handler({"a": torch.zeros(1)}, "ckpt_1.pt")
    handler.remove("ckpt_1.pt")  # ignite asks for the removal before saving the replacement
    assert (tmp_path / "ckpt_1.pt").exists()
    handler({"a": torch.ones(1)}, "ckpt_2.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt_2.pt"]


def test_a_fixed_name_is_never_deleted_by_its_own_replacement(tmp_path):
    handler = AtomicDiskSaver(tmp_path, filename="model.pt")
    handler({"a": torch.zeros(1)}, "model_key_metric=0.5.pt")
    handler.remove("model_key_metric=0.5.pt")
    handler({"a": torch.ones(1)}, "model_key_metric=0.7.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]
    assert float(torch.load(tmp_path / "model.pt", weights_only=True)["a"]) == 1.0


def test_missing_key_metric_is_named(tmp_path):
    engine = Engine(lambda e, b: None)
    AtomicCheckpointSaver(
        tmp_path, {"model": torch.nn.Linear(1, 1)}, save_key_metric=True, key_metric_name="dice"
    ).attach(engine)
    with pytest.raises(KeyError, match="dice"):
        engine.run([0], max_epochs=1)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"save_dict": {}}, "save_dict"),
        ({"key_metric_filename": "m.pt", "key_metric_n_saved": 2}, "n_saved=1"),
        ({"save_interval": -1}, "save_interval"),
    ],
)
def test_bad_arguments_are_refused(tmp_path, kwargs, words):
    args = {"save_dict": {"model": torch.nn.Linear(1, 1)}, **kwargs}
    with pytest.raises(ValueError, match=words):
        AtomicCheckpointSaver(tmp_path, **args)


def test_tracker_of_a_disabled_saver_is_an_empty_stand_in():
    tracker = key_metric_tracker(None)
    assert tracker.state_dict() == {}
    tracker.load_state_dict({})
