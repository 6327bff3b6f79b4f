"""Generate end to end through the CLI against the DeepGTAV protocol test server (2 scenes x 9
conditions), and sharding over two renderer endpoints giving the same scenes as one."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from PIL import Image

from pairedgta.testing.cli import run_cli
from pairedgta.testing.deepgtav_server import DeepGTAVTestServer

pytestmark = pytest.mark.slow  # end to end: the CLI or the stage graph on every test

PAPER_COLUMNS = ["location_id", "x", "y", "scene_sampling_time", "semantic_scene_construction_time",
                 "condition_wise_rendering_time", "pipeline_time", "overhead_time"]


def generate(tmp_path, cache, extra):
    args = ["renderer=deepgtav", "region=los_santos", "stages=[generate]", "generate.num_scenes=2",
            f"cache_dir={cache}", "tracking.enabled=false", "renderer.width=64", "renderer.height=36",
            "renderer.settle_s=0.0", "renderer.settle_frames=0", "renderer.timeout_s=5", *extra]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return next(p for p in (cache / "generate").iterdir() if not p.name.startswith("."))


def test_generate_cli_against_the_test_server_and_sharding(tmp_path):
    with DeepGTAVTestServer("zmq") as a, DeepGTAVTestServer("zmq") as b:
        one = generate(tmp_path, tmp_path / "c1", [f"renderer.port={a.port}", "renderer.transport=zmq"])
        index = json.loads((one / "index.json").read_text())
        assert len(index["scenes"]) == 2 and len(index["conditions"]) == 9
        scene = one / "scenes" / "00000"
        pngs = sorted(p.name for p in scene.glob("*.png"))
        assert len(pngs) == 9 and (scene / "descriptor.json").is_file()
        with open(one / "timings.csv") as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == 2 and set(PAPER_COLUMNS) <= set(rows[0])
        assert all(float(r["pipeline_time"]) > 0 for r in rows)
        with open(one / "validation.csv") as f:
            assert all(r["ok"] == "True" for r in csv.DictReader(f))
        two = generate(tmp_path, tmp_path / "c2", [
            "generate.workers=2", "renderer.transport=zmq",
            f"generate.endpoints=[{{port:{a.port}}},{{port:{b.port}}}]",
        ])
        assert one.name == two.name  # where scenes run is not part of what they are
        for sid in ("00000", "00001"):
            assert (one / "scenes" / sid / "descriptor.json").read_text() == (two / "scenes" / sid / "descriptor.json").read_text()
            day = [np.asarray(Image.open(d / "scenes" / sid / "Day-EXTRASUNNY.png")) for d in (one, two)]
            assert np.array_equal(*day)
