"""Untrusted weights and configs: a pickle that tries to run code is refused by every loader and its code never
runs; every torch.load in the package is weights_only=True; our bundle configs read nothing from the environment
beyond what they need; the docs say that bundle configs run Python.
"""

from __future__ import annotations

import contextlib
import io
import os
import pickle
import re
import zipfile
from pathlib import Path

import pytest
import torch
from conftest import FIXED_LPS, asymmetric_phantom, save_lps, tiny_bundle

from monai_probreg import ProbRegNet
from monai_probreg.cli.main import main
from monai_probreg.engines.checkpoints import attach_resume
from monai_probreg.registration.model import load_model
from monai_probreg.utils.errors import UntrustedFileError
from monai_probreg.weights.loading import load_weights

ROOT = Path(__file__).resolve().parents[2]


class Payload:
    """Unpickling this runs ``os.system('touch <marker>')``: the classic malicious checkpoint."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


@pytest.fixture
def evil(tmp_path: Path):
    """(torch zip checkpoint, plain pickle, marker): both files hold a real state dict plus the payload."""
    marker = tmp_path / "code_ran"
    state = {**ProbRegNet(network_size=(16, 16, 16)).state_dict(), "extra": Payload(marker)}
    torch.save(state, tmp_path / "evil.pt")
    with (tmp_path / "evil.pkl").open("wb") as f:
        pickle.dump(state, f)
    return tmp_path / "evil.pt", tmp_path / "evil.pkl", marker


@pytest.mark.parametrize("kind", [0, 1], ids=["torch-zip", "plain-pickle"])
def test_load_weights_refuses_code(evil, kind):
    path, marker = evil[kind], evil[2]
    with pytest.raises(UntrustedFileError) as info:
        load_weights(ProbRegNet(network_size=(16, 16, 16)), path)
    message = str(info.value)
    assert path.name in message and "refused" in message and "nothing in it was run" in message
    assert "posix.system" in message or "GLOBAL" in message or "Unsupported" in message  # what it asked for
    assert not marker.exists()


def test_bundle_model_and_command_line_refuse_code(evil, tmp_path):
    path, _, marker = evil
    bundle = tiny_bundle(tmp_path / "bundle", ROOT / "bundle")
    with pytest.raises(UntrustedFileError, match="--model-file .*evil.pt.*refused"):
        load_model(bundle, model_file=path)
    image, _ = asymmetric_phantom()
    fixed = save_lps(tmp_path / "fixed.nii.gz", image, FIXED_LPS)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(
            [
                "register",
                "--moving",
                str(fixed),
                "--fixed",
                str(fixed),
                "--out",
                str(tmp_path / "out"),
                "--bundle-root",
                str(bundle),
                "--model-file",
                str(path),
                "--threads",
                "1",
            ]
        )
    assert rc == 1 and "refused" in err.getvalue() and "Traceback" not in err.getvalue()
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_training_resume_refuses_code(evil, tmp_path):
    path, _, marker = evil
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    torch.save({"model": {}}, ckpt / "train_state_checkpoint_epoch=1.pt")  # an older, honest one
    os.replace(path, ckpt / "train_state_checkpoint_epoch=2.pt")  # the newest: never skipped past silently
    os.utime(ckpt / "train_state_checkpoint_epoch=2.pt")  # (the fixture wrote it first; latest = newest mtime)
    from ignite.engine import Engine

    with pytest.raises(UntrustedFileError, match="training checkpoint .*epoch=2.pt.*refused"):
        attach_resume(Engine(lambda e, b: None), str(ckpt), {"model": torch.nn.Linear(1, 1)})
    assert not marker.exists()


def test_bundle_inference_refuses_code(evil, tmp_path, tiny_dataset, bundle, single_thread):
    from monai.bundle import ConfigWorkflow

    path, _, marker = evil
    wf = ConfigWorkflow(
        config_file=str(bundle / "configs" / "inference.yaml"),
        workflow_type="infer",
        logging_file=False,
        bundle_root=str(bundle),
        dataset_dir=str(tiny_dataset),
        output_dir=str(tmp_path / "out"),
        network_size=[16, 16, 16],
        num_workers=0,
        model_file=str(path),
    )
    wf.initialize()
    with pytest.raises(Exception) as info:
        wf.run()
    chain, error = [], info.value
    while error is not None:
        chain.append(error)
        error = error.__cause__ or error.__context__
    assert any(isinstance(e, UntrustedFileError) for e in chain), [str(e)[:200] for e in chain]
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_the_payload_is_live(evil):
    """Guard against a test that passes because the payload does nothing: unpickled without restriction it runs.
    (Shown with ``pickle.load`` on the plain-pickle twin, so the project never calls ``torch.load`` unsafely; the
    torch zip holds the same ``os.system`` reduce in its pickle stream.)"""
    zipped, plain, marker = evil
    with zipfile.ZipFile(zipped) as archive:
        stream = archive.read(next(n for n in archive.namelist() if n.endswith("data.pkl")))
    assert b"system" in stream and str(marker).encode() in stream
    with plain.open("rb") as f:
        pickle.load(f)  # noqa: S301 - deliberately, on the test's own file
    assert marker.exists()


def _calls(text: str, name: str) -> list[str]:
    """The argument text of every ``name(...)`` call in ``text`` (balanced parentheses)."""
    found = []
    for match in re.finditer(re.escape(name) + r"\(", text):
        depth, i = 1, match.end()
        while depth and i < len(text):
            depth += {"(": 1, ")": -1}.get(text[i], 0)
            i += 1
        found.append(text[match.end() : i - 1])
    return found


def test_every_torch_load_is_weights_only():
    sources = [
        *(ROOT / "monai_probreg").rglob("*.py"),
        *(ROOT / "benchmarks").rglob("*.py"),
        *(ROOT / "experiments").rglob("*.py"),
        *(ROOT / "bundle" / "configs").glob("*.yaml"),
    ]
    calls = [(p.name, args) for p in sources for args in _calls(p.read_text(), "torch.load")]
    assert calls, "expected at least one torch.load (inference.load_weights goes through safe_torch_load)"
    unsafe = [(name, args) for name, args in calls if "weights_only=True" not in args]
    assert not unsafe, unsafe
    assert not [p.name for p in sources if re.search(r"\bpickle\.loads?\(|\bdill\.|joblib\.load", p.read_text())]


# `$` expressions of our configs may evaluate Python: nothing may reach the network, run programs or read files
# or environment variables beyond those torchrun sets for the multi-GPU configs (which device, launched or not).
TORCHRUN_VARIABLES = {"LOCAL_RANK", "MASTER_ADDR"}
FORBIDDEN = re.compile(
    r"subprocess|os\.system|os\.popen|urllib|requests|http|socket|download|\beval\(|\bexec\("
    r"|__import__|\bopen\(|getenv|pickle|shutil"
)


def test_bundle_configs_read_nothing_they_do_not_need():
    for config in sorted((ROOT / "bundle" / "configs").glob("*.yaml")):
        expressions = [re.sub(r"\s+#\s.*$", "", line) for line in config.read_text().splitlines() if "$" in line]
        for line in expressions:
            assert not FORBIDDEN.search(line), f"{config.name}: {line.strip()}"
            reads = re.findall(r"os\.environ(?:\.get\(|\[)\s*['\"](\w+)['\"]", line)
            reads += re.findall(r"['\"](\w+)['\"]\s+(?:not\s+)?in\s+os\.environ", line)
            assert line.count("os.environ") == len(reads), f"{config.name}: {line.strip()}"  # only by literal name
            assert set(reads) <= TORCHRUN_VARIABLES, f"{config.name} reads {reads}"


@pytest.mark.parametrize("doc", ["README.md", "bundle/docs/README.md"])
def test_docs_say_configs_run_python(doc):
    text = (ROOT / doc).read_text()
    assert "run only bundles you trust" in text.lower() and "`_target_`" in text and "weights_only=True" in text
