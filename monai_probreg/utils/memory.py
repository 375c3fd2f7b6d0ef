"""Keep freed CPU memory in the process, so large tensors reuse pages instead of faulting in fresh ones.

glibc's ``malloc`` serves every allocation above its mmap threshold (at most 32 MB) with a new ``mmap`` and gives
it back with ``munmap`` on ``free``. One registration at 160 x 192 x 224 allocates and frees many such buffers
(the full-resolution UNet activations, sampling grids, fields), so each call faults in their pages afresh, each
one zeroed by the kernel: a noticeable share of the call on a CPU (``benchmarks/speed_compare.py``'s "memory reuse
off" row against "ours, mean").
:func:`reuse_freed_memory` sets ``mallopt(M_MMAP_MAX, 0)`` (every allocation from the heap) and ``mallopt(M_TRIM_THRESHOLD, INT_MAX)`` (freed heap memory stays in the process), so
from the second pair on the same pages serve the same buffers. The arithmetic is untouched.

The cost: freed memory is never given back, and a heap only grows: arrays freed in another order than they were
made leave holes that later arrays of other sizes do not fit, so the resident memory climbs above what is in use,
stage after stage. :func:`trim_freed_memory` gives the free pages back (glibc's ``malloc_trim``) at points a
caller chooses: between stages that allocate differently (:func:`monai_probreg.registration.scan.register_scan`),
so that each starts from the memory in use, faults its pages in once and reuses them over its own repeated
allocations (the network's, the refinement's iterations), which is where reuse pays. It is a process-wide setting
of the C library, so the entry points turn it on (``monai-probreg``, the bundle's inference and evaluation:
``reuse_cpu_memory``), not the library calls; ``reuse_freed_memory(False)`` restores glibc's defaults for later
allocations. Written by hand with ``ctypes``: tcmalloc or jemalloc do the same but must be preloaded
(``LD_PRELOAD``) before Python starts. Elsewhere than glibc (macOS, musl) nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["reuse_freed_memory", "trim_freed_memory"]

# mallopt parameters and glibc's defaults (malloc.h, malloc/malloc.c)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_DEFAULT_TRIM_THRESHOLD, _DEFAULT_MMAP_MAX = 128 * 1024, 65536
_INT_MAX = 2**31 - 1


@functools.lru_cache(maxsize=1)
def _glibc():
    """glibc, or None on another C library."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()  # only glibc has it
    except (OSError, AttributeError, TypeError):
        return None
    return libc


def _glibc_mallopt():
    """glibc's ``mallopt``, or None on another C library."""
    libc = _glibc()
    if libc is None:
        return None
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def reuse_freed_memory(enable: bool = True) -> bool:
    """Keep freed memory for reuse (``enable``) or restore glibc's defaults; True if applied, False where the C
    library is not glibc (nothing changed)."""
    mallopt = _glibc_mallopt()
    if mallopt is None:
        return False
    mmap_max, trim = (0, _INT_MAX) if enable else (_DEFAULT_MMAP_MAX, _DEFAULT_TRIM_THRESHOLD)
    return bool(mallopt(_M_MMAP_MAX, mmap_max)) and bool(mallopt(_M_TRIM_THRESHOLD, trim))


def trim_freed_memory() -> bool:
    """Give the freed memory the process keeps back to the system now (glibc's ``malloc_trim(0)``: every whole free
    page of every arena, with or without :func:`reuse_freed_memory`); True if any was given back, False when none
    was or elsewhere than glibc."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(libc.malloc_trim(0))
