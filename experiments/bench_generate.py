"""Per-phase generation cost per scene with the DeepGTAV client against the in-process test server.

Phases as in the paper's cost analysis (Algorithm 1): location sampling, semantic scene
construction (`prepare`), condition-wise rendering of the 3 x 3 grid (`render` per condition),
and overhead (descriptor building, pair validation, bookkeeping). The server only synthesises
pictures, so the numbers measure the client and the wire protocol, not the game.

    python experiments/bench_generate.py --scenes 5 --transport zmq
"""
from __future__ import annotations

import argparse
import csv
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pairedgta.conditions import Condition
from pairedgta.render.deepgtav import DeepGTAVRenderer
from pairedgta.testing.deepgtav_server import DeepGTAVTestServer
from pairedgta.scene.descriptor import DynamicObject, Location, SceneDescriptor
from pairedgta.scene.validation import validate_group

TIMES = {"Day": (12, 0), "Sunset": (19, 30), "Night": (23, 0)}
WEATHERS = {"Sunny": "EXTRASUNNY", "Rain": "RAIN", "Fog": "FOGGY"}
MODELS = {
    "car": ["blista", "asea", "premier", "tailgater"],
    "truck": ["mule", "benson"],
    "bus": ["bus"],
    "motorcycle": ["bati", "pcj"],
    "bicycle": ["bmx", "scorcher"],
    "person": ["a_m_y_hipster_01", "a_f_y_tourist_01", "a_m_m_business_01"],
}


def conditions() -> list[Condition]:
    return [
        Condition(f"{t}-{w}", t, gta, clock_hour=hm[0], clock_minute=hm[1])
        for t, hm in TIMES.items()
        for w, gta in WEATHERS.items()
    ]


def region_sampler(path: Path):
    from matplotlib.path import Path as PolygonPath

    cfg = yaml.safe_load(path.read_text())
    valid = [np.asarray(p, float) for p in cfg["valid"]]
    valid_paths = [PolygonPath(p) for p in valid]
    excluded = [PolygonPath(np.asarray(p, float)) for p in cfg["excluded"]]
    lo = np.min([p.min(axis=0) for p in valid], axis=0)
    hi = np.max([p.max(axis=0) for p in valid], axis=0)

    def sample(rng: np.random.Generator) -> tuple[float, float]:
        while True:
            xy = tuple(rng.uniform(lo, hi))
            if any(p.contains_point(xy) for p in valid_paths) and not any(p.contains_point(xy) for p in excluded):
                return float(xy[0]), float(xy[1])

    return sample


def objects(rng: np.random.Generator, d_min: float = 3.0) -> tuple[DynamicObject, ...]:
    out: list[DynamicObject] = []
    for _ in range(int(rng.integers(3, 9))):
        category = str(rng.choice(list(MODELS)))
        for _ in range(20):
            fwd, right = float(rng.uniform(8, 40)), float(rng.uniform(-6, 6))
            if all(np.hypot(fwd - o.forward, right - o.right) >= d_min for o in out):
                out.append(DynamicObject(category, str(rng.choice(MODELS[category])), fwd, right,
                                         heading=float(rng.choice([0.0, 180.0]))))
                break
    return tuple(out)


def paper_means() -> dict[str, float] | None:
    path = ROOT / "pairedgta" / "data" / "paper_generation_times.csv"
    if not path.exists():
        return None
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    keys = {"sampling": "scene_sampling_time", "construction": "semantic_scene_construction_time",
            "rendering": "condition_wise_rendering_time"}
    means = {k: statistics.fmean(float(r[c]) for r in rows) for k, c in keys.items()}
    # global_time is cumulative within a run (it restarts with each run): a scene's total is its
    # increment; overhead = total - pipeline
    ends = [float(r["global_time"]) for r in rows]
    totals = [b - a if b >= a else b for a, b in zip([0.0] + ends, ends)]
    means["overhead"] = statistics.fmean(totals) - statistics.fmean(float(r["pipeline_time"]) for r in rows)
    means["total"] = statistics.fmean(totals)
    return means


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=5)
    ap.add_argument("--transport", choices=("zmq", "tcp"), default="zmq")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--rate", type=float, default=60.0, help="frames per second the server streams")
    ap.add_argument("--settle-s", type=float, default=0.05, help="conf default is 1.0 (real game)")
    ap.add_argument("--settle-frames", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    sample = region_sampler(ROOT / "pairedgta" / "conf" / "region" / "los_santos.yaml")
    grid = conditions()
    rows = []
    t_session = time.perf_counter()
    with DeepGTAVTestServer(args.transport) as server:
        renderer = DeepGTAVRenderer(
            width=args.width, height=args.height, port=server.port, transport=args.transport, timeout_s=5.0,
            retries=1, backoff_s=0.1, settle_s=args.settle_s, settle_frames=args.settle_frames, rate=args.rate,
        )
        t0 = time.perf_counter()
        renderer.open()
        session_open = time.perf_counter() - t0
        print(f"{args.transport}, {args.width}x{args.height}, {len(grid)} conditions, settle_s={args.settle_s}, "
              f"rate={args.rate:g} Hz; connect {session_open:.3f} s")
        for k in range(args.scenes):
            t_start = time.perf_counter()
            x, y = sample(rng)
            t_sampled = time.perf_counter()
            descriptor = SceneDescriptor(
                scene_id=f"bench{k:04d}", seed=args.seed + k,
                location=Location(x, y, 30.0, float(rng.uniform(0, 360))), objects=objects(rng),
            )
            t_built = time.perf_counter()
            renderer.prepare(descriptor)
            t_constructed = time.perf_counter()
            results = {}
            per_condition = []
            for c in grid:
                tc = time.perf_counter()
                results[c.name] = renderer.render(descriptor, c)
                per_condition.append(time.perf_counter() - tc)
            t_rendered = time.perf_counter()
            check = validate_group({n: r.image for n, r in results.items()}, grid[0].name, descriptor,
                                   {n: r.state for n, r in results.items()})
            t_end = time.perf_counter()
            row = {
                "sampling": t_sampled - t_start,
                "construction": t_constructed - t_built,
                "rendering": t_rendered - t_constructed,
                "overhead": (t_built - t_sampled) + (t_end - t_rendered),
                "total": t_end - t_start,
            }
            rows.append(row)
            print(f"scene {k + 1} ({len(descriptor.objects)} objects at {x:.0f},{y:.0f}): "
                  f"sampling {row['sampling']:.4f} s, construction {row['construction']:.3f} s, "
                  f"rendering {row['rendering']:.3f} s ({min(per_condition):.3f}-{max(per_condition):.3f} s per "
                  f"condition), overhead {row['overhead']:.3f} s, total {row['total']:.3f} s, "
                  f"valid={check.ok} (min structure {min(check.structure.values()):.2f})")
        t0 = time.perf_counter()
        renderer.close()
        session_close = time.perf_counter() - t0
    print(f"close {session_close:.3f} s; whole run {time.perf_counter() - t_session:.2f} s")
    print("mean per scene: " + ", ".join(f"{k} {statistics.fmean(r[k] for r in rows):.3f} s" for k in rows[0]))
    paper = paper_means()
    if paper:
        print("paper (GTA V, RTX 2080): " + ", ".join(f"{k} {v:.3f} s" for k, v in paper.items()))


if __name__ == "__main__":
    main()
