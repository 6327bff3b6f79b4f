"""The interpreters the project installs on (issue 51, item 1): README's one command resolves Blender as a module and
numpy through environment markers (bpy 5.0.1 and numpy 1.26 on Python 3.11, bpy 5.3 and numpy 2 on 3.13, no bpy
on 3.12), the constraints hold on each, and bpy and torch live in one process without a crash or stray EGL lines."""
from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

from pairedgta.render.blender.cycles import BPY_FOR_PYTHON

ROOT = Path(__file__).resolve().parents[1]
PYTHONS = ("3.11", "3.12", "3.13")


def env(python: str) -> dict[str, str]:
    return {"python_version": python, "python_full_version": f"{python}.0", "sys_platform": "linux",
            "platform_system": "Linux", "platform_machine": "x86_64", "implementation_name": "cpython",
            "platform_python_implementation": "CPython", "os_name": "posix", "extra": ""}


def active(lines: list[str], python: str) -> dict[str, Requirement]:
    """The requirements whose marker holds on `python`, by name (one each)."""
    out: dict[str, Requirement] = {}
    for line in lines:
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate(env(python)):
            assert req.name not in out, f"{req.name} is required twice on Python {python}"
            out[req.name] = req
    return out


def project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def constraints() -> list[str]:
    lines = (ROOT / "constraints.txt").read_text().splitlines()
    return [line.split("#")[0].strip() for line in lines if line.split("#")[0].strip()]


def pinned(req: Requirement | None) -> str | None:
    (spec,) = req.specifier if req is not None else (None,)
    assert spec is None or spec.operator == "==", req
    return spec.version if spec is not None else None


@pytest.mark.parametrize("python", PYTHONS)
def test_every_supported_python_resolves_its_blender_and_numpy(python):
    assert SpecifierSet(project()["requires-python"]).contains(f"{python}.0")
    deps = active(project()["dependencies"], python)
    pins = active(constraints(), python)
    bpy = deps.get("bpy")
    if python in BPY_FOR_PYTHON:  # the backend's message names exactly the Pythons the markers give bpy to
        pin = pinned(pins.get("bpy"))
        assert bpy is not None and bpy.specifier.contains(pin) and pin.startswith(BPY_FOR_PYTHON[python])
    else:
        assert bpy is None and "bpy" not in pins  # 3.12: no Blender module exists; the package installs without it
    numpy = deps["numpy"]
    want_major = "2" if python >= "3.13" else "1"
    assert all(s.version.startswith(want_major) or s.operator == "<" for s in numpy.specifier), numpy
    # the extras README's install takes (.[dev] includes them) are pinned here too: the corruption library's
    extras = active([r for rs in project()["optional-dependencies"].values() for r in rs
                     if not r.startswith("pairedgta[") and Requirement(r).name in ("imagecorruptions", "opencv-python",
                                                                                   "scikit-image")], python)
    deps = {**deps, **extras}
    for name, pin in pins.items():  # every constraint satisfies the project's own range on that Python
        assert name in deps or name in ("torch", "torchvision")
        if name in deps and pin.specifier:
            version = next((s.version for s in pin.specifier if s.operator in ("==", ">=")), None)
            assert version is None or deps[name].specifier.contains(version), (python, name, pin, deps[name])
    assert pinned(pins["torch"]) == "2.14.1" and pinned(pins["torchvision"]) == "0.29.1"


def test_the_blender_pythons_are_named_once():
    """BPY_FOR_PYTHON (the backend's error line) and the pyproject markers name the same Pythons."""
    marked = {m.group(1) for dep in project()["dependencies"] if dep.startswith("bpy")
              for m in [re.search(r"python_version\s*==\s*'([\d.]+)'", dep)] if m}
    assert marked == set(BPY_FOR_PYTHON)


# a fogged night (the compositor path) at a few pixels, then what the pseudolabel stage imports: torch's compiler
# loads triton and its LLVM; with the GPU compositor Blender 5.1+ had loaded Mesa's LLVM and the process crashed
RENDER_THEN_TORCH = """
import sys
from omegaconf import OmegaConf
from pairedgta import schema
from pairedgta.conditions import build_condition_grid
from pairedgta.render import build_renderer
from pairedgta.scene.sampling import build_region
from pairedgta.stages.generate import build_descriptor
from pairedgta.testing.cli import compose_cfg

cfg = OmegaConf.to_container(compose_cfg(["renderer.width=32", "renderer.height=16", "renderer.samples=1"]), resolve=True)
run = schema.parse(cfg)
grid = build_condition_grid(cfg["conditions"])
descriptor, _ = build_descriptor(0, run.generate, build_region(run.region))
with build_renderer(cfg["renderer"]) as renderer:
    image = renderer.render(descriptor, grid["Night-RAIN"]).image
assert image.shape == (16, 32, 3)
import torch, torch._dynamo
try:
    import triton  # noqa: F401  (where torch ships it)
except ImportError:
    pass
torch.nn.functional.conv2d(torch.ones(1, 3, 8, 8), torch.ones(2, 3, 3, 3))
maps = open("/proc/self/maps").read()
print("mesa:", sorted({l.split()[-1] for l in maps.splitlines() if "libEGL_mesa" in l or "libLLVM" in l}))
"""


@pytest.mark.slow  # renders with Blender
def test_blender_and_torch_share_a_process_without_a_crash_or_egl_lines(tmp_path):
    proc = subprocess.run([sys.executable, "-c", RENDER_THEN_TORCH], check=False, capture_output=True, text=True,
                          cwd=tmp_path, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]  # -11 (a segmentation fault) with bpy 5.3's GPU compositor
    assert "EGL" not in out, out[-3000:]
    assert "mesa: []" in proc.stdout, proc.stdout  # no Mesa GL context, so no second LLVM in the process
