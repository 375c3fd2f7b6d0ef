"""Training that survives a crash: SIGKILL mid-epoch and mid-checkpoint-write, then resume; NaN guards; numerical
extremes of the loss and the log-variance; determinism. Tiny runs of bundle/configs/train.yaml (3 subjects of 32^3,
two training iterations per epoch) on the synthetic dataset of tests/conftest.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from ignite.engine import Engine, Events
from monai.bundle import ConfigWorkflow

from monai_probreg import ProbRegNet
from monai_probreg.engines.checkpoints import latest_checkpoint
from monai_probreg.engines.guards import NonFiniteGuard
from monai_probreg.losses.elbo import ProbRegLoss
from monai_probreg.networks.velocity_unet import LOG_VAR_MAX, bound_log_var
from monai_probreg.utils.files import PARTIAL_FILE, atomic_write, remove_partial_files

ROOT = Path(__file__).resolve().parents[2]
TRAIN = ROOT / "bundle" / "configs" / "train.yaml"
TINY = {"network_size": [32, 32, 32], "val_ids": ["T01"], "val_interval": 1, "num_workers": 0}
ITERS = 2  # per epoch: 2 training subjects, batch 1

# The child: a tiny train.yaml run that either pauses mid-epoch (the parent SIGKILLs it) or SIGKILLs itself halfway
# through writing a training-state checkpoint.
CHILD = r"""
import io, json, os, signal, sys, time
from pathlib import Path
import torch
from ignite.engine import Events
from monai.bundle import ConfigWorkflow

cfg = json.loads(sys.argv[1])
wf = ConfigWorkflow(config_file=cfg["config"], workflow_type="train", logging_file=False, **cfg["settings"])
wf.initialize()
trainer, kill_epoch, marker = wf.trainer, cfg["kill_epoch"], Path(cfg["marker"])
if cfg["mode"] == "mid_epoch":
    @trainer.on(Events.ITERATION_COMPLETED)
    def pause(engine):
        if engine.state.epoch == kill_epoch and engine.state.iteration % engine.state.epoch_length == 1:
            marker.write_text(str(engine.state.iteration))
            time.sleep(600)  # SIGKILLed here, between two iterations of epoch kill_epoch
else:
    real_save = torch.save
    def half_save(obj, f, *args, **kwargs):
        if trainer.state.epoch == kill_epoch and "train_state" in str(f):
            buffer = io.BytesIO()
            real_save(obj, buffer, *args, **kwargs)
            with open(f, "wb") as out:
                out.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
            marker.write_text(str(f))
            os.kill(os.getpid(), signal.SIGKILL)
        return real_save(obj, f, *args, **kwargs)
    torch.save = half_save
