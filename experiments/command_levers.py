"""The command line's speed levers, each against what it replaced, side by side in one run on synthetic inputs.

No dataset needed: every input is made here (seeded) at the sizes of a real registration (a 1 mm atlas grid of
160 x 192 x 160, a native scan's 256 x 124 x 256 moving grid). Rows:

- ``gzip``: a float32 displacement field of the moving grid's size (98 MB) compressed by zlib level 1 (Python's
  ``gzip``) and by ISA-L level 1 (``isal``, :mod:`monai_probreg.spatial.nifti_write`): seconds and compressed MB;
- ``point transform``: a 4 x 4 applied to the atlas grid's 4.9 million points by numpy's ``points @ M.T + t`` and by
  :func:`monai_probreg.spatial.physical.apply_affine` (one ``torch.addmm``);
- ``jacobian``: the determinant of a displacement on the atlas grid by ``torch.linalg.det`` on the stacked 3 x 3
  field and by :func:`monai_probreg.metrics.jacobian.jacobian_determinant` (cofactors on views of the gradients);
- ``exit``: a fresh process importing the command's modules, leaving normally (Python tears the modules down) and
  with ``os._exit`` (:func:`monai_probreg.cli.main.run`);
- ``torch._dynamo``: a fresh process importing torch, without and with ``torch._dynamo`` (what the first
  ``torch.optim.LBFGS`` of a process imports);
- ``nearest labels``: a Fortran-ordered label map of the moving grid (as nibabel reads NIfTI) sampled at the atlas
  grid's points slab by slab (:func:`~monai_probreg.spatial.physical.row_slabs`), as the compose stage samples the
  labels: with a C-ordered copy of the map per slab (what :func:`~monai_probreg.spatial.point_sampling.sample_nearest`
  made before it read both orders in place) and without; the same values.

Each in-process row is the best of ``--repeats`` after one warm-up; each process row the median of ``--repeats``.
Prints a table and writes ``OUT_DIR/command_levers.json``.

    python experiments/command_levers.py --threads 2   # -> experiments/results/command_levers.json
"""

from __future__ import annotations

import argparse
import gzip
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from isal import igzip

from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.spatial.nifti_write import GZIP_LEVEL
from monai_probreg.spatial.physical import apply_affine, grid_points, mapped_index, row_slabs
from monai_probreg.spatial.point_sampling import sample_nearest
from monai_probreg.spatial.volume_io import Volume
from monai_probreg.utils.files import write_text
from monai_probreg.utils.provenance import library_versions

RESULTS = Path(__file__).resolve().parent / "results"  # experiments/results, next to this script
ATLAS_SHAPE = (160, 192, 160)
MOVING_SHAPE = (256, 124, 256)
SEED = 0


