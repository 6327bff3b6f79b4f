"""Cycles itself: importing bpy, the render settings of a session, and keeping Blender's C output quiet.

Everything here is fixed for a session (sampling, bounces, denoiser, device, resolution, colour
management); what a scene or a condition changes lives in scene.py and shading.py.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile

from pairedgta.errors import ConfigError, RendererError


@contextlib.contextmanager
def quiet_stdout():
    """Silence C-level stdout (file descriptor 1) for the duration; errors still raise."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no usable stdout: nothing to silence
        yield
        return
    with open(os.devnull, "wb") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


@contextlib.contextmanager
def quiet_cuda_probe(active: bool):
    """Blender's C code prints to file descriptor 1, and Cycles' CUDA probe prints "CUEW initialization
    failed" on every machine without the CUDA driver: noise when rendering on the CPU. The block's output
    goes through a temporary file and every other line is passed on."""
    if not active:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 1)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
            tmp.seek(0)
            kept = [line for line in tmp.read().decode(errors="replace").splitlines(keepends=True) if "CUEW" not in line]
            if kept:
                sys.stdout.write("".join(kept))
                sys.stdout.flush()


# Blender as a Python module (the bpy wheels on PyPI) exists for one Python per Blender release: the releases
# this project renders with, by the Python they need (pyproject.toml installs the one that fits)
BPY_FOR_PYTHON = {"3.11": "5.0.1", "3.13": "5.3"}


def running_python() -> str:
    return f"{sys.version_info.major}.{sys.version_info.minor}"


def bpy_unavailable(python: str | None = None) -> str:
    """The one line that says why renderer=blender cannot run on this interpreter, and what to do instead."""
    python = python or running_python()
    have = " and ".join(f"Python {py} (bpy {v})" for py, v in BPY_FOR_PYTHON.items())
    if python in BPY_FOR_PYTHON:
        return (f"renderer=blender needs Blender as a Python module (bpy), which is not installed; install the project "
                f"as README says (pip install -e \".[dev]\" -c constraints.txt installs bpy {BPY_FOR_PYTHON[python]} on "
                f"Python {python}), or use renderer=synthetic")
    return (f"renderer=blender needs Blender as a Python module (bpy), which exists for {have} only, not for this "
            f"Python {python}; install the project on one of those, or try the tool here with renderer=synthetic")


def blender_version() -> str:
    """The version of the installed Blender module ("5.0.1"), read from its package metadata without importing it
    (bpy takes seconds to import); a bpy that pip did not install is asked itself. ConfigError (one line, naming
    the Pythons that have bpy) where there is none."""
    import importlib.metadata
    import importlib.util

    try:
        return importlib.metadata.version("bpy")
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        found = importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise ConfigError(bpy_unavailable())
    return ".".join(str(v) for v in import_bpy().app.version)


def renderer_versions() -> dict[str, str]:
    """What the blender backend draws its pixels with, for the generate stage's key and manifest."""
    return {"blender_version": blender_version()}


def import_bpy():
    """bpy, imported on first use so that the package (and its numpy helpers) imports without it."""
    try:
        import bpy
    except ImportError as exc:
        raise RendererError(f"{bpy_unavailable()} ({exc})") from None
    return bpy


def image_pixels(image):
    """A loaded Blender image's pixels as a float32 (height, width, channels) array, rows bottom-up as Blender
    stores them (`image.pixels.foreach_set(a.ravel())` writes such an array back)."""
    import numpy as np

    w, h = image.size
    px = np.empty(w * h * image.channels, dtype=np.float32)
    image.pixels.foreach_get(px)
    return px.reshape(h, w, image.channels)


def configure_cycles(bpy, *, width: int, height: int, samples: int, device: str, denoise: bool,
                     denoiser_quality: str, max_bounces: int, fast_gi: bool, light_tree: bool, seed: int,
                     filter_width: float, volume_step_rate: float, threads: int, view_transform: str,
                     look: str) -> None:
    """Set the session's render settings (renderer.* keys) on the current scene. Sampling is fixed
    (no adaptive sampling, no animated seed) so that an image depends on (scene, condition) alone."""
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    cy = sc.cycles
    if device == "GPU":
        enable_gpu(bpy)
    cy.device = device
    cy.samples = samples
    cy.use_adaptive_sampling = False
    cy.use_denoising = denoise
    if denoise:
        with quiet_cuda_probe(device == "CPU"):  # choosing the denoiser probes every GPU library
            cy.denoiser = "OPENIMAGEDENOISE"
        cy.denoising_prefilter = "FAST"
        cy.denoising_quality = denoiser_quality
        cy.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    cy.max_bounces = max_bounces
    cy.diffuse_bounces = min(max_bounces, 1)
    cy.glossy_bounces = min(max_bounces, 2)
    cy.transmission_bounces = min(max_bounces, 1)
    cy.volume_bounces = 0
    cy.transparent_max_bounces = 4
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    cy.use_fast_gi = fast_gi
    cy.fast_gi_method = "REPLACE"
    cy.ao_bounces_render = 1
    cy.use_light_tree = light_tree
    cy.seed = seed
    cy.use_animated_seed = False
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 10.0
    cy.filter_width = filter_width
    cy.volume_step_rate = volume_step_rate
    cy.use_auto_tile = False
    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    r.use_persistent_data = True
    r.threads_mode = "FIXED" if threads else "AUTO"
    if threads:
        r.threads = threads
    r.dither_intensity = 0.0
    # the fog compositor on the CPU, as 5.0 does by default: 5.1 and later default to the GPU compositor, which
    # opens an EGL context through Mesa (two "EGL Error (0x3009): EGL_BAD_MATCH" lines on a machine without a
    # display), loads Mesa's LLVM into the process, and the LLVM in triton (imported by torch's compiler, which
    # transformers imports) then crashes it: a segmentation fault when the pseudolabel stage starts
    r.compositor_device = "CPU"
    r.use_file_extension = True
    try:
        sc.view_settings.view_transform = view_transform
        sc.view_settings.look = look
    except TypeError as exc:
        raise ConfigError(f"camera.view_transform/look: {exc}; use e.g. camera.view_transform=AgX camera.look=None") from None


def enable_gpu(bpy) -> None:
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for kind in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
        try:
            prefs.compute_device_type = kind
        except TypeError:
            continue
        prefs.refresh_devices()
        devices = [d for d in prefs.devices if d.type == kind]
        if devices:
            for d in prefs.devices:
                d.use = d.type == kind
            return
    raise ConfigError("renderer.device=GPU but Cycles finds no GPU on this machine; set renderer.device=CPU")


__all__ = ["BPY_FOR_PYTHON", "blender_version", "bpy_unavailable", "configure_cycles", "enable_gpu", "import_bpy",
           "quiet_cuda_probe", "quiet_stdout", "renderer_versions"]
