"""Automated pair validation: the paper's manual check that a group X_k shows one scene.

Two independent checks on a group of images rendered from one SceneDescriptor S_k:

* entity states: what the backend reports about the world (ego location, spawned vehicles and
  peds) must match the descriptor (count, kind/model, position within a tolerance);
* structure agreement: every variant must show the same geometry as the reference image. The
  score is the agreement of gradient orientations on the reference's edge pixels, computed with
  doubled angles (so it ignores edge polarity) and independent of gradient magnitude (so it
  ignores global darkening, tinting and loss of contrast from fog). Identical geometry scores
  close to 1, an unrelated picture close to 0.

Entity-state format (the DeepGTAV frame JSON; wire facts in the docstrings of
pairedgta/render/deepgtav_protocol.py and pairedgta/testing/deepgtav_server.py):
``{"location": [x, y, z], "vehicles": [entity, ...], "peds": [entity, ...]}`` where an entity has
``"position": [x, y, z]`` in world metres (or the classic DeepGTAV ``"FUR"``/``"BLL"`` box corners,
whose midpoint is used), optionally ``"model"`` (vehicle name, or ped model name / ``0x`` hash),
``"classID"`` (classic DeepGTAV: 0 car, 1 motorcycle, 2 bicycle) and ``"spawned"``. When entities
carry ``"spawned"``, only spawned ones are compared and their count must equal the descriptor's;
otherwise the game may report ambient traffic too, so only missing objects are flagged.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pairedgta.scene.descriptor import DynamicObject, SceneDescriptor

VEHICLE_CATEGORIES = frozenset({"car", "truck", "bus", "motorcycle", "bicycle"})
PED_CATEGORIES = frozenset({"person", "rider"})
# classic DeepGTAV vehicle classID per descriptor category
_CLASS_ID = {"car": 0, "truck": 0, "bus": 0, "motorcycle": 1, "bicycle": 2}

DEFAULT_THRESHOLD = 0.5
DEFAULT_POSITION_TOL_M = 2.0
DEFAULT_EGO_TOL_M = 5.0


@dataclass
class GroupValidation:
    """Outcome for one group: ``ok`` iff ``reasons`` is empty; ``structure`` maps every condition
    to its structure agreement with the reference (1.0 for the reference, nan when not computable)."""

    ok: bool
    reasons: list[str] = field(default_factory=list)
    structure: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------- GTA model keys


def joaat(text: str) -> int:
    """GTA's model-name hash (Jenkins one-at-a-time over the lower-cased name), 32 bits."""
    h = 0
    for byte in text.lower().encode("utf-8"):
        h = (h + byte) & 0xFFFFFFFF
        h = (h + (h << 10)) & 0xFFFFFFFF
        h ^= h >> 6
    h = (h + (h << 3)) & 0xFFFFFFFF
    h ^= h >> 11
    h = (h + (h << 15)) & 0xFFFFFFFF
    return h


def model_key(model: Any) -> int | None:
    """Comparable key of a model given as a name, a ``0x`` hex hash string or an int hash."""
    if isinstance(model, bool) or model is None:
        return None
    if isinstance(model, int):
        return model & 0xFFFFFFFF
    text = str(model).strip()
    if not text:
        return None
    if text.lower().startswith("0x"):
        try:
            return int(text, 16) & 0xFFFFFFFF
        except ValueError:
            return joaat(text)
    return joaat(text)


# --------------------------------------------------------------------------- entity states


def object_world_xy(descriptor: SceneDescriptor, obj: DynamicObject) -> tuple[float, float]:
    """World (x, y) of a descriptor object placed relative to the ego vehicle (GTA heading:
    degrees counter-clockwise from +y, so forward = (-sin h, cos h) and right = (cos h, sin h))."""
    loc = descriptor.location
    h = math.radians(loc.heading)
    fx, fy = -math.sin(h), math.cos(h)
    rx, ry = math.cos(h), math.sin(h)
    return (loc.x + obj.forward * fx + obj.right * rx, loc.y + obj.forward * fy + obj.right * ry)


def _entity_xy(entity: Mapping[str, Any]) -> tuple[float, float] | None:
    pos = entity.get("position")
    try:
        if isinstance(pos, (list, tuple)) and len(pos) >= 2:
            return float(pos[0]), float(pos[1])
        fur, bll = entity.get("FUR"), entity.get("BLL")
        if isinstance(fur, (list, tuple)) and isinstance(bll, (list, tuple)):
            return (float(fur[0]) + float(bll[0])) / 2.0, (float(fur[1]) + float(bll[1])) / 2.0
    except (TypeError, ValueError, IndexError):
        return None
    return None


def _reported(state: Mapping[str, Any], key: str) -> tuple[list[Mapping[str, Any]], bool]:
    """Entities listed under `key` and whether the list is authoritative (spawned flags present)."""
    raw = state.get(key)
    if not isinstance(raw, list):
        return [], False
    items = [e for e in raw if isinstance(e, Mapping)]
    flagged = any("spawned" in e for e in items)
    if flagged:
        items = [e for e in items if e.get("spawned")]
    return items, flagged