def best_of(function: Callable[[], object], repeats: int) -> float:
    function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def process_seconds(code: str, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def gzip_row(repeats: int) -> dict:
    rng = np.random.default_rng(SEED)
    field = (rng.normal(size=(*MOVING_SHAPE, 3)) * 3.0).astype(np.float32).tobytes()
    return {
        "before": best_of(lambda: gzip.compress(field, 1, mtime=0), repeats),
        "after": best_of(lambda: igzip.compress(field, GZIP_LEVEL, mtime=0), repeats),
        "megabytes": {
            "raw": len(field) / 1e6,
            "zlib": len(gzip.compress(field, 1, mtime=0)) / 1e6,
            "isal": len(igzip.compress(field, GZIP_LEVEL, mtime=0)) / 1e6,
        },
    }


def point_transform_row(repeats: int) -> dict:
    matrix = np.eye(4)
    matrix[:3, :3] = [[0.98, 0.1, 0.0], [-0.1, 0.98, 0.05], [0.0, -0.05, 1.02]]
    matrix[:3, 3] = [5.0, -10.0, 20.0]
    points = grid_points(ATLAS_SHAPE, np.diag([-1.0, -1.0, 1.0, 1.0]))
    before = best_of(lambda: points @ matrix[:3, :3].T + matrix[:3, 3], repeats)
    after = best_of(lambda: apply_affine(matrix, points), repeats)
    difference = float(np.abs(apply_affine(matrix, points) - (points @ matrix[:3, :3].T + matrix[:3, 3])).max())
    return {"before": before, "after": after, "max_difference_mm": difference}


def jacobian_row(repeats: int) -> dict:
    ddf = torch.randn(1, 3, *ATLAS_SHAPE, generator=torch.Generator().manual_seed(SEED)) * 0.3

    def stacked_det() -> torch.Tensor:
        grads = torch.gradient(ddf, dim=(2, 3, 4))
        jac = torch.stack(grads, dim=2) + torch.eye(3).view(1, 3, 3, 1, 1, 1)
        return torch.linalg.det(jac.movedim((1, 2), (-2, -1)))

    difference = float((stacked_det() - jacobian_determinant(ddf)).abs().max())
    return {
        "before": best_of(stacked_det, repeats),
        "after": best_of(lambda: jacobian_determinant(ddf), repeats),
        "max_difference": difference,
    }


def exit_row(repeats: int) -> dict:
    imports = "import monai_probreg.registration.scan"
    return {
        "before": process_seconds(imports, repeats),
        "after": process_seconds(f"{imports}; import os, sys; sys.stdout.flush(); os._exit(0)", repeats),
    }


def dynamo_row(repeats: int) -> dict:
    return {
        "before": process_seconds("import torch", repeats),
        "after": process_seconds("import torch, torch._dynamo", repeats),
    }


def nearest_labels_row(repeats: int) -> dict:
    rng = np.random.default_rng(SEED)
    labels = np.asfortranarray(rng.integers(0, 60, MOVING_SHAPE, dtype=np.uint8))
    moving_grid, atlas_grid = np.diag([0.94, 1.5, 0.94, 1.0]), np.eye(4)
    moving_grid[:3, 3] = [-120.0, -93.0, -120.0]
    atlas_grid[:3, 3] = [-80.0, -96.0, -80.0]
    slabs = [
        (rows, mapped_index((rows.stop - rows.start, *ATLAS_SHAPE[1:]), atlas_grid, moving_grid, first_row=rows.start))
        for rows in row_slabs(ATLAS_SHAPE)
    ]

    def sample(copy_per_slab: bool) -> np.ndarray:
        out = np.empty(ATLAS_SHAPE, np.uint8)
        for rows, index in slabs:
            array = np.ascontiguousarray(labels) if copy_per_slab else labels
            out[rows] = sample_nearest(Volume(array, moving_grid), None, index=index)
        return out

    return {
        "before": best_of(lambda: sample(True), repeats),
        "after": best_of(lambda: sample(False), repeats),
        "same_values": bool(np.array_equal(sample(True), sample(False))),
    }


ROWS = {
    "gzip (98 MB field): zlib 1 -> ISA-L 1": gzip_row,
    "point transform (4.9 M points): numpy -> torch.addmm": point_transform_row,
    "jacobian (160x192x160): linalg.det -> cofactors": jacobian_row,
    "process exit after the command's imports: teardown -> os._exit": exit_row,
    "import torch -> + torch._dynamo (first LBFGS)": dynamo_row,
    "nearest labels (Fortran-ordered 256x124x256, by slab): a copy per slab -> in place": nearest_labels_row,
}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats per row (default: %(default)s)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="where command_levers.json goes")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = {}
    for name, measure in ROWS.items():
        rows[name] = measure(args.repeats)
        print(f"{name}: {rows[name]['before']:.3f} s -> {rows[name]['after']:.3f} s", flush=True)
    lines = ["| lever | before (s) | after (s) | ratio |", "|---|---|---|---|"]
    lines += [
        f"| {name} | {r['before']:.3f} | {r['after']:.3f} | {r['before'] / r['after']:.2f} |"
        for name, r in rows.items()
    ]
    table = "\n".join(lines)
    result = {
        "threads": args.threads,
        "repeats": args.repeats,
        "rows": rows,
        "markdown": table,
        "versions": {**library_versions(), "platform": platform.platform()},
    }  # write_text creates the folder
    path = write_text(args.out_dir / "command_levers.json", json.dumps(result, indent=2) + "\n")
    print(f"\n{table}\n\nwrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
