"""Atomic files: every file the package writes appears whole or not at all.

A writer writes to a hidden temporary next to the target, ``.<name>.<12 hex>.tmp<suffixes>`` (same folder, so the
final ``os.replace`` is atomic, and the same suffixes, so ``itk.imwrite`` and nibabel still pick the format), renames
it onto the target when complete and deletes it on any error. :data:`PARTIAL_FILE` matches exactly those temporary
names (what a kill mid-write can leave) and :func:`remove_partial_files` clears them: this module is the one home of
that naming.
"""

from __future__ import annotations

import logging
import os
import re
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "PARTIAL_FILE",
    "IMAGE_SUFFIXES",
    "atomic_write",
    "write_text",
    "parallel_writes",
    "remove_partial_files",
    "file_stem",
]

_TOKEN_HEX = 12  # random hex digits in a temporary name
PARTIAL_FILE = re.compile(rf"\..+\.[0-9a-f]{{{_TOKEN_HEX}}}\.tmp(\.[^.]+)*")
_LOG = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")  # image files we read, longest first


def _temporary_name(path: Path) -> Path:
    return path.parent / f".{path.name}.{uuid.uuid4().hex[:_TOKEN_HEX]}.tmp{''.join(path.suffixes)}"


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Write a file atomically with any writer: ``write(tmp)`` on a temporary name next to ``path`` that keeps
    its suffixes, then ``os.replace`` onto ``path``; the temporary is deleted if ``write`` raises. The parent folder
    is created if needed; permissions follow the umask."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_name(path)
    try:
        write(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file atomically."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


@contextmanager
def parallel_writes(threads: int) -> Iterator[Callable[[Callable[[], object]], None]]:
    """Yield ``submit(writer)``: each writer (a call that writes one file) runs in a pool of ``threads`` threads
    while the body goes on (e.g. drawing a figure); on leaving, every writer has finished, and the first writer's
    error is raised. With ``threads <= 1`` each writer runs at once, in order. Worth it where writing releases the GIL
    (compression, :mod:`monai_probreg.spatial.nifti_write`). An error in the body still waits for the writers, so
    none is left writing into a folder that the caller then removes."""
    if threads <= 1:
        yield lambda write: write()
        return
    futures: list[Future] = []
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="write") as pool:
        yield lambda write: futures.append(pool.submit(write))
    for future in futures:
        future.result()


def remove_partial_files(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporaries that interrupted atomic writes left in ``folder`` (only names matching
    :data:`PARTIAL_FILE`); returns them."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = [p for p in folder.iterdir() if p.is_file() and PARTIAL_FILE.fullmatch(p.name)]
    for path in removed:
        path.unlink(missing_ok=True)
        _LOG.warning(f"removed {path.name}: a file whose writing was interrupted")
    return removed


def file_stem(path: str | os.PathLike) -> str:
    """A file's name without its image suffix (``S01.nii.gz`` -> ``S01``; any of :data:`IMAGE_SUFFIXES`), else without
    its last suffix: the subject id of a scan file."""
    name = Path(path).name
    for suffix in IMAGE_SUFFIXES:
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return Path(name).stem
