"""Evaluate's decoding workers (`inputs.load_groups`, num_workers > 0) start from a fork server, not as forks of
the stage's process: a forked worker shares that process's heap copy-on-write, so every page the forward then
wrote was first copied, one fault each (the CPU forward 30 % slower at 2 workers). Counted in page faults of a
fresh process while the workers are alive (no timing), against plain fork as the control."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = r"""
import resource, sys
import numpy as np
import torch
from pairedgta.evaluation.inputs import _identity, load_groups
heap = np.ones(64 * 2**20, dtype=np.uint8)  # the stage's memory, in use before the workers start
if sys.argv[1] == "fork":
    loader = torch.utils.data.DataLoader(list(range(8)), batch_size=None, num_workers=2, collate_fn=_identity,
                                         multiprocessing_context="fork")
else:
    loader = load_groups(list(range(8)), 2)
items = iter(loader)
first = [next(items), next(items)]  # both workers up (and blocked on their prefetch)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
heap[::4096] = 2  # the forward writing into memory it had before
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
assert first + list(items) == list(range(8))
print(faults)
"""


def faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, env=dict(os.environ))
    assert out.returncode == 0, out.stderr[-2000:]
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(sys.platform != "linux", reason="copy-on-write after fork as Linux does it")
def test_decoding_workers_do_not_share_the_stages_memory_copy_on_write():
    huge_pages = 64 * 2**20 // 2**21  # at least one fault per 2 MB (transparent huge pages), one per 4 kB without
    assert faults("fork") >= huge_pages  # forked workers: every page written is copied first
    assert faults("load_groups") < huge_pages // 4

