"""Label pass: every surface emits its object's pass index (class + 32 * instance) in red and its
distance from the camera in green, rendered with one centred sample per pixel into a float EXR and
decoded exactly."""
from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX
from pairedgta.render.blender.cycles import image_pixels
from pairedgta.render.blender.nodes import Knobs

LABEL_CODE_VOID = 31  # class code for surfaces that are not one of the 19 classes
MAX_INSTANCES = 32767 // 32


def decode_labels(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label-pass values -> (train ids uint8, instance ids uint16). 0 is sky."""
    code = np.rint(code).astype(np.int64)
    cls = code % 32
    train = np.where((cls >= 1) & (cls <= len(CLASS_NAMES)), cls - 1, IGNORE_INDEX)
    train = np.where(code == 0, CLASS_NAMES.index("sky"), train)
    return train.astype(np.uint8), (code // 32).astype(np.uint16)


def label_code(label: str, instance: int = 0) -> int:
    cls = CLASS_NAMES.index(label) + 1 if label in CLASS_NAMES else LABEL_CODE_VOID
    return instance * 32 + cls


def render_label_pass(bpy, knobs: Knobs, render_to: Callable[[str], None],
                      tmp_dir: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render the index pass of the current scene and return (train ids, instance ids, distance in m;
    inf for the sky).

    Only values change (label_mode, fog_on, compositing, sampling settings) and are restored afterwards:
    toggling visibility would reorder Cycles' scene and so the beauty pass's sampling."""
    sc = bpy.context.scene
    vl = sc.view_layers[0]
    cy = sc.cycles
    saved = (cy.samples, cy.filter_width, cy.use_denoising)
    compositing = sc.render.use_compositing  # analytic fog must not tint the codes
    fog = knobs.get("fog_on")
    img = sc.render.image_settings
    knobs.set("label_mode", 1.0)
    knobs.set("fog_on", 0.0)
    vl.use_sky = False
    sc.render.use_compositing = False
    cy.samples, cy.filter_width, cy.use_denoising = 1, 0.01, False  # one centred sample per pixel
    img.file_format = "OPEN_EXR"
    img.color_depth = "32"
    img.exr_codec = "NONE"
    path = os.path.join(tmp_dir, "labels.exr")
    try:
        render_to(path)
    finally:
        knobs.set("label_mode", 0.0)
        knobs.set("fog_on", fog)
        vl.use_sky = True
        sc.render.use_compositing = compositing
        cy.samples, cy.filter_width, cy.use_denoising = saved
    image = bpy.data.images.load(path, check_existing=False)
    try:
        px = image_pixels(image)[::-1]
    finally:
        bpy.data.images.remove(image)
    train, instances = decode_labels(px[..., 0])
    distance = np.where(np.rint(px[..., 0]) == 0, np.inf, px[..., 1]).astype(np.float32)
    return train, instances, distance


__all__ = ["LABEL_CODE_VOID", "MAX_INSTANCES", "decode_labels", "label_code", "render_label_pass"]
