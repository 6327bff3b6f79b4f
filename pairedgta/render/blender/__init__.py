"""Cycles backend (bpy), split by concern: geometry (mesh templates), models (object models), scene
(town and entity construction), illumination (condition -> render parameters), nodes (shader-node
helpers and condition knobs), materials, atmosphere (sky and analytic fog), shading (lights and applying
a condition), labels (label codes and the index pass), cycles (bpy and render settings) and renderer
(BlenderRenderer). Importing the package does not import bpy."""
from pairedgta.render.blender.geometry import TEMPLATES, mesh_arrays, srgb_to_linear
from pairedgta.render.blender.illumination import lighting, sun_transmittance, sun_vector
from pairedgta.render.blender.labels import LABEL_CODE_VOID, MAX_INSTANCES, decode_labels, label_code
from pairedgta.render.blender.models import model_parts
from pairedgta.render.blender.renderer import BlenderRenderer

__all__ = ["BlenderRenderer", "LABEL_CODE_VOID", "MAX_INSTANCES", "TEMPLATES", "decode_labels", "label_code",
           "lighting", "mesh_arrays", "model_parts", "srgb_to_linear", "sun_transmittance", "sun_vector"]
