"""What the benchmark scripts share: default paths, the bundle's config parser, ``--override`` values, ANTs SyN.

Every script runs as ``python benchmarks/<name>.py``, which puts this folder on ``sys.path``, so the scripts import
this module plainly (``from common import bundle_parser``), never by editing ``sys.path``; the tests get the same
through pytest's ``pythonpath`` (pyproject.toml). Importing it costs the standard library only: monai, torch and
antspyx are imported by the functions that use them, so the light scripts (``experiments/ddp_scaling.py``) stay light.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch
    from monai.bundle import ConfigParser

__all__ = [
    "REPO",
    "SHARED_DATA",
    "DEFAULT_DATASET",
    "DEFAULT_NATIVE",
    "DEFAULT_OUT",
    "DEFAULT_REFINE_ITERATIONS",
    "ANTS_INSTALL_HINT",
    "bundle_parser",
    "parse_overrides",
    "ants_available",
    "ants_register",
    "run_command",
    "parse_variant",
    "write_report",
]

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"  # the data sets live next to the checkout, never inside it
DEFAULT_DATASET = SHARED_DATA / "lpba40"  # ../shared/data/lpba40 from the repository root (preprocessed, labelled)
DEFAULT_NATIVE = SHARED_DATA / "lpba40-native"  # the same subjects as scanned (native grids and headers)
DEFAULT_OUT = REPO / "benchmarks" / "results"
# refinement steps of the "ours + refinement" / default rows: the bundle's own (inference.yaml's refine_iterations,
# the one home of the default; read as text, so importing this module stays light)
DEFAULT_REFINE_ITERATIONS = int(
    re.search(
        r"^refine_iterations:\s*(\d+)",
        (REPO / "bundle" / "configs" / "inference.yaml").read_text(encoding="utf-8"),
        re.MULTILINE,
    ).group(1)
)
ANTS_INSTALL_HINT = "pip install -e '.[bench]'"  # antspyx is the optional extra "bench" (pyproject.toml)


# ------------------------------------------------------------------------------------------------ the command
def run_command(subcommand: str, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    """``monai-probreg SUBCOMMAND ARGS...`` in a fresh process of this interpreter, as a user runs it: (the finished
    process, stdout and stderr captured; its wall seconds from start to exit). RuntimeError naming the command and the
    tail of its stderr when it fails."""
    cmd = [sys.executable, "-m", "monai_probreg.cli.main", subcommand, *args]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-2000:]}")
    return done, wall


# ------------------------------------------------------------------------------------------------ configs
def bundle_parser(bundle_root: Path, names: Sequence[str], overrides: dict[str, Any] | None = None) -> ConfigParser:
    """The package's :func:`monai_probreg.fitting.stages.bundle_parser` (imported here, when called): the bundle's
    ``configs/<names>`` merged, each overlay on top of its base (evaluate.yaml over inference.yaml), ``bundle_root``
    and each ``overrides`` key set, as ``monai.bundle run`` does."""
    from monai_probreg.fitting.stages import bundle_parser as parser

    return parser(bundle_root, names, overrides)


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``--override KEY=VALUE`` arguments -> ``{KEY: VALUE}``, each VALUE read as YAML (``network_size=[80,96,80]``,
    ``network_size=null``).

    Raises:
        SystemExit: an item without ``=`` or with an empty key (the scripts' usage error).
    """
    import yaml

    overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(
                f"--override expects KEY=VALUE (VALUE in YAML, e.g. network_size=[80,96,80]); got {item!r}"
            )
        overrides[key] = yaml.safe_load(value)
    return overrides


# ------------------------------------------------------------------------------------------------ ANTs
def parse_variant(text: str) -> tuple[str, dict]:
    """``name=field:value,field:value`` -> (name, {field: value}) with bool (true/false)/int/float/str values."""
    name, _, fields = text.partition("=")
    out: dict = {}
    for item in filter(None, fields.split(",")):
        key, _, value = item.partition(":")
        if value.lower() in ("true", "false"):
            out[key] = value.lower() == "true"
            continue
        for cast in (int, float, str):
            try:
                out[key] = cast(value)
                break
            except ValueError:
                continue
    return name, out


def ants_available() -> tuple[bool, str]:
    """Whether antspyx imports: ``(True, its version)``, or ``(False, "antspyx not importable (<the ImportError>)")``
    for the script to report (rows say ``skipped: ...``, with :data:`ANTS_INSTALL_HINT` where the script gives it).

    Importing it here also loads it, so a later timed call does not pay for the import."""
    try:
        import ants
    except ImportError as err:
        return False, f"antspyx not importable ({err})"
    return True, getattr(ants, "__version__", "unknown")


def ants_register(
    moving: torch.Tensor, fixed: torch.Tensor, moving_label: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """ANTs SyN of ``moving`` onto ``fixed`` (both (1, 1, *S) on one grid) with antspyx defaults.

    Returns (moving labels warped nearest neighbour by ANTs (1, 1, *S) int16, the composed forward displacement
    (1, 3, *S) in our convention, registration wall time in s). The images get spacing 1, origin 0 and identity
    direction, so ITK's physical x, y, z are array axes 0, 1, 2 in voxels, and ITK's forward transform maps a fixed
    point x to the moving point x + u(x): exactly our pull-back ``warped[x] = moving[x + u(x)]``.
    """
    import ants
    import numpy as np
    import torch

    from monai_probreg.utils.tensors import plain_tensor

    def image(t: torch.Tensor) -> ants.ANTsImage:
        array = np.ascontiguousarray(plain_tensor(t)[0, 0].detach().cpu().numpy(), dtype=np.float32)
        return ants.from_numpy(array, origin=(0.0, 0.0, 0.0), spacing=(1.0, 1.0, 1.0), direction=np.eye(3))

    fixed_img, moving_img = image(fixed), image(moving)
    with tempfile.TemporaryDirectory(prefix="ants_syn_") as tmp:
        start = time.perf_counter()
        result = ants.registration(fixed_img, moving_img, type_of_transform="SyN", outprefix=f"{tmp}/tx_")
        runtime = time.perf_counter() - start
        fwd = result["fwdtransforms"]
        warped = ants.apply_transforms(fixed_img, image(moving_label.float()), fwd, interpolator="nearestNeighbor")
        # |J| from the whole forward transform (affine then SyN), on the same finite differences as ours
        field = ants.image_read(ants.apply_transforms(fixed_img, moving_img, fwd, compose=f"{tmp}/composed_"))
        displacement = torch.from_numpy(np.ascontiguousarray(field.numpy(), dtype=np.float32))  # (X, Y, Z, 3)
    labels = torch.from_numpy(np.rint(warped.numpy())).to(torch.int16)[None, None]
    return labels, displacement.movedim(-1, 0)[None], runtime


def write_report(out_dir: Path, name: str, result: dict[str, Any], lines: Sequence[str]) -> Path:
    """``result`` with the library versions and the table ``lines`` (``markdown``) written atomically to
    ``out_dir/name.json``, the table printed: how a benchmark reports."""
    import json

    from monai_probreg.utils.files import write_text
    from monai_probreg.utils.provenance import library_versions

    result = {**result, "versions": library_versions(), "markdown": "\n".join(lines)}
    path = write_text(Path(out_dir) / f"{name}.json", json.dumps(result, indent=2) + "\n")
    print(f"\n{result['markdown']}\n\nwrote {path}", flush=True)
    return path
