"""2D corruptions as conditions (issue 71): C-<corruption>-<severity> from the clean image through imagecorruptions,
byte for byte the library's own output, seeded per scene and condition, paired by construction (the clean truth),
cached by config without moving the rendered sets' keys, bad input one line before any stage writes, and the
Cityscapes-C / Michaelis et al. summaries against a hand count."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf
from PIL import Image

from pairedgta import corruptions
from pairedgta.conditions import build_condition_grid
from pairedgta.errors import ConfigError
from pairedgta import corruption_summary as cs
from pairedgta.testing.cli import base_overrides, compose_cfg, run_cli

# the `corruptions` extra (in .[dev]); through the wrapper, which supplies pkg_resources where setuptools has none
imagecorruptions = corruptions.library()


def street(h: int = 48, w: int = 64) -> np.ndarray:
    """A deterministic image with structure: gradients and a block (not flat, not noise)."""
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 255 // w, y * 255 // h, (x + y) * 255 // (w + h)], axis=-1).astype(np.uint8)
    img[h // 4: h // 2, w // 3: w // 2] = (200, 30, 60)
    return img


def png(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


# -- the library and the wrapper -------------------------------------------------------------------------------------


def test_the_names_and_subsets_are_the_librarys():
    lib = corruptions.library()
    for subset, names in corruptions.SUBSETS.items():
        assert tuple(lib.get_corruption_names(subset)) == names, subset


@pytest.mark.parametrize("name", ["brightness", "contrast"])
def test_a_deterministic_corruption_is_the_librarys_output_byte_for_byte(name):
    img = street()
    for severity in (1, 3, 5):
        ours = corruptions.corrupt(img, name, severity, seed=123)
        theirs = imagecorruptions.corrupt(img.copy(), corruption_name=name, severity=severity)
        assert ours.dtype == np.uint8 and ours.shape == img.shape
        assert ours.tobytes() == np.asarray(theirs, np.uint8).tobytes()
        assert not np.array_equal(ours, img)  # it did corrupt


def test_seeded_the_same_image_every_time_and_the_global_generator_is_left_as_it_was():
    img = street()
    np.random.seed(7)
    before = np.random.get_state()[1].copy()
    a = corruptions.corrupt(img, "gaussian_noise", 3, seed=11)
    assert np.array_equal(np.random.get_state()[1], before)  # restored
    np.random.seed(99)  # another global state: no influence on the result
    b = corruptions.corrupt(img, "gaussian_noise", 3, seed=11)
    c = corruptions.corrupt(img, "gaussian_noise", 3, seed=12)
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()
    seeds = {corruptions.seed_for(0, s, n) for s in ("00000", "00001") for n in ("C-fog-1", "C-fog-2")}
    assert len(seeds) == 4  # distinct per scene and condition


def test_glass_blur_and_gaussian_blur_run_on_current_scikit_image():
    """The library's skimage call with `multichannel` (removed in scikit-image 0.21) goes through the wrapper's fix."""
    img = street(32, 32)
    for name in ("glass_blur", "gaussian_blur"):
        out = corruptions.corrupt(img, name, 1, seed=0)
        assert out.shape == img.shape and not np.array_equal(out, img)


# -- conditions and config -------------------------------------------------------------------------------------------


def grid_of(overrides: list[str]):
    cfg = OmegaConf.to_container(compose_cfg(overrides), resolve=True)
    return build_condition_grid(cfg["conditions"])


def test_the_corruption_set_names_each_corruption_and_severity_a_condition_of_the_clean_one():
    grid = grid_of(["conditions=corruptions"])
    assert grid.reference == "Day-EXTRASUNNY" and len(grid) == 1 + 15 * 5
    assert [c.name for c in grid.rendered] == ["Day-EXTRASUNNY"]
    fog = grid["C-fog-3"]
    assert (fog.corruption, fog.severity, fog.source) == ("fog", 3, "Day-EXTRASUNNY")
    assert np.isnan(fog.transmittance(np.array([1.0, 50.0]))).all()  # no depth, no transmittance
    picked = grid_of(["conditions=corruptions", "conditions.corruptions.only=[fog,brightness]",
                      "conditions.corruptions.severities=[1,3,5]"])
    assert picked.adverse == [f"C-{n}-{s}" for n in ("fog", "brightness") for s in (1, 3, 5)]  # the library's order
    mixed = grid_of(["conditions=paper_corruptions", "conditions.corruptions.only=[snow]"])
    assert len(mixed) == 9 + 5 and "Night-RAIN" in mixed.names and "C-snow-5" in mixed.names
    assert corruptions.parse_name("C-zoom_blur-2") == ("zoom_blur", 2) and corruptions.parse_name("Day-RAIN") is None


# the generate keys of the rendered sets before corruptions existed: none may move
# the DeepGTAV key moved with issue 73 (renderer.frame, the plugin's boxes parsed anew: old entries hold other boxes),
# not with the corruptions (CHANGELOG)
KEYS = {(): "cb74c720a4d2c928", ("renderer=synthetic", "region=synthetic_street"): "e9d71756240f53f9",
        ("conditions=fog_ladder",): "c8bae0e1db602667", ("conditions=light_ladder",): "c3f6b65168cb1b50",
        ("conditions=rain_ladder",): "8830633b084e257e", ("renderer=deepgtav", "region=los_santos"): "a84c6bdb1ce24eb7"}


def generate_key(overrides: list[str]) -> str:
    from pairedgta import schema
    from pairedgta.cache import stage_hash
    from pairedgta.stages import generate

    cfg = OmegaConf.to_container(compose_cfg(overrides), resolve=True)
    config = generate.hash_config(schema.parse(cfg), build_condition_grid(cfg["conditions"]))
    return stage_hash("generate", generate.VERSION, config, {})


def test_the_rendered_sets_keep_their_generate_keys_and_corruptions_key_their_options(monkeypatch):
    import importlib.metadata

    real = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version", lambda n: "5.0.1" if n == "bpy" else real(n))  # the main job's
    for overrides, key in KEYS.items():
        assert generate_key(list(overrides)) == key, overrides
    base = ["renderer=synthetic", "region=synthetic_street", "conditions=corruptions"]
    one = generate_key([*base, "conditions.corruptions.only=[fog]"])
    assert one != generate_key([*base, "conditions.corruptions.only=[fog]", "conditions.corruptions.severities=[1]"])
    assert one != generate_key([*base, "conditions.corruptions.only=[snow]"])
    monkeypatch.setattr(corruptions, "library_version", lambda: "9.9")
    assert one != generate_key([*base, "conditions.corruptions.only=[fog]"])  # another library, another entry


@pytest.mark.parametrize("override, says", [
    ("conditions.corruptions.only=[fogg]", "conditions.corruptions.only: unknown corruption(s) ['fogg']"),
    ("conditions.corruptions.severities=[0,3]", "conditions.corruptions.severities: severity 0 is not one of 1..5"),
    ("conditions.corruptions.severities=[6]", "conditions.corruptions.severities: severity 6 is not one of 1..5"),
    ("conditions.corruptions.severities=[high]", "severity 'high' is not one of 1..5"),
    ("conditions.corruptions.of=Night-RAIN", "conditions.corruptions.of='Night-RAIN': corruptions need a rendered"),
    ("conditions.corruptions.names=[snow]", "conditions.corruptions.only: ['fog'] not in conditions.corruptions.names"),
    ("metric.min_transmittance=0.2", "metric.min_transmittance=0.2 does not apply to corruption conditions"),
    ("dataset=acdc", "conditions.corruptions: dataset=acdc has no clean condition"),
])
def test_bad_input_is_one_line_before_any_stage_writes(tmp_path, override, says):
    extra = ["dataset.root=/nonexistent"] if override == "dataset=acdc" else []
    only = [] if "only=" in override else ["conditions.corruptions.only=[fog]"]
    cache = tmp_path / "cache"
    proc = run_cli([*base_overrides(tmp_path, store=False), "tracking.enabled=false", "renderer=synthetic",
                    "region=synthetic_street", "conditions=corruptions", *only, override, *extra], tmp_path)
    assert proc.returncode != 0
    line = proc.stderr.strip().splitlines()[-1]
    assert says in line, proc.stderr[-2000:]
    assert not (cache / "generate").exists()


def test_a_clean_condition_left_out_by_only_is_named():
    with pytest.raises(ConfigError, match="leaves out Day-RAIN, the clean condition it corrupts"):
        grid_of(["conditions=paper_corruptions", "conditions.corruptions.of=Day-RAIN",
                 "conditions.only=[Day-EXTRASUNNY,C-fog-1]"])


# -- generation through the CLI ------------------------------------------------------------------------------------


def tiny(tmp_path: Path, *extra: str) -> list[str]:
    return [*base_overrides(tmp_path, store=False), "tracking.enabled=false", "renderer=synthetic",
            "region=synthetic_street", "renderer.width=64", "renderer.height=32", "generate.num_scenes=2",
            "stages=[generate]", "conditions=corruptions", "conditions.corruptions.only=[brightness,gaussian_noise]",
            "conditions.corruptions.severities=[1,3]", *extra]


def entry_of(cache: Path) -> Path:
    (entry,) = [p for p in (cache / "generate").iterdir() if not p.name.startswith(".") and p.is_dir()]
    return entry


@pytest.mark.slow  # the CLI in-process, then once more with two worker processes (about 15 s)
def test_generate_writes_paired_seeded_corruptions_through_the_cli(tmp_path):
    from pairedgta.datasets import open_dataset

    proc = run_cli(tiny(tmp_path), tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    entry = entry_of(tmp_path / "cache")
    grid = grid_of(tiny(tmp_path))
    names = [f"C-{n}-{s}" for n in ("gaussian_noise", "brightness") for s in (1, 3)]
    assert sorted(grid.adverse) == sorted(names)
    dataset = open_dataset({"kind": "generated", "name": "generated"}, grid, root=entry)
    assert len(dataset) == 2
    for g in dataset.groups:
        clean = png(g.images["Day-EXTRASUNNY"])
        for name in names:
            c = grid[name]
            assert g.labels[name] == g.labels["Day-EXTRASUNNY"]  # the clean truth, file for file
            assert g.instances[name] == g.instances["Day-EXTRASUNNY"]
            assert name not in g.transmittance
            image = png(g.images[name])
            want = corruptions.corrupt(clean, c.corruption, c.severity, corruptions.seed_for(0, g.group_id, name))
            assert image.tobytes() == want.tobytes()
        theirs = imagecorruptions.corrupt(clean.copy(), corruption_name="brightness", severity=3)
        assert png(g.images["C-brightness-3"]).tobytes() == theirs.tobytes()
    assert "corruption_time" in pd.read_csv(entry / "timings.csv").columns
    assert json.loads((entry / "manifest.json").read_text())["config"]["corruptions"]["library"] == "imagecorruptions"
    again = run_cli(tiny(tmp_path), tmp_path)
    assert again.returncode == 0 and "cache hit" in again.stderr + again.stdout
    # another cache, two worker processes: the same bytes (seeded by scene and condition, not by worker or order)
    other = tmp_path / "other"
    other.mkdir()
    proc = run_cli(tiny(other, "generate.workers=2"), other)
    assert proc.returncode == 0, proc.stderr[-3000:]
    second = entry_of(other / "cache")
    assert second.name == entry.name
    for f in sorted((entry / "scenes").rglob("C-*.png")):
        assert f.read_bytes() == (second / f.relative_to(entry)).read_bytes(), f


@pytest.mark.slow  # the CLI in-process on a tiny released-layout folder (a few seconds)
def test_the_released_layout_gets_its_clean_frames_corrupted(tmp_path):
    root = tmp_path / "PairedGTA"
    (root / "Day").mkdir(parents=True)
    for loc in ("0001", "0002"):
        Image.fromarray(np.roll(street(), int(loc), axis=1)).save(root / "Day" / f"{loc}_Day_EXTRASUNNY.png")
    args = [*tiny(tmp_path), "dataset=paired_gta", f"dataset.root={root}"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    entry = entry_of(tmp_path / "cache")
    for loc in ("0001", "0002"):
        clean = png(root / "Day" / f"{loc}_Day_EXTRASUNNY.png")
        for name, c in (("C-gaussian_noise-3", ("gaussian_noise", 3)), ("C-brightness-1", ("brightness", 1))):
            want = corruptions.corrupt(clean, *c, corruptions.seed_for(0, loc, name))
            assert png(entry / "scenes" / loc / f"{name}.png").tobytes() == want.tobytes()
    assert json.loads((entry / "index.json").read_text())["groups"] == ["0001", "0002"]
    again = run_cli(args, tmp_path)
    assert again.returncode == 0 and "cache hit" in again.stderr + again.stdout, again.stderr[-3000:]


# -- summaries -------------------------------------------------------------------------------------------------------


def test_mpc_and_rpc_are_michaelis_et_al_s_by_hand():
    """P = 0.40; every common corruption at severity s has AP 0.40 - 0.05 s, except fog, 0.30 at every severity.
    By hand: 14 corruptions average 0.25 over their severities (0.35, 0.30, 0.25, 0.20, 0.15), fog 0.30, so
    mPC = (14 * 0.25 + 0.30) / 15 = 3.80 / 15 = 0.25333..., rPC = mPC / P = 0.63333..."""
    rows = [{"model": "m", "condition": "Day-EXTRASUNNY", "value": 0.40},
            {"model": "m", "condition": "Night-RAIN", "value": 0.01}]  # a rendered condition: not a corruption
    for name in corruptions.COMMON:
        for s in corruptions.SEVERITIES:
            value = 0.30 if name == "fog" else 0.40 - 0.05 * s
            rows.append({"model": "m", "condition": f"C-{name}-{s}", "value": value})
    table = cs.summarise(pd.DataFrame(rows), "Day-EXTRASUNNY", "ap")
    headline = table[table["corruption"] == "all"].iloc[0]
    assert headline["clean"] == pytest.approx(0.40)
    assert headline["n_conditions"] == 75 and bool(headline["complete"])
    assert headline["mean"] == pytest.approx(3.80 / 15) and headline["relative"] == pytest.approx(3.80 / 15 / 0.40)
    per = table.set_index("corruption")
    assert per.loc["snow", "mean"] == pytest.approx(0.25) and per.loc["snow", "relative"] == pytest.approx(0.625)
    assert per.loc["fog", "mean"] == pytest.approx(0.30) and per.loc["fog", "relative"] == pytest.approx(0.75)
    assert len(table) == 16  # 15 corruptions and `all`


def test_the_summary_reads_evaluates_csvs_and_a_missing_cell_leaves_mpc_undefined(tmp_path):
    gt = pd.DataFrame([{"model": "m", "condition": c, "class_id": -1, "class_name": "mean", "iou": v}
                       for c, v in (("Day-EXTRASUNNY", 0.6), ("C-fog-1", 0.5), ("C-fog-3", 0.3), ("C-snow-1", 0.4))]
                      + [{"model": "m", "condition": "C-fog-1", "class_id": 0, "class_name": "road", "iou": 0.9}])
    gt.to_csv(tmp_path / "gt_iou.csv", index=False)
    ap = pd.DataFrame([{"model": "d", "condition": c, "class_name": k, "ap": v, "ap50": v + 0.1}
                       for c, v in (("Day-EXTRASUNNY", 0.5), ("C-fog-1", 0.4), ("C-fog-2", math.nan))
                       for k in ("all", "car")])
    ap.to_csv(tmp_path / "detection_ap.csv", index=False)
    table = cs.entry_summary(tmp_path, "Day-EXTRASUNNY")
    seg = table[table["score"] == "gt_miou"].set_index("corruption")
    assert seg.loc["fog", "mean"] == pytest.approx(0.4) and seg.loc["fog", "relative"] == pytest.approx(0.4 / 0.6)
    assert seg.loc["all", "mean"] == pytest.approx(1.2 / 3) and not bool(seg.loc["all", "complete"])
    det = table[table["score"] == "ap"].set_index("corruption")
    assert math.isnan(det.loc["all", "mean"]) and math.isnan(det.loc["all", "relative"])  # C-fog-2 has no AP
    assert det.loc["all", "clean"] == pytest.approx(0.5)
    out = cs.write_csv(table, tmp_path / "corruptions.csv")
    assert pd.read_csv(out).shape == table.shape
    assert "fog" in cs.format_table(table, "gt_miou")
    assert cs.write_entry(tmp_path, "Day-EXTRASUNNY") == tmp_path / cs.SUMMARY
    lines = cs.terminal_summary([tmp_path], "Day-EXTRASUNNY").splitlines()
    assert "mPC" in lines[0] and len(lines) == 1 + 1 + 3  # header, column names, `all` of gt_miou, ap, ap50
    empty = tmp_path / "rendered"
    empty.mkdir()
    gt[~gt["condition"].str.startswith("C-")].to_csv(empty / "gt_iou.csv", index=False)
    assert cs.write_entry(empty, "Day-EXTRASUNNY") is None and cs.terminal_summary([empty], "Day-EXTRASUNNY") == ""


@pytest.mark.slow  # three CLI runs in-process (a few seconds)
def test_shards_split_the_corruptions_with_their_scenes(tmp_path):
    proc = run_cli(tiny(tmp_path, "generate.num_shards=2", "generate.shard=0"), tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (work,) = [p for p in (tmp_path / "cache" / "generate").iterdir() if p.name.startswith(".partial-")]
    assert sorted(p.parent.name for p in work.rglob("C-brightness-3.png")) == ["00000"]  # shard 0's scene only
    proc = run_cli(tiny(tmp_path, "generate.num_shards=2", "generate.shard=1"), tmp_path)  # the last part: complete
    assert proc.returncode == 0, proc.stderr[-3000:]
    entry = entry_of(tmp_path / "cache")
    for scene in ("00000", "00001"):
        clean = png(entry / "scenes" / scene / "Day-EXTRASUNNY.png")
        want = corruptions.corrupt(clean, "gaussian_noise", 3, corruptions.seed_for(0, scene, "C-gaussian_noise-3"))
        assert png(entry / "scenes" / scene / "C-gaussian_noise-3.png").tobytes() == want.tobytes()
    again = run_cli(tiny(tmp_path), tmp_path)  # the unsharded run finds the entry
    assert again.returncode == 0 and "cache hit" in again.stderr + again.stdout


@pytest.mark.slow  # two tiny runs through the CLI, one per task (about 30 s)
def test_evaluate_writes_the_corruption_summary_for_both_tasks(tmp_path):
    """The task-neutral evaluate stage writes corruption_summary.csv beside either task's tables (P, mPC, rPC of
    Michaelis et al. for detection's AP, Cityscapes-C's per-corruption means for segmentation's mIoU)."""
    from pairedgta.corruption_summary import SUMMARY

    seg = [*tiny(tmp_path, "stages=[generate,pseudolabel,evaluate,plot]", "model=tiny_segformer", "models=null",
                 "reference_model=tiny_segformer", "metric.bootstrap.resamples=20", "threads=1",
                 "plot.figures=[corruptions]", "plot.formats=[png]", "plot.dpi=40")]
    proc = run_cli(seg, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (entry,) = [p for p in (tmp_path / "cache" / "evaluate").iterdir() if not p.name.startswith(".")]
    table = pd.read_csv(entry / SUMMARY)
    assert {"gt_miou", "xi"} <= set(table["score"]) and {"brightness", "gaussian_noise", "all"} <= set(
        table["corruption"])
    drawn = pd.read_csv(next((tmp_path / "cache" / "plot").glob("*/corruptions*.csv")))  # the figure's numbers
    row = drawn[(drawn["condition"] == "C-brightness-3")].iloc[0]
    clean = pd.read_csv(entry / "gt_iou.csv").query("class_name == 'mean' and condition == 'Day-EXTRASUNNY'")["iou"]
    assert row["relative"] == pytest.approx(row["value"] / float(clean.iloc[0]))
    assert list((tmp_path / "cache" / "plot").glob("*/corruptions*.png"))

    det = tmp_path / "det"
    det.mkdir()
    proc = run_cli([*tiny(det, "stages=[generate,pseudolabel,evaluate,plot]"), "+experiment=smoke_detection",
                    "renderer.width=96", "renderer.height=48", "models=[tiny_fcos]", "metric.bootstrap.resamples=20",
                    "threads=1", "plot.figures=[corruptions]", "plot.formats=[png]", "plot.dpi=40"], det)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (entry,) = [p for p in (det / "cache" / "evaluate").iterdir() if not p.name.startswith(".")]
    table = pd.read_csv(entry / SUMMARY)
    assert {"ap", "detection_xi"} <= set(table["score"])
    assert list((det / "cache" / "plot").glob("*/corruptions*.png"))  # the same figure for detection's AP


def test_loading_the_library_leaves_no_stand_in_pkg_resources_behind():
    """The pkg_resources stand-in serves the library's import only: left in sys.modules it broke every later
    monkeypatch.syspath_prepend of the same test process (pytest imports pkg_resources.fixup_namespace_packages)."""
    import sys

    corruptions.library()
    left = sys.modules.get("pkg_resources")
    assert left is None or hasattr(left, "fixup_namespace_packages")  # none, or setuptools' own


def test_corrupting_a_released_layout_resumes_from_its_finished_groups(tmp_path, caplog):
    """A job stopped half-way (a shard's part, a kill) leaves finished groups: the next call corrupts only the rest,
    and says so (the line once named an undefined logger)."""
    import logging
    from types import SimpleNamespace

    from pairedgta.datasets import open_dataset
    from pairedgta.render.corruptions import corrupt_groups

    root = tmp_path / "PairedGTA"
    (root / "Day").mkdir(parents=True)
    for loc in ("0001", "0002"):
        Image.fromarray(np.roll(street(), int(loc), axis=1)).save(root / "Day" / f"{loc}_Day_EXTRASUNNY.png")
    over = tiny(tmp_path, "dataset=paired_gta", f"dataset.root={root}")
    grid = grid_of(over)
    dataset = open_dataset({"kind": "paired_gta", "name": "paired_gta", "root": str(root)}, grid)
    gen = SimpleNamespace(workers=1, seed=0)
    corrupt_groups(dataset, grid, gen, tmp_path / "out", [0])
    first = sorted((tmp_path / "out" / "scenes").rglob("C-*.png"))
    assert first and all(p.parent.name == "0001" for p in first)
    caplog.set_level(logging.INFO, logger="pairedgta")
    corrupt_groups(dataset, grid, gen, tmp_path / "out", [0, 1])
    assert "resuming, 1 of 2 groups already corrupted" in caplog.text
    assert {p.parent.name for p in (tmp_path / "out" / "scenes").rglob("C-*.png")} == {"0001", "0002"}


# -- the corruptions-vs-rendered study ---------------------------------------------------------------------------------


def test_the_study_finds_a_planted_stand_in_and_says_when_it_cannot_tell():
    """Eight models whose robustness under C-fog follows Day-FOGGY's and under C-contrast Night's (with scene noise):
    each rendered condition's best stand-in is the planted corruption, separated from the runner-up; the means agree.
    With every corruption unrelated to the rendered condition nothing is called clear."""
    from pairedgta.corruptions import parse_name
    from pairedgta.metrics import corruption_study as study

    rng = np.random.default_rng(0)
    m = 8
    conds = ["Day-EXTRASUNNY", "Night-EXTRASUNNY", "Day-FOGGY", "C-fog-1", "C-fog-3", "C-contrast-1", "C-contrast-3"]
    clean, night, fog = rng.uniform(0.3, 0.8, m), rng.uniform(0.2, 0.9, m), rng.uniform(0.2, 0.9, m)
    s = np.zeros((1 + 300, m, len(conds)))
    for k, rob in enumerate([np.ones(m), night, fog, fog * 0.9 + 0.05, fog * 0.8, night, night * 0.7]):
        s[:, :, k] = clean * rob
    s[1:] *= rng.uniform(0.97, 1.03, s[1:].shape)
    pairs, means, best = study.compare(s, conds, "Day-EXTRASUNNY", parse_name)
    by = {(b["measure"], b["rendered"]): b for b in best}
    assert by["relative", "Day-FOGGY"]["best"] == "fog" and by["relative", "Day-FOGGY"]["clear"]
    assert by["relative", "Night-EXTRASUNNY"]["best"] == "contrast" and by["relative", "Night-EXTRASUNNY"]["clear"]
    row = next(p for p in pairs if p["measure"] == "relative" and p["rendered"] == "Day-FOGGY"
               and p["corruption"] == "fog" and p["severity"] == "3")
    assert row["spearman"] == pytest.approx(1.0) and row["ci_low"] > 0.5
    assert len(means) == 2 and all(-1 <= r["spearman"] <= 1 for r in means)

    noise = s.copy()
    noise[:, :, 3:] = clean[None, :, None] * rng.uniform(0.2, 0.9, (1, m, 4))  # corruptions unrelated to either
    noise[1:, :, 3:] *= rng.uniform(0.9, 1.1, noise[1:, :, 3:].shape)
    _, _, best = study.compare(noise, conds, "Day-EXTRASUNNY", parse_name)
    assert not any(b["clear"] and b["measure"] == "relative" and abs(b["spearman"]) < 0.9 for b in best)


@pytest.mark.slow  # a tiny synthetic run of four tiny models through the CLI (about 15 s)
def test_the_study_through_the_cli(tmp_path):
    args = [*base_overrides(tmp_path, store=False), "+experiment=corruptions_vs_rendered", "tracking.enabled=false",
            "renderer=synthetic", "region=synthetic_street", "renderer.width=64", "renderer.height=32",
            "generate.num_scenes=4", "conditions.corruptions.only=[fog,contrast,brightness]",
            "conditions.corruptions.severities=[1,3]",
            "models=[tiny_segformer,tiny_ddrnet,tiny_pidnet,tiny_deeplabv3plus]", "reference_model=tiny_segformer",
            "metric.bootstrap.resamples=50", "plot.formats=[png]", "plot.dpi=40", "threads=1"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (plot,) = [p for p in (tmp_path / "cache" / "plot").iterdir() if not p.name.startswith(".")]
    pairs = pd.read_csv(plot / "corruption_study_pairs.csv")
    assert len(set(pairs["rendered"])) == 8 and {"Day-FOGGY", "Night-EXTRASUNNY"} <= set(pairs["rendered"])
    assert set(pairs["corruption"]) == {"fog", "contrast", "brightness"}
    assert set(pairs["severity"].astype(str)) == {"1", "3", "mean"}
    assert (pairs["models"] == 3).all()  # the reference is not ranked
    assert "Best stand-in per rendered condition" in (plot / "corruption_study.md").read_text()
    assert (plot / "corruption_study.png").is_file() and (plot / "corruptions.png").is_file()
    few = run_cli([a for a in args if not a.startswith("models=")] + ["models=[tiny_segformer,tiny_ddrnet]",
                                                                     "force=[plot]"], tmp_path)
    assert few.returncode != 0 and "corruption_study ranks the models other than the reference" in few.stderr
