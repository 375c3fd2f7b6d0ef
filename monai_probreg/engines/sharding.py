"""Batch inference sharded over processes, and the merge of the shards into one output folder.

``bundle/configs/multi_gpu_inference.yaml``, passed after ``inference.yaml`` or ``evaluate.yaml`` and launched with
``torchrun`` (one process per GPU, or per few CPU cores), runs the same workflow on a slice of the subjects:

- rank ``r`` of ``W`` takes subjects ``r, r + W, r + 2W, ...`` of the sorted subject list
  (``monai.data.partition_dataset``, no shuffling, no padding: every subject is registered exactly once);
- it writes everything it would write into ``output_dir/shards/rank_<r>_of_<W>/`` (subject folders, README.txt,
  and for evaluate.yaml ``scores.csv`` / ``summary.json`` / ``scores.json`` of its slice), so ranks never share a file;
- when every rank is done (a barrier), rank 0 merges: :func:`merge_shards` moves the subject folders into
  ``output_dir`` (the layout of a single-process run), re-summarises the scores of all shards with
  :func:`~monai_probreg.engines.score_files.write_scores` (the same ``scores.csv`` and ``summary.json`` as one process would
  write: subjects in sorted order, means and stds over all of them), writes ``shards.json`` (who did what) and
  removes ``shards/``.

Processes started without torchrun (e.g. a job array setting ``RANK`` and ``WORLD_SIZE``) have no process group:
each writes its shard and stops; merge afterwards with ``python -m monai_probreg.engines.sharding OUTPUT_DIR``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch.distributed as dist
from monai.data import partition_dataset

from monai_probreg.data.screening import FAILED_FILE, InputFailures, read_failures
from monai_probreg.engines.outputs import OUTPUTS_README
from monai_probreg.engines.score_files import read_scores, write_scores
from monai_probreg.utils.files import write_text

__all__ = ["SHARDS_DIR", "MANIFEST", "process_rank", "shard_items", "shard_dir", "merge_shards", "finish", "main"]

SHARDS_DIR = "shards"
MANIFEST = "shards.json"
_SHARD_NAME = re.compile(r"^rank_(\d+)_of_(\d+)$")
_SCORE_FILES = (
    "scores.csv",
    "summary.json",
    "scores.json",
    "README.txt",
    FAILED_FILE,
)  # shard files that are merged, not moved


def process_rank() -> tuple[int, int]:
    """(rank, world size): from the initialised process group, else ``RANK`` / ``WORLD_SIZE`` (set by torchrun or
    by hand), else (0, 1)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    rank, world = int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))
    if not 0 <= rank < world:
        raise ValueError(f"expected 0 <= RANK < WORLD_SIZE, got RANK={rank}, WORLD_SIZE={world}")
    return rank, world


def shard_items(items: Sequence[Any], rank: int | None = None, world_size: int | None = None) -> list[Any]:
    """This process's slice of ``items``: every ``world_size``-th item from ``rank`` (defaults: :func:`process_rank`).
    The slices of all ranks are disjoint and cover ``items`` exactly once (a rank may get none)."""
    if rank is None or world_size is None:
        rank, world_size = process_rank()
    if not 0 <= rank < world_size:
        raise ValueError(f"expected 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
    items = list(items)
    if len(items) < world_size:  # partition_dataset refuses this; its partition would be the same
        return items[rank : rank + 1]
    return partition_dataset(items, num_partitions=world_size, shuffle=False, even_divisible=False)[rank]


def shard_dir(output_dir: str | os.PathLike, rank: int | None = None, world_size: int | None = None) -> str:
    """``output_dir/shards/rank_<r>_of_<W>``: where rank ``r`` of ``W`` writes."""
    if rank is None or world_size is None:
        rank, world_size = process_rank()
    return str(Path(output_dir) / SHARDS_DIR / f"rank_{rank}_of_{world_size}")


def _shards(output_dir: Path) -> tuple[int, dict[int, Path]]:
    """The shard folders of one complete run: (world size, {rank: folder}); a clear error otherwise."""
    found: dict[int, dict[int, Path]] = {}
    for folder in sorted((output_dir / SHARDS_DIR).glob("rank_*")):
        match = _SHARD_NAME.match(folder.name)
        if match and folder.is_dir():
            found.setdefault(int(match[2]), {})[int(match[1])] = folder
    if not found:
        raise FileNotFoundError(f"no shard folders {SHARDS_DIR}/rank_<r>_of_<W> in {str(output_dir)!r}")
    if len(found) > 1:
        raise ValueError(
            f"shards of runs with different world sizes {sorted(found)} in {str(output_dir / SHARDS_DIR)!r}; "
            "remove the stale ones"
        )
    ((world, shards),) = found.items()
    missing = sorted(set(range(world)) - set(shards))
    if missing:
        raise ValueError(
            f"expected {world} shards in {str(output_dir / SHARDS_DIR)!r}, got none from ranks {missing} "
            "(still running, or failed?)"
        )
    return world, shards


def _move_tree(source: Path, target: Path) -> None:
    """Move the files of ``source`` into ``target`` (replacing files of an earlier run, each atomically)."""
    for path in sorted(source.rglob("*")):
        if path.is_file():
            destination = target / path.relative_to(source)
            destination.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, destination)


