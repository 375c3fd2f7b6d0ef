"""What a result needs to be reproduced: the file hash of the weights and the versions of the libraries that
computed it. Recorded in the command's ``summary.json`` (``reproducibility``) and the calibration sidecars.

Reproducible means: the same inputs, options and seed on the same machine with the same versions give the same
files. Across CPUs (other SIMD paths in oneDNN/ITK), CPU against GPU, or other library versions, results differ in the
last digits of floating point arithmetic, and so may a voxel's label at a boundary.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from importlib import metadata

__all__ = ["file_sha256", "library_versions"]

_LIBRARIES = ("monai-probreg", "torch", "monai", "itk", "numpy", "nibabel", "scipy")
_CHUNK_BYTES = 1 << 20


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK_BYTES), b""):
            digest.update(block)
    return digest.hexdigest()


def library_versions() -> dict[str, str | None]:
    """Installed versions of Python, the libraries in the computation (None: not installed) and the CPU architecture."""
    import monai_probreg  # the package's version (as registration.summary reads it); imported here: the root imports us

    versions: dict[str, str | None] = {"python": sys.version.split()[0], "machine": platform.machine()}
    for name in _LIBRARIES:
        if name == "monai-probreg":  # the code that ran: an editable install's metadata keeps its install-time version
            versions[name] = monai_probreg.__version__
            continue
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions
