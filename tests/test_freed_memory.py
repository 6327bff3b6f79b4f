"""`reuse_freed_memory` (pairedgta/models/runtime.py): after it, a large block freed and allocated again comes
back without the kernel faulting in fresh pages, which had been half of a CPU forward's time. Counted in page
faults of a fresh process (no timing)."""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

PROBE = r"""
import resource, sys
import numpy as np
from pairedgta.models.runtime import reuse_freed_memory
if sys.argv[1] == "reuse":
    assert reuse_freed_memory() and reuse_freed_memory()  # once per process; the second call says the same
if sys.argv[1] == "opted out":
    assert not reuse_freed_memory()  # PAIREDGTA_REUSE_FREED_MEMORY=0: glibc's defaults
def faults_of_a_64_mb_block():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.empty(64 * 2**20, dtype=np.uint8)
    a[::4096] = 1  # touch every page
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults_of_a_64_mb_block()
print(faults_of_a_64_mb_block())
"""


def faults(mode: str) -> int:
    env = {**os.environ, "PAIREDGTA_REUSE_FREED_MEMORY": "0" if mode == "opted out" else "1"}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True, env=env)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_a_freed_block_is_reused_without_new_page_faults():
    huge_pages = 64 * 2**20 // 2**21  # at least one fault per 2 MB (transparent huge pages), one per 4 kB without
    assert faults("default") >= huge_pages  # glibc maps it afresh each time: the probe sees what it should
    assert faults("reuse") < huge_pages // 4
    assert faults("opted out") >= huge_pages
