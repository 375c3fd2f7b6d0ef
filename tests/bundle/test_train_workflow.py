"""bundle/configs/train.yaml (and multi_gpu_train.yaml) run end to end on the tiny synthetic dataset.

Every run is tiny on purpose (3 subjects of 32^3, network grid 32^3, one or two epochs): these tests pin the
wiring (what is written where, what a resume restores, which rank writes), not the quality of the training.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest
import torch
from ignite.engine import Events
from monai.bundle import ConfigWorkflow

from monai_probreg import ProbRegNet

ROOT = Path(__file__).resolve().parents[2]
BUNDLE = ROOT / "bundle"
TRAIN = BUNDLE / "configs" / "train.yaml"
MULTI_GPU = BUNDLE / "configs" / "multi_gpu_train.yaml"

TINY = {"network_size": [32, 32, 32], "val_ids": ["T01"], "val_interval": 1, "num_workers": 0}


def _workflow(tmp_path: Path, dataset: Path, config: str | Sequence[str] = str(TRAIN), **override) -> ConfigWorkflow:
    """An initialised train workflow on ``dataset`` writing into ``tmp_path`` (ckpt/, runs/)."""
    settings = {
        **TINY,
        "bundle_root": str(BUNDLE),
        "dataset_dir": str(dataset),
        "ckpt_dir": str(tmp_path / "ckpt"),
        "output_dir": str(tmp_path / "runs"),
        **override,
    }
    wf = ConfigWorkflow(config_file=config, workflow_type="train", logging_file=False, **settings)
    wf.initialize()
    return wf


def _train_states(ckpt_dir: Path) -> list[Path]:
    return sorted(ckpt_dir.glob("train_state*.pt"))


def _epoch(trainer_state: dict) -> int:
    """ignite's Engine.state_dict keeps iteration and epoch_length; the epoch follows from them."""
    return trainer_state["iteration"] // trainer_state["epoch_length"]


def _net_from_config(wf: ConfigWorkflow) -> ProbRegNet:
    p = wf.parser
    return ProbRegNet(
        spatial_dims=3,
        enc_channels=p["enc_channels"],
        dec_channels=p["dec_channels"],
        int_downsize=p["int_downsize"],
        num_steps=p["num_steps"],
        bidirectional=p["bidirectional"],
        network_size=p["network_size"],
    )


def test_train_writes_best_weights_and_training_state(tmp_path, tiny_dataset):
    wf = _workflow(tmp_path, tiny_dataset, max_epochs=2)
    assert wf.check_properties() == []  # every required TrainProperties/MetaProperties entry, optional IDs right
    history: list[dict] = []
    wf.evaluator.add_event_handler(Events.EPOCH_COMPLETED, lambda e: history.append(dict(e.state.metrics)))
    wf.run()
    wf.finalize()

    ckpt = tmp_path / "ckpt"
    weights = torch.load(ckpt / "model.pt", weights_only=True)
    _net_from_config(wf).load_state_dict(weights)  # strict: the same architecture, plain (unwrapped) names
    # the settings the tensors cannot show travel beside them, and the training config's network fits them
    from monai_probreg.weights.settings import check_network_settings

    recorded = check_network_settings(ckpt / "model.pt", _net_from_config(wf))
    assert recorded is not None and recorded["network_size"] == TINY["network_size"]
    states = _train_states(ckpt)
    assert len(states) == 1, f"n_saved=1 keeps one training state; found {[p.name for p in states]}"
    state = torch.load(states[0], weights_only=True)
    assert set(state) == {"model", "optimizer", "trainer", "best_model"}
    assert _epoch(state["trainer"]) == 2
    # the best-Dice bookkeeping travels with the training state, so a resume keeps comparing against it
    (best,) = state["best_model"]["_saved"]
    assert str(best[1]).startswith("model")  # ignite names it model_key_metric=<score>.pt; MONAI writes model.pt
    # the priority is the folding-aware score (max_folding 1): Dice, minus 1 for an epoch folding >= 1 voxel per pair
    assert len(history) == 2
    for metrics in history:
        penalty = 0.0 if metrics["val_dice_folding"] < 1.0 else 1.0
        assert metrics["val_dice_selection"] == pytest.approx(metrics["val_dice"] - penalty)
    assert best[0] == pytest.approx(max(m["val_dice_selection"] for m in history))
    assert any((tmp_path / "runs").glob("events.out.tfevents.*"))