wf.run()
"""


def _settings(tmp_path: Path, dataset: Path, **override) -> dict:
    return {
        **TINY,
        "bundle_root": str(ROOT / "bundle"),
        "dataset_dir": str(dataset),
        "ckpt_dir": str(tmp_path / "ckpt"),
        "output_dir": str(tmp_path / "runs"),
        **override,
    }


def _workflow(tmp_path: Path, dataset: Path, **override) -> ConfigWorkflow:
    wf = ConfigWorkflow(
        config_file=str(TRAIN), workflow_type="train", logging_file=False, **_settings(tmp_path, dataset, **override)
    )
    wf.initialize()
    return wf


def _crash(tmp_path: Path, dataset: Path, mode: str, kill_epoch: int) -> None:
    """Run the child until its kill point; mid_epoch: wait for its marker, then SIGKILL it from here."""
    marker = tmp_path / "marker"
    cfg = {
        "config": str(TRAIN),
        "settings": _settings(tmp_path, dataset, max_epochs=10),
        "mode": mode,
        "kill_epoch": kill_epoch,
        "marker": str(marker),
    }
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    log = (tmp_path / "child.log").open("w")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    child = subprocess.Popen(
        [sys.executable, str(script), json.dumps(cfg)], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT
    )
    deadline = time.monotonic() + 150
    while not marker.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    if mode == "mid_epoch" and marker.exists():
        child.send_signal(signal.SIGKILL)
    try:
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
        log.close()
    assert marker.exists(), "the child never reached its kill point:\n" + (tmp_path / "child.log").read_text()[-3000:]
    assert child.returncode == -signal.SIGKILL, (tmp_path / "child.log").read_text()[-3000:]


def _resume_and_check(tmp_path: Path, dataset: Path, saved_epoch: int) -> None:
    """Resume to saved_epoch + 2: it must start exactly from the checkpoint (weights, Adam moments and step
    counts, iteration and epoch), run the two remaining epochs, and leave only complete checkpoint files."""
    ckpt = tmp_path / "ckpt"
    (state_file,) = ckpt.glob("train_state*.pt")
    assert state_file.name == f"train_state_checkpoint_epoch={saved_epoch}.pt"
    saved = torch.load(state_file, weights_only=True)
    resumed = _workflow(tmp_path, dataset, max_epochs=saved_epoch + 2)
    seen: dict = {"epochs": []}

    @resumed.trainer.on(Events.EPOCH_STARTED)
    def _check_restored(engine):  # after CheckpointLoader (Events.STARTED), before the first update
        seen["epochs"].append(engine.state.epoch)
        if len(seen["epochs"]) > 1:
            return
        seen["iteration"] = engine.state.iteration
        for name, value in resumed.parser.get_parsed_content("network").state_dict().items():
            torch.testing.assert_close(value, saved["model"][name], rtol=0, atol=0, msg=name)
        optimizer = resumed.parser.get_parsed_content("optimizer").state_dict()
        assert optimizer["param_groups"] == saved["optimizer"]["param_groups"]
        for index, state in saved["optimizer"]["state"].items():
            for key, value in state.items():  # Adam: step, exp_avg, exp_avg_sq, bit for bit
                torch.testing.assert_close(optimizer["state"][index][key], value, rtol=0, atol=0, msg=key)

    resumed.run()
    resumed.finalize()
    assert seen["epochs"] == [saved_epoch + 1, saved_epoch + 2]
    assert seen["iteration"] == saved_epoch * ITERS
    final = torch.load(ckpt / f"train_state_checkpoint_epoch={saved_epoch + 2}.pt", weights_only=True)
    assert final["trainer"]["iteration"] == (saved_epoch + 2) * ITERS
    assert {int(s["step"]) for s in final["optimizer"]["state"].values()} == {(saved_epoch + 2) * ITERS}
    assert not [p.name for p in ckpt.iterdir() if PARTIAL_FILE.fullmatch(p.name)]
    for path in ckpt.glob("*.pt"):
        torch.load(path, weights_only=True)  # every file left is complete


@pytest.mark.parametrize("mode", ["mid_epoch", "during_save"])
def test_sigkill_then_resume(tmp_path, tiny_dataset, mode, single_thread):
    """mid_epoch: killed after iteration 1 of epoch 3, the epoch-2 checkpoint on disk. during_save: killed with
    half of the epoch-3 training state written, which must leave the epoch-2 checkpoint intact."""
    _crash(tmp_path, tiny_dataset, mode, kill_epoch=3)
    partial = [p for p in (tmp_path / "ckpt").iterdir() if PARTIAL_FILE.fullmatch(p.name)]
    assert len(partial) == (1 if mode == "during_save" else 0)  # the interrupted write is a hidden temporary
    _resume_and_check(tmp_path, tiny_dataset, saved_epoch=2)


def test_atomic_write_temporaries_match_the_cleanup_pattern(tmp_path):
    names = []
    atomic_write(
        tmp_path / "train_state_checkpoint_epoch=3.pt", lambda tmp: names.append(Path(tmp).name) or torch.save({}, tmp)
    )
    assert PARTIAL_FILE.fullmatch(names[0])
    for keep in ("model.pt", "train_state_checkpoint_epoch=3.pt", ".hidden", "tmpab12cd34", "notes.tmp.txt"):
        (tmp_path / keep).write_text("mine")
    (tmp_path / names[0]).write_text("half")
    assert [p.name for p in remove_partial_files(tmp_path)] == [names[0]]
    assert not (tmp_path / names[0]).exists() and (tmp_path / "tmpab12cd34").exists()


def test_resume_skips_a_truncated_newest_checkpoint(tmp_path):
    torch.save({"trainer": {"iteration": 2}}, tmp_path / "train_state_checkpoint_epoch=1.pt")
    time.sleep(0.01)
    newest = tmp_path / "train_state_checkpoint_epoch=2.pt"
    torch.save({"trainer": {"iteration": 4}, "pad": torch.zeros(1000)}, newest)
    newest.write_bytes(newest.read_bytes()[:500])  # a writer that was not atomic, killed halfway
    assert latest_checkpoint(str(tmp_path)) == str(tmp_path / "train_state_checkpoint_epoch=1.pt")


# ------------------------------------------------------------------------------------------------ numerical guards
@pytest.mark.parametrize(
    "fault, words", [("nan_gradient", "expected finite weights"), ("tiny_sigma", "non-finite training loss")]
)
def test_non_finite_training_stops_without_writing_a_checkpoint(tmp_path, tiny_dataset, fault, words, single_thread):
    """nan_gradient: a finite loss whose gradient is NaN in one tensor (a hook), so Adam's step writes NaN weights:
    NonFiniteGuard stops at that iteration. tiny_sigma: image_sigma 1e-30 makes the image term Inf, refused by
    RegistrationLoss before backward. Either way: a clear error and no checkpoint of NaN weights on disk."""
    wf = _workflow(tmp_path, tiny_dataset, max_epochs=2, **({"image_sigma": 1e-30} if fault == "tiny_sigma" else {}))
    if fault == "nan_gradient":
        bias = wf.parser.get_parsed_content("network").unet.mean_head.bias
        bias.register_hook(lambda grad: torch.full_like(grad, float("nan")))
    with pytest.raises(Exception) as info:
        wf.run()
    chain, error = [], info.value
    while error is not None:
        chain.append(error)
        error = error.__cause__ or error.__context__
    stop = next((e for e in chain if isinstance(e, FloatingPointError)), None)
    assert stop is not None and words in str(stop), [str(e)[:200] for e in chain]
    if fault == "nan_gradient":
        assert "epoch 1, iteration 1" in str(stop) and "'unet.mean_head.bias'" in str(stop)
    assert not list((tmp_path / "ckpt").glob("*.pt"))


def test_non_finite_guard_names_the_parameter():
    net = torch.nn.Linear(2, 2)
    engine = Engine(lambda e, batch: {"loss": torch.tensor(1.0)})
    engine.network = net
    NonFiniteGuard().attach(engine)
    engine.run([0, 1], max_epochs=1)  # finite: nothing happens
    with torch.no_grad():
        net.bias[1] = float("nan")
    with pytest.raises(
        FloatingPointError,
        match=r"epoch 1, iteration 1: expected finite weights, got 1 NaN/Inf "
        r"values in 'bias'",
    ):
        engine.run([0, 1], max_epochs=1)
    nan_loss = Engine(lambda e, batch: {"loss": torch.tensor(float("inf"))})
    NonFiniteGuard().attach(nan_loss)
    with pytest.raises(FloatingPointError, match="expected a finite loss, got \\[inf\\]"):
        nan_loss.run([0], max_epochs=1)


@pytest.mark.parametrize("image_loss", ["gaussian", "lncc"])
@pytest.mark.parametrize("value", [0.0, 0.5, 1.0])
def test_loss_and_gradients_are_finite_on_constant_images(image_loss, value, single_thread):
    """All-zero and constant pairs (no contrast: LNCC's variances are 0) in train mode, bidirectional."""
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=3, bidirectional=True).train()
    moving = fixed = torch.full((1, 1, 16, 16, 16), value)
    terms = ProbRegLoss(image_loss=image_loss)(net(moving, fixed), moving, fixed)
    terms.total.backward()
    assert all(torch.isfinite(t) for t in terms)
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_log_variance_head_is_bounded_and_unchanged_at_initialisation():
    torch.manual_seed(0)
    net = ProbRegNet(spatial_dims=2).train()
    unet, pair = net.unet, (torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32))
    captured = {}  # the head's output before the bound
    unet.log_var_head.register_forward_hook(lambda module, inputs, output: captured.__setitem__("raw", output))
    log_var = net(*pair).velocity_log_var
    assert torch.equal(log_var, captured["raw"])  # initial values ~ -10: the bound is the identity there
    with torch.no_grad():
        unet.log_var_head.bias.fill_(1e4)  # a diverged head: exp() of the raw value would be inf
    log_var = net(*pair).velocity_log_var
    assert float(captured["raw"].min()) > 1e3  # the raw values really are beyond exp()'s float32 range (88.7)
    assert torch.isfinite(torch.exp(log_var)).all() and float(log_var.max()) <= LOG_VAR_MAX
    x = torch.tensor([-10.0, 0.0, 4.9, 9.0, 50.0], requires_grad=True)
    bound_log_var(x).sum().backward()
    assert torch.equal(x.grad[:3], torch.ones(3))  # identity inside [-25, 5]
    assert 0 < x.grad[3] < 1 and x.grad[4] >= 0  # smooth saturation, never a negative slope


# ---------------------------------------------------------------------------------------------------- determinism
def test_same_seed_gives_identical_weights(tmp_path, tiny_dataset, single_thread):
    """Two CPU runs of train.yaml with seed 0 give bit-identical weights; seed 1 differs (the test can fail)."""

    def train(folder: str, seed: int) -> dict:
        wf = _workflow(tmp_path / folder, tiny_dataset, max_epochs=1, seed=seed, val_interval=100)
        wf.run()
        wf.finalize()
        return {k: v.clone() for k, v in wf.parser.get_parsed_content("network").state_dict().items()}

    first, second, other = train("a", 0), train("b", 0), train("c", 1)
    for name in first:
        assert torch.equal(first[name], second[name]), name
    assert any(not torch.equal(first[name], other[name]) for name in first)
