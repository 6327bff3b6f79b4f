"""The renderer's version is part of what a render is (issue 51, item 2): the generate stage's key names the Blender
version, its manifest and index record it, and two Blenders never share a cache entry. Without bpy (Python 3.12,
where no Blender module exists) renderer=blender stops with one line before any stage writes."""
from __future__ import annotations

import importlib.metadata
import json
import sys

import numpy as np
import pytest

from pairedgta.cache import MANIFEST
from pairedgta.render import renderer_versions
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.render.blender import cycles
from pairedgta.stages import generate as generate_stage
from pairedgta.testing.cli import base_overrides, compose_cfg, run_cli

REAL_VERSION = importlib.metadata.version


def pretend_bpy(monkeypatch, version: str | None) -> None:
    """The installed bpy, as its package metadata says (None: not installed, as on Python 3.12)."""

    def version_of(name: str) -> str:
        if name == "bpy":
            if version is None:
                raise importlib.metadata.PackageNotFoundError(name)
            return version
        return REAL_VERSION(name)

    monkeypatch.setattr(importlib.metadata, "version", version_of)
    if version is None:
        monkeypatch.setitem(sys.modules, "bpy", None)  # `import bpy` fails, find_spec finds nothing


class Flat(Renderer):
    """Stands in for Cycles: a grey image whose level follows the (pretended) Blender version, so the test
    renders in milliseconds and can tell the two versions' entries apart."""

    gives_labels = True

    def __init__(self, level: int, width: int, height: int) -> None:
        super().__init__(width, height)
        self.level = level

    def prepare(self, descriptor) -> None:
        pass

    def render(self, descriptor, condition) -> RenderResult:
        h, w = self.height, self.width
        return RenderResult(image=np.full((h, w, 3), self.level, np.uint8), labels=np.zeros((h, w), np.uint8))


def tiny(tmp_path) -> list[str]:
    return base_overrides(tmp_path, store=False) + [
        "renderer=blender", "region=procedural_town", "stages=[generate]", "generate.num_scenes=1",
        "renderer.width=32", "renderer.height=16", "conditions.only=[Day-EXTRASUNNY,Night-RAIN]",
        "generate.validation.enabled=false", "tracking.enabled=false",
    ]


def generate_key(overrides: list[str]) -> tuple[str, dict]:
    from omegaconf import OmegaConf

    from pairedgta import schema
    from pairedgta.cache import stage_hash
    from pairedgta.conditions import build_condition_grid

    cfg = OmegaConf.to_container(compose_cfg(overrides), resolve=True)
    config = generate_stage.hash_config(schema.parse(cfg), build_condition_grid(cfg["conditions"]))
    return stage_hash("generate", generate_stage.VERSION, config, {}), config


def test_the_generate_key_names_the_blender_version(monkeypatch):
    keys = {}
    for version in ("5.0.1", "5.3.0", "5.0.1"):
        pretend_bpy(monkeypatch, version)
        assert renderer_versions("blender") == {"blender_version": version}
        key, config = generate_key([])  # the main job
        assert config["blender_version"] == version
        keys.setdefault(version, set()).add(key)
    assert len(keys["5.0.1"]) == 1 and keys["5.0.1"] != keys["5.3.0"]  # stable per version, distinct between them
    # a backend without a version of its own hashes as before: no key, nothing added
    assert renderer_versions("synthetic") == {} and renderer_versions("deepgtav") == {}
    _, synthetic = generate_key(["renderer=synthetic", "region=synthetic_street"])
    assert not any(k.endswith("_version") for k in synthetic)


@pytest.mark.slow  # the stage graph (in-process, a stand-in renderer: about a second)
def test_two_blender_versions_never_share_an_entry(tmp_path, monkeypatch):
    from pairedgta.app import run

    levels = {"5.0.1": 90, "5.3.0": 110}
    monkeypatch.setattr(generate_stage, "build_renderer",
                        lambda cfg: Flat(levels[cycles.blender_version()], cfg["width"], cfg["height"]))
    entries = {}
    for version in ("5.0.1", "5.3.0", "5.0.1"):
        pretend_bpy(monkeypatch, version)
        summary = run(compose_cfg(tiny(tmp_path)))
        (stage,) = summary["stages"]
        entry = tmp_path / "cache" / "generate" / stage["key"]
        assert json.loads((entry / MANIFEST).read_text())["config"]["blender_version"] == version
        assert json.loads((entry / "index.json").read_text())["blender_version"] == version
        image = entry / "scenes" / "00000" / "Day-EXTRASUNNY.png"
        from PIL import Image

        assert np.asarray(Image.open(image)).mean() == levels[version]  # the entry holds that version's pixels
        entries.setdefault(version, []).append((stage["key"], stage["hit"]))
    (first, hit_first), (again, hit_again) = entries["5.0.1"]
    ((other, hit_other),) = entries["5.3.0"]
    assert first == again != other
    assert not hit_first and not hit_other and hit_again  # 5.3.0 rendered its own entry; 5.0.1's was kept
    assert len([d for d in (tmp_path / "cache" / "generate").iterdir() if (d / MANIFEST).is_file()]) == 2


@pytest.mark.slow  # the CLI (in-process)
def test_without_bpy_renderer_blender_is_one_line_naming_the_pythons(tmp_path, monkeypatch):
    """Python 3.12 (no Blender module exists for it): the package works, renderer=blender stops with one line
    naming the Pythons that have bpy and renderer=synthetic, before any stage writes."""
    pretend_bpy(monkeypatch, None)
    monkeypatch.setattr(cycles, "running_python", lambda: "3.12")
    # with the record on: it is never opened
    proc = run_cli([a for a in tiny(tmp_path) if a != "tracking.enabled=false"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    line = errors[0]
    assert "Python 3.11" in line and "Python 3.13" in line and "not for this Python 3.12" in line
    assert "renderer=synthetic" in line and "Traceback" not in proc.stderr
    assert not [p for p in (tmp_path / "cache").glob("*") if p.is_dir() and not p.name.startswith(".")]  # no stage
    assert not (tmp_path / "mlflow.db").exists()  # nor the MLflow record: the check comes before both
    # the renderer itself says the same when built directly (a script that skips the stage graph)
    from pairedgta.errors import RendererError
    from pairedgta.render.blender import BlenderRenderer

    with pytest.raises(RendererError, match="renderer=synthetic") as err:
        BlenderRenderer(width=32, height=16).open()
    assert "\n" not in str(err.value)


def test_the_message_names_what_to_do_on_each_python():
    for python in ("3.12", "3.14"):
        line = cycles.bpy_unavailable(python)
        assert f"not for this Python {python}" in line and "renderer=synthetic" in line
        assert all(f"Python {py} (bpy {v})" in line for py, v in cycles.BPY_FOR_PYTHON.items())
    for python, bpy in cycles.BPY_FOR_PYTHON.items():  # a supported Python without bpy: reinstall as README says
        line = cycles.bpy_unavailable(python)
        assert "not installed" in line and f"bpy {bpy} on Python {python}" in line and "constraints.txt" in line