def test_resume_continues_from_saved_epoch_with_optimizer_state(tmp_path, tiny_dataset):
    first = _workflow(tmp_path, tiny_dataset, max_epochs=1)
    first.run()
    first.finalize()
    (saved,) = _train_states(tmp_path / "ckpt")
    saved_state = torch.load(saved, weights_only=True)
    iters_per_epoch = saved_state["trainer"]["epoch_length"]
    assert iters_per_epoch == 2  # 2 training subjects, batch 1
    assert _epoch(saved_state["trainer"]) == 1

    second = _workflow(tmp_path, tiny_dataset, max_epochs=2)
    trainer = second.trainer
    seen = {"epochs": [], "iterations": 0}

    @trainer.on(Events.EPOCH_STARTED)
    def _check_restored(engine):  # after CheckpointLoader (Events.STARTED), before the first update
        seen["epochs"].append(engine.state.epoch)
        if len(seen["epochs"]) == 1:
            seen["iteration_at_start"] = engine.state.iteration
            net = second.parser.get_parsed_content("network")
            for name, value in net.state_dict().items():
                torch.testing.assert_close(value, saved_state["model"][name], rtol=0, atol=0, msg=name)
            opt_state = second.parser.get_parsed_content("optimizer").state_dict()["state"]
            seen["adam_steps_at_start"] = {int(s["step"]) for s in opt_state.values()}

    @trainer.on(Events.ITERATION_COMPLETED)
    def _count(engine):
        seen["iterations"] += 1

    second.run()
    second.finalize()

    assert seen["epochs"] == [2], "the resumed run must train only epoch 2"
    assert seen["iteration_at_start"] == iters_per_epoch
    assert seen["iterations"] == iters_per_epoch
    assert seen["adam_steps_at_start"] == {iters_per_epoch}, "Adam moments/step counts not restored"
    final = torch.load(_train_states(tmp_path / "ckpt")[-1], weights_only=True)
    assert final["trainer"]["iteration"] == 2 * iters_per_epoch
    assert {int(s["step"]) for s in final["optimizer"]["state"].values()} == {2 * iters_per_epoch}


def test_semi_supervised_training_uses_the_label_term(tmp_path, tiny_dataset):
    semi = str(TRAIN.parent / "train_semisupervised.yaml")
    # the variant fine-tunes from models/model.pt (train.yaml's output, or the shipped default), here in ckpt_dir as
    # train.yaml leaves it: a model whose mean-head bias is recognisable
    init = ProbRegNet(spatial_dims=3, network_size=TINY["network_size"])
    with torch.no_grad():
        init.unet.mean_head.bias.fill_(0.123)
    start = tmp_path / "ckpt" / "model.pt"
    start.parent.mkdir()
    torch.save(init.state_dict(), start)
    start_bytes = start.read_bytes()
    wf = _workflow(tmp_path, tiny_dataset, config=[str(TRAIN), semi], max_epochs=1, init_model_file=str(start))
    assert wf.parser.get_parsed_content("label_values") == [21, 22, 181]  # read from the atlas label map
    wf.run()
    wf.finalize()
    # 2 Adam steps of lr 2e-4 move a parameter by at most ~4e-4: the start was the given weights, not a fresh init
    bias = wf.parser.get_parsed_content("network_def").unet.mean_head.bias
    assert torch.allclose(bias, torch.full_like(bias, 0.123), atol=1e-2)
    assert (tmp_path / "ckpt" / "model_semisupervised.pt").is_file()
    assert start.read_bytes() == start_bytes  # the weights it starts from (models/model.pt) are never overwritten
    terms = wf.parser.get_parsed_content("loss").last_terms
    assert terms is not None and torch.isfinite(terms.total)
    # a Dice loss of labels that overlap only partly; exactly 0 would mean the term was never computed
    assert 0.0 < float(terms.label) < 1.0
    weight = wf.parser.get_parsed_content("label_weight")
    torch.testing.assert_close(terms.total, terms.image + terms.kl + weight * terms.label, rtol=1e-5, atol=1e-5)


def test_augmented_semi_supervised_training_runs_after_the_cache(tmp_path, tiny_dataset):
    from monai.transforms import RandAffined

    semi = str(TRAIN.parent / "train_semisupervised.yaml")
    wf = _workflow(
        tmp_path,
        tiny_dataset,
        config=[str(TRAIN), semi],
        max_epochs=1,
        init_model_file=None,
        augment_prob=1.0,
        augment_rotate=0.2,
        augment_translate=3.0,
    )
    dataset = wf.parser.get_parsed_content("train#dataset")
    steps = dataset.transform.transforms
    first_random = next(i for i, t in enumerate(steps) if isinstance(t, RandAffined))
    assert first_random == len(wf.parser.get_parsed_content("train#preprocessing").transforms)
    assert steps[first_random].keys == ("moving", "moving_label")  # the atlas (fixed) side is never augmented
    wf.run()
    wf.finalize()
    terms = wf.parser.get_parsed_content("loss").last_terms
    assert terms is not None and torch.isfinite(terms.total) and 0.0 < float(terms.label) < 1.0