def entity_mismatches(
    descriptor: SceneDescriptor,
    state: Mapping[str, Any],
    position_tol_m: float = DEFAULT_POSITION_TOL_M,
    ego_tol_m: float = DEFAULT_EGO_TOL_M,
) -> list[str]:
    """Ways in which a backend-reported state disagrees with the descriptor (empty = agrees).
    Lists the state does not report (no "vehicles"/"peds"/"location" key) are not checked."""
    reasons: list[str] = []
    loc = state.get("location")
    if isinstance(loc, (list, tuple)) and len(loc) >= 2:
        try:
            d = math.hypot(float(loc[0]) - descriptor.location.x, float(loc[1]) - descriptor.location.y)
        except (TypeError, ValueError):
            d = math.inf
        if d > ego_tol_m:
            reasons.append(
                f"ego reported at ({_fmt(loc[0])}, {_fmt(loc[1])}), {d:.1f} m from the descriptor location "
                f"(tolerance {ego_tol_m} m)"
            )
    for key, kinds in (("vehicles", VEHICLE_CATEGORIES), ("peds", PED_CATEGORIES)):
        if key not in state:
            continue
        expected = [o for o in descriptor.objects if o.category in kinds]
        entities, authoritative = _reported(state, key)
        if authoritative and len(entities) != len(expected):
            reasons.append(f"{len(entities)} spawned {key} reported, descriptor has {len(expected)}")
        reasons.extend(_match(descriptor, expected, entities, key, position_tol_m))
    return reasons


def _compatible(obj: DynamicObject, entity: Mapping[str, Any], kind: str) -> bool:
    if "model" in entity and model_key(entity.get("model")) != model_key(obj.model):
        return False
    if kind == "vehicles" and isinstance(entity.get("classID"), int) and not isinstance(entity.get("classID"), bool):
        return entity["classID"] == _CLASS_ID[obj.category]
    return True


def _match(
    descriptor: SceneDescriptor,
    expected: list[DynamicObject],
    entities: list[Mapping[str, Any]],
    kind: str,
    tol: float,
) -> list[str]:
    positions = [_entity_xy(e) for e in entities]
    pairs = []
    for i, obj in enumerate(expected):
        ox, oy = object_world_xy(descriptor, obj)
        for j, (entity, xy) in enumerate(zip(entities, positions)):
            if xy is None or not _compatible(obj, entity, kind):
                continue
            d = math.hypot(xy[0] - ox, xy[1] - oy)
            if d <= tol:
                pairs.append((d, i, j))
    pairs.sort()
    used_obj: set[int] = set()
    used_ent: set[int] = set()
    for _, i, j in pairs:
        if i in used_obj or j in used_ent:
            continue
        used_obj.add(i)
        used_ent.add(j)
    reasons = []
    for i, obj in enumerate(expected):
        if i not in used_obj:
            ox, oy = object_world_xy(descriptor, obj)
            reasons.append(
                f"{obj.category} '{obj.model}' expected at ({ox:.1f}, {oy:.1f}) "
                f"(forward {obj.forward:g} m, right {obj.right:g} m): no reported {kind[:-1]} "
                f"of that model within {tol:g} m"
            )
    return reasons


def _fmt(v: Any) -> str:
    try:
        return f"{float(v):.1f}"
    except (TypeError, ValueError):
        return repr(v)


# --------------------------------------------------------------------------- structure agreement


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        if img.shape[2] >= 3:
            img = 0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]
        else:
            img = img[..., 0]
    if img.ndim != 2:
        raise ValueError(f"expected an HxW or HxWxC image, got shape {np.shape(image)}")
    if np.issubdtype(np.asarray(image).dtype, np.floating) and img.size and float(img.max()) <= 1.0:
        img = img * 255.0  # float images in [0, 1]: same scale as uint8 for the edge floor
    return img


def _gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sobel gradients of a binomially smoothed image (edge-replicated borders); the extra
    smoothing keeps orientations stable in dark, noisy variants."""
    q = np.pad(gray, 1, mode="edge")
    q = (q[:-2] + 2.0 * q[1:-1] + q[2:]) / 4.0
    gray = (q[:, :-2] + 2.0 * q[:, 1:-1] + q[:, 2:]) / 4.0
    p = np.pad(gray, 1, mode="edge")
    # [1 2 1]/4 smoothing both ways, then central differences: together a scaled Sobel operator
    s = (p[:-2] + 2.0 * p[1:-1] + p[2:]) / 4.0  # vertical smoothing, shape (H, W+2)
    gx = (s[:, 2:] - s[:, :-2]) / 2.0
    t = (p[:, :-2] + 2.0 * p[:, 1:-1] + p[:, 2:]) / 4.0  # horizontal smoothing, shape (H+2, W)
    gy = (t[2:] - t[:-2]) / 2.0
    return gx, gy


def reference_edges(
    gray: np.ndarray, edge_fraction: float = 0.15, min_gradient: float = 4.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge mask of the reference (the strongest `edge_fraction` of gradients above `min_gradient`
    grey levels per pixel) and its doubled-angle unit vectors (cos 2θ, sin 2θ)."""
    gx, gy = _gradients(gray)
    mag2 = gx * gx + gy * gy
    mag = np.sqrt(mag2)
    cut = max(float(np.quantile(mag, 1.0 - edge_fraction)) if mag.size else 0.0, min_gradient)
    mask = mag >= cut
    with np.errstate(invalid="ignore", divide="ignore"):
        c2 = np.where(mask, (gx * gx - gy * gy) / mag2, 0.0)
        s2 = np.where(mask, 2.0 * gx * gy / mag2, 0.0)
    return mask, c2, s2


