"""Scene model: the non-photometric part of a group (descriptor S_k), sampling and placement."""
from pairedgta.scene.descriptor import (
    CATEGORIES,
    CameraPose,
    DynamicObject,
    Location,
    SceneDescriptor,
)

__all__ = ["CATEGORIES", "CameraPose", "DynamicObject", "Location", "SceneDescriptor"]