def test_multi_gpu_config_parses_and_overrides_single_process_pieces():
    from monai.bundle import ConfigParser

    single = ConfigParser.load_config_file(str(TRAIN))
    config = ConfigParser.load_config_files([str(TRAIN), str(MULTI_GPU)])
    assert config["imports"] == single["imports"] + ["$import torch.distributed as dist"]  # '+imports' extends
    assert config["network"]["_target_"] == "torch.nn.parallel.DistributedDataParallel"
    assert config["train"]["dataloader"]["sampler"] == "@train#sampler"
    assert config["train"]["dataloader"]["shuffle"] is False
    # the indices multi_gpu_train.yaml disables on ranks > 0 must still point at the handlers named there
    train_targets = [h["_target_"] for h in config["train"]["handlers"]]
    val_targets = [h["_target_"] for h in config["validate"]["handlers"]]
    assert train_targets == [
        "ValidationHandler",
        "StatsHandler",
        "TensorBoardStatsHandler",
        "monai_probreg.engines.guards.NonFiniteGuard",
    ]
    assert val_targets == [
        "StatsHandler",
        "TensorBoardStatsHandler",
        "monai_probreg.engines.checkpoints.AtomicCheckpointSaver",
        "monai_probreg.weights.settings.NetworkSettingsWriter",
    ]
    # every rank keeps its NaN guard (its own weights); the other handlers run on rank 0 only
    assert all("_disabled_" in h for h in config["train"]["handlers"][:3] + config["validate"]["handlers"])
    assert "_disabled_" not in config["train"]["handlers"][3]
    assert "finalize" in config and "run" in config


@pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="torch.distributed with the gloo backend is not available in this torch build",
)
def test_two_process_ddp_training_on_gloo(tmp_path, tiny_dataset):
    try:
        import torch.distributed.run  # noqa: F401  (what the torchrun script runs)
    except ImportError as err:
        pytest.skip(f"torchrun (torch.distributed.run) is unavailable: {err}")
    # test probe: ranks other than 0 save into their own folder, so a file there would show a second writer
    probe = tmp_path / "probe.yaml"
    other = "$@ckpt_dir if dist.get_rank() == 0 else @ckpt_dir + '/other_ranks'"
    probe.write_text(f'checkpoint#saver#save_dir: "{other}"\nvalidate#handlers#2#save_dir: "{other}"\n')
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "monai.bundle",
        "run",
        "--config_file",
        f"['{TRAIN}','{MULTI_GPU}','{probe}']",
        "--bundle_root",
        str(BUNDLE),
        "--dataset_dir",
        str(tiny_dataset),
        "--ckpt_dir",
        str(tmp_path / "ckpt"),
        "--output_dir",
        str(tmp_path / "runs"),
        "--network_size",
        "[32,32,32]",
        "--val_ids",
        "['T01']",
        "--val_interval",
        "1",
        "--num_workers",
        "0",
        "--max_epochs",
        "1",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}  # gloo on CPU even on a GPU host
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=180)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]

    ckpt = tmp_path / "ckpt"
    assert sorted(p.name for p in ckpt.iterdir() if p.name != "other_ranks") == [
        "model.network.json",
        "model.pt",
        "train_state_checkpoint_epoch=1.pt",
    ]
    # one checkpoint writer: rank 1 builds the (unattached) saver, which may create its folder, but writes nothing
    assert not [p for p in (ckpt / "other_ranks").rglob("*")] if (ckpt / "other_ranks").exists() else True
    ProbRegNet(network_size=[32, 32, 32]).load_state_dict(torch.load(ckpt / "model.pt", weights_only=True))
    state = torch.load(ckpt / "train_state_checkpoint_epoch=1.pt", weights_only=True)
    assert not any(k.startswith("module.") for k in state["model"]), "DDP wrapper leaked into the checkpoint"
    # 2 training subjects over 2 ranks: one iteration per rank per epoch (disjoint shards, not the whole set each)
    assert state["trainer"]["iteration"] == 1
    assert len(re.findall(r"Epoch: 1/1, Iter: 1/1", log)) == 1, "one logger (rank 0): " + log[-4000:]
    # TensorBoard files are named events.out.tfevents.<time>.<host>.<pid>.<n>: all from one process (rank 0)
    writers = {p.name.split(".")[-2] for p in (tmp_path / "runs").glob("events.out.tfevents.*")}
    assert len(writers) == 1, f"TensorBoard events written by several processes: {writers}"
    assert len(re.findall(r"Key metric: val_dice", log)) == 1, "validation must run on rank 0 only"