def structure_agreement(
    reference: np.ndarray,
    variant: np.ndarray,
    edge_fraction: float = 0.15,
    min_gradient: float = 4.0,
) -> float:
    """Mean cos(2Δθ) between gradient orientations of `variant` and `reference` over the
    reference's edge pixels: ~1 for the same geometry under any illumination, ~0 for unrelated
    content, nan when the reference has no edges. Pixels where the variant is flat count as 0."""
    ref = _gray(reference)
    var = _gray(variant)
    if ref.shape != var.shape:
        raise ValueError(f"image sizes differ: {ref.shape} vs {var.shape}")
    return _agreement(reference_edges(ref, edge_fraction, min_gradient), var)


def _agreement(edges: tuple[np.ndarray, np.ndarray, np.ndarray], var: np.ndarray) -> float:
    mask, c2r, s2r = edges
    if not mask.any():
        return float("nan")
    gx, gy = _gradients(var)
    mag2 = gx * gx + gy * gy
    with np.errstate(invalid="ignore", divide="ignore"):
        c2v = np.where(mag2 > 1e-12, (gx * gx - gy * gy) / mag2, 0.0)
        s2v = np.where(mag2 > 1e-12, 2.0 * gx * gy / mag2, 0.0)
    agree = c2r * c2v + s2r * s2v
    return float(agree[mask].mean())


# --------------------------------------------------------------------------- group check


def validate_group(
    images: Mapping[str, np.ndarray],
    reference: str,
    descriptor: SceneDescriptor | None = None,
    states: Mapping[str, Mapping[str, Any]] | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    *,
    position_tol_m: float = DEFAULT_POSITION_TOL_M,
    ego_tol_m: float = DEFAULT_EGO_TOL_M,
    edge_fraction: float = 0.15,
    min_gradient: float = 4.0,
) -> GroupValidation:
    """Check one group X_k: same image size everywhere, backend states agreeing with the
    descriptor (when both are given), and structure agreement >= `threshold` for every variant."""
    reasons: list[str] = []
    structure: dict[str, float] = {}
    if reference not in images:
        return GroupValidation(
            False, [f"reference condition '{reference}' has no image (have: {', '.join(images)})"], {}
        )
    ref_img = np.asarray(images[reference])
    ref_shape = ref_img.shape[:2]
    ref_gray = _gray(ref_img)
    edges = reference_edges(ref_gray, edge_fraction, min_gradient)
    mask = edges[0]
    min_edges = max(20, int(0.002 * ref_gray.size))
    flat_reference = int(mask.sum()) < min_edges
    if flat_reference:
        reasons.append(
            f"reference '{reference}' has almost no edges ({int(mask.sum())} pixels); "
            "it is blank or not a rendered view"
        )
    for name, img in images.items():
        img = np.asarray(img)
        if name == reference:
            structure[name] = 1.0
            continue
        if img.shape[:2] != ref_shape:
            reasons.append(
                f"{name}: size {img.shape[1]}x{img.shape[0]} differs from reference "
                f"{ref_shape[1]}x{ref_shape[0]}"
            )
            structure[name] = float("nan")
            continue
        if flat_reference:
            structure[name] = float("nan")
            continue
        score = _agreement(edges, _gray(img))
        structure[name] = score
        if not score >= threshold:
            reasons.append(
                f"{name}: structure agreement {score:.2f} with '{reference}' is below {threshold:.2f} "
                "(different view or geometry)"
            )
    if states is not None and descriptor is not None:
        for name, state in states.items():
            if not isinstance(state, Mapping):
                reasons.append(f"{name}: backend state is {type(state).__name__}, not a JSON object")
                continue
            for why in entity_mismatches(descriptor, state, position_tol_m, ego_tol_m):
                reasons.append(f"{name}: {why}")
    return GroupValidation(not reasons, reasons, structure)


__all__: Iterable[str] = [
    "GroupValidation",
    "entity_mismatches",
    "joaat",
    "model_key",
    "object_world_xy",
    "structure_agreement",
    "validate_group",
]
