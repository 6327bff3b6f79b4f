"""Cycles backend (bpy), split by concern: geometry (mesh templates), models (object models),
materials (materials, world, lights, fog, conditions), labels (label codes and the index pass) and
renderer (BlenderRenderer). Importing the package does not import bpy."""
from pairedgta.render.blender.geometry import TEMPLATES, mesh_arrays, srgb_to_linear
from pairedgta.render.blender.labels import LABEL_CODE_VOID, MAX_INSTANCES, decode_labels, label_code
from pairedgta.render.blender.materials import lighting, sun_transmittance, sun_vector
from pairedgta.render.blender.models import model_parts
from pairedgta.render.blender.renderer import BlenderRenderer

__all__ = ["BlenderRenderer", "LABEL_CODE_VOID", "MAX_INSTANCES", "TEMPLATES", "decode_labels", "label_code",
           "lighting", "mesh_arrays", "model_parts", "srgb_to_linear", "sun_transmittance", "sun_vector"]