def test_multi_gpu_sampler_gives_each_rank_its_own_subjects(tmp_path, tiny_dataset):
    """The DistributedSampler of multi_gpu_train.yaml, for both ranks of 2 (given explicitly: no process group):
    disjoint shards that together cover the training subjects, every epoch (reshuffled alike on every rank)."""
    from monai.bundle import ConfigParser

    shards = {}
    for rank in (0, 1):
        parser = ConfigParser()  # parsed, not initialised: no init_process_group
        parser.read_config([str(TRAIN), str(MULTI_GPU)])
        settings = {
            **TINY,
            "bundle_root": str(BUNDLE),
            "dataset_dir": str(tiny_dataset),
            "train#sampler#num_replicas": 2,
            "train#sampler#rank": rank,
        }
        for key, value in settings.items():
            parser[key] = value
        sampler, dataset = parser.get_parsed_content("train#sampler"), parser.get_parsed_content("train#dataset")
        assert parser.get_parsed_content("train#dataloader").sampler is sampler
        for epoch in (0, 1):
            sampler.set_epoch(epoch)  # MONAI's Workflow does this at every epoch start
            shards[rank, epoch] = [dataset.data[i]["id"] for i in sampler]
    for epoch in (0, 1):
        assert sorted(shards[0, epoch] + shards[1, epoch]) == ["T02", "T03"]  # val_ids: T01


def test_any_pair_training_draws_subject_and_atlas_pairs_and_validates_on_both(tmp_path):
    from conftest import make_tiny_dataset

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=4)
    configs = [
        str(TRAIN),
        str(BUNDLE / "configs" / "train_semisupervised.yaml"),
        str(BUNDLE / "configs" / "train_pairs.yaml"),
    ]
    wf = _workflow(
        tmp_path,
        dataset,
        configs,
        max_epochs=1,
        val_ids=["T01", "T02"],
        pairs_per_epoch=5,
        init_model_file=None,
        val_interval=1,
        augment_prob=0.0,
        self_repeats=2,
    )
    seen_ids, scored = [], []
    wf.trainer.add_event_handler(Events.ITERATION_COMPLETED, lambda e: seen_ids.extend(e.state.batch["id"]))
    wf.evaluator.add_event_handler(Events.ITERATION_COMPLETED, lambda e: scored.extend(e.state.batch["id"]))
    wf.run()
    wf.finalize()
    train = {"T03_to_T04", "T04_to_T03", "T03_to_atlas", "T04_to_atlas", "T03_to_T03", "T04_to_T04", "atlas_to_atlas"}
    assert len(seen_ids) == 5 and set(seen_ids) <= train
    # subject pairs + atlas pairs x atlas_repeats + every scan against itself x self_repeats
    assert len(wf.parser.get_parsed_content("train#dataset")) == 2 + 2 * 4 + 3 * 2
    assert sorted(scored) == ["T01_to_T02", "T01_to_atlas", "T02_to_T01", "T02_to_atlas"]
    assert (tmp_path / "ckpt" / "model_anypair.pt").is_file()
    assert (tmp_path / "ckpt" / "model_anypair.network.json").is_file()


