"""A cached rerun imports no torch (issue 58: the rerun had grown from 2.7 s to 4.8 s since the stage keys began to
fingerprint the zoo's in-package weights through a module that imports torch): a rerun whose stages are all cached
builds no model, so torch (~1.2 s), transformers, seaborn and scipy.stats stay unimported (the cached main job takes
~5 s)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from pairedgta.testing.cli import OFFLINE, fast_overrides, run_cli

HEAVY = ("torch", "transformers", "seaborn", "scipy.stats")


@pytest.mark.slow
def test_a_cached_rerun_imports_no_torch(tmp_path):
    over = [a for a in fast_overrides(tmp_path) if a != "model=tiny_segformer"]
    # a zoo member (its weights fingerprinted in its keys) beside a hub-layout reference (transformers' SegFormer),
    # and the main job's figures (a cached plot stage reads none of their modules)
    over += ["models=[demo_ddrnet]"]
    first = run_cli(over, tmp_path)
    assert first.returncode == 0, first.stderr
    code = ("import sys; from pairedgta.__main__ import cli; sys.argv = ['pairedgta', *sys.argv[1:]]\n"
            "try:\n    cli()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            f"print('imported:', sorted(m for m in {HEAVY!r} if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code, *over, f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path,
                       capture_output=True, text=True, env={**__import__("os").environ, **OFFLINE}, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout + r.stderr
    assert "evaluate [demo_ddrnet]: cache hit" in out and out.count(": cache hit ") >= 4, out[-2000:]
    assert "imported: []" in r.stdout, r.stdout[-2000:]
