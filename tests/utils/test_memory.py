"""reuse_freed_memory: after it, repeated large allocations fault in no new pages; the arithmetic is unchanged.
trim_freed_memory gives the pages kept back."""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import sys

import pytest
import torch

from monai_probreg import ProbRegNet
from monai_probreg.engines.registration import register_pair
from monai_probreg.utils.memory import reuse_freed_memory, trim_freed_memory

GLIBC = platform.libc_ver()[0] == "glibc"
BUFFER_ELEMENTS = 16 * 1024 * 1024  # 64 MB of float32: above glibc's largest mmap threshold (32 MB)
PAGES = BUFFER_ELEMENTS * 4 // resource.getpagesize()


FAULTS_SCRIPT = f"""
import resource, statistics, sys, torch
from monai_probreg.utils.memory import reuse_freed_memory
assert reuse_freed_memory(sys.argv[1] == "on")
for _ in range(2):  # the first buffers fault in either mode (the heap grows to its steady state)
    torch.empty({BUFFER_ELEMENTS}).fill_(1.0)
faults = []
for _ in range(7):
    start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    torch.empty({BUFFER_ELEMENTS}).fill_(1.0)  # touches every page
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start)
print(statistics.median(faults))
"""


def _faults_per_allocation(mode: str) -> float:
    """Median minor page faults per 64 MB buffer in a fresh interpreter (the setting is process-wide, and a long-lived
    test process has a heap of its own history)."""
    done = subprocess.run(
        [sys.executable, "-c", FAULTS_SCRIPT, mode],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr
    return float(done.stdout.split()[-1])


@pytest.fixture
def restore_defaults():
    yield
    reuse_freed_memory(False)


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_freed_pages_are_reused_only_when_enabled():
    assert _faults_per_allocation("off") > 0.5 * PAGES  # glibc's default: mmap per buffer, every page faulted again
    assert _faults_per_allocation("on") < 0.01 * PAGES


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_registration_is_bitwise_the_same_with_memory_reuse(restore_defaults):
    torch.manual_seed(0)
    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    moving, fixed = torch.rand(1, 1, 16, 16, 16), torch.rand(1, 1, 16, 16, 16)
    reuse_freed_memory(False)
    plain = register_pair(network, moving, fixed)
    reuse_freed_memory(True)
    reused = register_pair(network, moving, fixed)
    assert torch.equal(plain.displacement, reused.displacement) and torch.equal(plain.warped, reused.warped)


def test_other_c_libraries_are_left_alone(monkeypatch):
    import monai_probreg.utils.memory as memory

    monkeypatch.setattr(memory, "_glibc_mallopt", lambda: None)  # what the lookup gives on macOS or musl
    assert memory.reuse_freed_memory() is False


TRIM_SCRIPT = f"""
import torch
from monai_probreg.utils.memory import reuse_freed_memory, trim_freed_memory

def resident() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1])  # pages

assert reuse_freed_memory()
kept = torch.empty(1024)  # allocated after the buffers: the heap's top stays in use, the buffers' pages in a hole
buffers = [torch.empty({BUFFER_ELEMENTS}).fill_(1.0) for _ in range(4)]
kept = torch.empty(1024)
before = resident()
del buffers
freed = resident()
trimmed = trim_freed_memory()
print(before - freed, freed - resident(), int(trimmed))
"""


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_trim_gives_back_the_pages_reuse_keeps():
    """With reuse on, freed buffers stay resident (in a hole of the heap: no top to trim); trim_freed_memory gives
    their pages back."""
    done = subprocess.run(
        [sys.executable, "-c", TRIM_SCRIPT], capture_output=True, text=True, timeout=120, env=os.environ.copy()
    )
    assert done.returncode == 0, done.stderr
    kept_by_free, given_back, trimmed = (int(v) for v in done.stdout.split())
    assert kept_by_free < 0.01 * 4 * PAGES  # freeing alone keeps them (reuse)
    assert given_back > 0.9 * 4 * PAGES
    assert trimmed == 1


def test_trim_elsewhere_than_glibc_does_nothing(monkeypatch):
    import monai_probreg.utils.memory as memory

    monkeypatch.setattr(memory, "_glibc", lambda: None)
    assert trim_freed_memory() is False