def test_template_training_draws_pairs_in_both_spaces_and_never_a_validation_subject(tmp_path):
    """train_template.yaml: half the pairs from the template-space folder (another grid, resized to the same network
    grid), whose validation subjects are left out even when the folder has them; validation stays on LPBA40's."""
    from conftest import make_tiny_dataset

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=4)
    template = make_tiny_dataset(tmp_path / "template", num_subjects=4, shape=(24, 28, 20), seed=1)
    configs = [
        str(TRAIN),
        *(str(BUNDLE / "configs" / f"train_{name}.yaml") for name in ("semisupervised", "pairs", "template")),
    ]
    wf = _workflow(
        tmp_path,
        dataset,
        configs,
        max_epochs=1,
        val_ids=["T01", "T02"],
        pairs_per_epoch=24,
        init_model_file=None,
        val_interval=1,
        augment_prob=0.0,
        self_repeats=1,
        template_repeats=3,
        template_dataset_dir=str(template),
    )
    seen_ids, scored = [], []
    wf.trainer.add_event_handler(Events.ITERATION_COMPLETED, lambda e: seen_ids.extend(e.state.batch["id"]))
    wf.evaluator.add_event_handler(Events.ITERATION_COMPLETED, lambda e: scored.extend(e.state.batch["id"]))
    wf.run()
    wf.finalize()
    in_template = [i for i in seen_ids if i.startswith("template:")]
    assert len(seen_ids) == 24 and 0 < len(in_template) < 24  # both spaces drawn (P(one space only) = 2 * 0.5**24)
    assert not [i for i in seen_ids if "T01" in i or "T02" in i]
    template_pairs = wf.parser.get_parsed_content("template#dataset")
    assert len(template_pairs) == 2 + 2 * 3 + 3 * 1  # T03<->T04, each to the template x 3, 3 scans x self
    assert template_pairs[0]["moving"].shape[1:] == (32, 32, 32)  # the template's grid, resized for the network
    assert sorted(scored) == ["T01_to_T02", "T01_to_atlas", "T02_to_T01", "T02_to_atlas"]
    assert (tmp_path / "ckpt" / "model_template.pt").is_file()


def test_synthetic_heads_are_a_third_space_rendered_anew_with_their_structures_on_the_dice_slots(tmp_path):
    """train_synth.yaml: pairs drawn in all three spaces; a synthetic pair's images are renderings of its label maps
    (not the cached images) and its labels reach the loss as slots of label_values, nothing else."""
    import nibabel as nib
    import numpy as np
    from conftest import make_tiny_dataset

    dataset = make_tiny_dataset(tmp_path / "data", num_subjects=4)
    template = make_tiny_dataset(tmp_path / "template", num_subjects=4, shape=(24, 28, 20), seed=1)
    synth = make_tiny_dataset(tmp_path / "synth", num_subjects=3, shape=(28, 24, 20), seed=2)
    freesurfer = {21: 2, 22: 3, 181: 507}  # white matter, cortex, an extra-cerebral class (TINY_LABELS)
    for path in (synth / "labels").glob("*.nii.gz"):
        img = nib.load(path)
        data = np.asarray(img.dataobj).astype(np.int16)
        nib.save(
            nib.Nifti1Image(np.vectorize(lambda v: freesurfer.get(int(v), 0))(data).astype(np.int16), img.affine), path
        )
    configs = [
        str(TRAIN),
        *(str(BUNDLE / "configs" / f"train_{name}.yaml") for name in ("semisupervised", "pairs", "template", "synth")),
    ]
    wf = _workflow(
        tmp_path,
        dataset,
        configs,
        max_epochs=1,
        val_ids=["T01", "T02"],
        pairs_per_epoch=30,
        init_model_file=None,
        val_interval=1,
        augment_prob=0.0,
        self_repeats=1,
        template_repeats=3,
        template_dataset_dir=str(template),
        synth_dataset_dir=str(synth),
        synth_structures=[2, 3],
    )  # the tiny dataset has 3 slots, LPBA40 56 for the 32 of ASEG_LABELS
    seen = []
    wf.trainer.add_event_handler(
        Events.ITERATION_COMPLETED,
        lambda e: seen.append(
            (e.state.batch["id"][0], e.state.batch["moving"].clone(), e.state.batch["moving_label"].clone())
        ),
    )
    wf.run()
    wf.finalize()
    spaces = {i.split(":")[0] if ":" in i else "lpba" for i, _, _ in seen}
    assert len(seen) == 30 and spaces == {"lpba", "template", "synth"}  # P(a space missed) < 3 * 0.7**30
    slots = wf.parser.get_parsed_content("label_values")
    synth_pairs = wf.parser.get_parsed_content("synth#dataset")
    assert len(synth_pairs) == 3 * 2 + 3 * wf.parser["synth_self_repeats"]  # subject pairs, no atlas, self pairs
    for pair_id, moving, labels in seen:
        if not pair_id.startswith("synth:"):
            continue
        values = {int(v) for v in labels.unique()}
        assert values <= {0, *slots[:2]}, f"{pair_id}: white matter and cortex on the first two slots, got {values}"
        moving_id = pair_id.split(":")[1].split("_to_")[0]
        cached = next(
            synth_pairs.scans[k]["image"] for k, s in enumerate(synth_pairs.scans.data) if s["id"] == moving_id
        )
        assert moving.shape[2:] == cached.shape[1:] == (32, 32, 32)
        assert (moving[0] - cached).abs().max() > 0.05, f"{pair_id}: the cached image, not a rendering"
    assert (tmp_path / "ckpt" / "model_synth.pt").is_file()