def merge_shards(output_dir: str | os.PathLike) -> dict[str, Any]:
    """Merge the shards of a sharded run in ``output_dir`` (module docstring); returns the ``shards.json`` content.

    Raises FileNotFoundError / ValueError naming the folder when the shards are absent, mixed or incomplete."""
    out = Path(output_dir)
    world, shards = _shards(out)
    subjects: dict[str, list[str]] = {}
    rows, config, failed = [], {}, InputFailures()
    for rank in range(world):
        folder = shards[rank]
        failed.items += read_failures(folder / FAILED_FILE)
        subjects[str(rank)] = sorted(p.name for p in folder.iterdir() if p.is_dir())
        if (folder / "scores.json").is_file():
            shard_rows, shard_config = read_scores(folder / "scores.json")
            rows += shard_rows
            config = config or shard_config
    for rank in range(world):
        for name in subjects[str(rank)]:
            _move_tree(shards[rank] / name, out / name)
    if subjects and any(subjects.values()):
        write_text(out / "README.txt", OUTPUTS_README)
    summary = write_scores(out, sorted(rows, key=lambda row: row[0]), config, failed.items) if rows else None
    failed.finish(out, exit_on_failure=False)  # one failed.csv over all ranks (none if nothing failed)
    manifest = {
        "world_size": world,
        "subjects_per_rank": subjects,
        "num_subjects": len(rows) if rows else sum(len(v) for v in subjects.values()),
        "scored": bool(rows),
        "failed": failed.as_records(),
    }
    write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    shutil.rmtree(out / SHARDS_DIR)
    return {**manifest, "summary": summary}


def finish(output_dir: str | os.PathLike, merge: bool = True) -> None:
    """End of a sharded run: wait for every rank (when a process group exists), let rank 0 merge, tear down."""
    if not (dist.is_available() and dist.is_initialized()):
        return  # no process group: nothing to wait for; merge later with python -m monai_probreg.engines.sharding
    dist.barrier()
    if merge and dist.get_rank() == 0:
        manifest = merge_shards(output_dir)
        print(
            f"merged {manifest['world_size']} shards, {manifest['num_subjects']} subjects -> {output_dir}", flush=True
        )
    dist.barrier()  # nobody leaves (and reads output_dir) before the merge is complete
    dist.destroy_process_group()


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``python -m monai_probreg.engines.sharding OUTPUT_DIR`` merges the shards written there."""
    parser = argparse.ArgumentParser(prog="python -m monai_probreg.engines.sharding", description=main.__doc__)
    parser.add_argument("output_dir", help="the --output_dir of the sharded run (it holds shards/rank_<r>_of_<W>/)")
    args = parser.parse_args(argv)
    try:
        manifest = merge_shards(args.output_dir)
    except (FileNotFoundError, ValueError) as err:
        print(f"monai_probreg.engines.sharding: error: {err}", flush=True)
        return 1
    print(f"merged {manifest['world_size']} shards, {manifest['num_subjects']} subjects -> {args.output_dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
