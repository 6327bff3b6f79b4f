"""Object models (cars, trucks, buses, two-wheelers, people, riders) as primitive rows in the
object's local frame (x right, y forward, z up), real-world dimensions; pure numpy, no bpy.

Rows have a 12th column, a pitch about the local x axis through the row's base centre, so that
legs and arms can swing (walking poses). Cars take their size from the model name
(pairedgta.scene.population.CAR_MODELS: compacts, saloons, estates, SUVs, vans)."""
from __future__ import annotations

import math
import zlib

from pairedgta.errors import RendererError
from pairedgta.scene.population import CAR_DEFAULT, CAR_MODELS


def _row(shape, material, c, s, yaw=0.0, color=(1, 1, 1), a=0.0, pitch=0.0):
    return shape, material, (*c, *s, yaw, *color, a, pitch)


def _rgb(c) -> tuple[float, float, float]:
    return tuple(float(v) / 255.0 for v in c)  # type: ignore[return-value]


def _car(p, s, dims=CAR_DEFAULT):
    """Body, cabin with glass all round, bumpers, grille, plates, mirrors, four wheels, head and
    tail lights; proportions follow the size (a tall car is a van or an SUV)."""
    length, width, height = dims
    van, suv = height > 1.95, 1.65 < height <= 1.95
    clear = 0.2
    belt = clear + (0.9 if van else 0.72 if suv else 0.6)
    cab_len = length * (0.8 if van else 0.6 if suv or length > 4.8 or length < 4.0 else 0.5)
    cab_y = -length / 2 + cab_len / 2 + length * (0.02 if van else 0.1 if suv else 0.12 if length > 4.0 else 0.04)
    cab_w = width * 0.88
    top = height - belt
    front, rear = length / 2, -length / 2
    r = 0.36 if van or suv else 0.32
    rows = [
        _row("box", "paint", (0, 0, clear), (width, length, belt - clear), color=p),
        _row("box", "paint", (0, cab_y, belt), (cab_w, cab_len, top), color=p),
        _row("box", "paint", (0, cab_y, height - 0.04), (cab_w * 0.9, cab_len * 0.94, 0.04), color=p),
        # glass: windscreen, rear window, two side windows each side split by a pillar
        _row("panel", "glass", (0, cab_y + cab_len / 2 + 0.005, belt + 0.06), (cab_w - 0.12, 0, top - 0.14)),
        _row("panel", "glass", (0, cab_y - cab_len / 2 - 0.005, belt + 0.08), (cab_w - 0.16, 0, top - 0.18), 180),
    ]
    for sx, yaw in ((1, 270), (-1, 90)):
        seg = (cab_len - 0.4) / 2
        for k in (-1, 1):
            rows.append(_row("panel", "glass", (sx * (cab_w / 2 + 0.005), cab_y + k * (seg / 2 + 0.06), belt + 0.07),
                             (seg, 0, top - 0.16), yaw))
        rows.append(_row("box", "paint", (sx * (width / 2 + 0.06), cab_y + cab_len / 2 - 0.15, belt + 0.02),
                         (0.14, 0.08, 0.1), color=p))  # mirror
    rows += [
        _row("box", "trim", (0, front - 0.06, clear - 0.02), (width + 0.02, 0.14, 0.3), color=s),
        _row("box", "trim", (0, rear + 0.06, clear - 0.02), (width + 0.02, 0.14, 0.3), color=s),
        _row("panel", "trim", (0, front + 0.005, belt - 0.3), (width * 0.36, 0, 0.16), color=(0.05, 0.05, 0.05)),
        _row("panel", "matte", (0, front + 0.015, clear + 0.04), (0.5, 0, 0.12), color=(0.9, 0.9, 0.86)),
        _row("panel", "matte", (0, rear - 0.015, clear + 0.08), (0.5, 0, 0.12), 180, color=(0.9, 0.9, 0.86)),
    ]
    for sx in (-1, 1):
        rows.append(_row("panel", "headlight", (sx * (width / 2 - 0.3), front + 0.01, belt - 0.26), (0.36, 0, 0.14)))
        rows.append(_row("panel", "taillight", (sx * (width / 2 - 0.22), rear - 0.01, belt - 0.24), (0.3, 0, 0.16),
                         180))
    rows += [_row("xcyl", "rubber", (x * (width / 2 - 0.12), y * (length * 0.31), 0), (0.24, 2 * r, 2 * r))
             for x in (-1, 1) for y in (-1, 1)]
    rows += [_row("xcyl", "metal", (x * (width / 2 - 0.005), y * (length * 0.31), r * 0.45), (0.02, r, r),
                  color=(0.55, 0.56, 0.58)) for x in (-1, 1) for y in (-1, 1)]  # hubs
    return rows, [(0.0, front + 0.1, belt - 0.2)]


def _truck(p, s):
    rows = [
        _row("box", "paint", (0, 2.6, 0.55), (2.4, 2.3, 2.3), color=p),
        _row("panel", "glass", (0, 3.755, 1.75), (2.1, 0, 0.85)),
        _row("panel", "glass", (1.205, 2.9, 1.75), (1.0, 0, 0.75), 270),
        _row("panel", "glass", (-1.205, 2.9, 1.75), (1.0, 0, 0.75), 90),
        _row("box", "matte", (0, -1.1, 0.95), (2.45, 5.1, 2.75), color=s),
        _row("box", "rubber", (0, 0, 0.45), (1.2, 7.4, 0.35)),
        _row("box", "trim", (0, 3.8, 0.35), (2.4, 0.12, 0.35), color=(0.3, 0.3, 0.3)),
        _row("panel", "headlight", (0.85, 3.755, 0.8), (0.35, 0, 0.18)),
        _row("panel", "headlight", (-0.85, 3.755, 0.8), (0.35, 0, 0.18)),
        _row("panel", "taillight", (0.95, -3.655, 0.62), (0.25, 0, 0.15), 180),
        _row("panel", "taillight", (-0.95, -3.655, 0.62), (0.25, 0, 0.15), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.35, 1.0, 1.0)) for x in (-1.05, 1.05) for y in (2.6, -1.8, -3.0)]
    return rows, [(0.0, 3.9, 0.8)]


def _bus(p, s):
    rows = [
        _row("box", "paint", (0, 0, 0.3), (2.55, 12.0, 2.9), color=p),
        _row("panel", "glass", (1.28, -0.3, 1.3), (10.6, 0, 1.25), 270),
        _row("panel", "glass", (-1.28, -0.3, 1.3), (10.6, 0, 1.25), 90),
        _row("panel", "trim", (1.28, 0, 0.75), (11.8, 0, 0.3), 270, color=s),
        _row("panel", "trim", (-1.28, 0, 0.75), (11.8, 0, 0.3), 90, color=s),
        _row("panel", "glass", (0, 6.005, 1.05), (2.3, 0, 1.9)),
        _row("panel", "glass", (0, -6.005, 1.9), (2.1, 0, 0.9), 180),
        _row("panel", "headlight", (0.95, 6.005, 0.55), (0.4, 0, 0.2)),
        _row("panel", "headlight", (-0.95, 6.005, 0.55), (0.4, 0, 0.2)),
        _row("panel", "taillight", (1.0, -6.005, 0.7), (0.25, 0, 0.35), 180),
        _row("panel", "taillight", (-1.0, -6.005, 0.7), (0.25, 0, 0.35), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.35, 1.0, 1.0)) for x in (-1.1, 1.1) for y in (4.0, -3.6)]
    return rows, [(0.0, 6.1, 0.6)]


def _motorcycle(p, s):
    rows = [
        _row("xcyl", "rubber", (0, 0.72, 0), (0.13, 0.62, 0.62)),
        _row("xcyl", "rubber", (0, -0.72, 0), (0.13, 0.62, 0.62)),
        _row("box", "paint", (0, 0.05, 0.5), (0.32, 0.9, 0.38), color=p),
        _row("box", "metal", (0, 0.0, 0.26), (0.3, 0.5, 0.26), color=(0.3, 0.3, 0.32)),
        _row("box", "rubber", (0, -0.45, 0.78), (0.3, 0.65, 0.1)),
        _row("box", "paint", (0, -0.72, 0.64), (0.2, 0.5, 0.06), color=s),
        _row("box", "metal", (0, 0.68, 0.3), (0.08, 0.08, 0.75), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.62, 1.0), (0.75, 0.05, 0.05), color=(0.6, 0.6, 0.62)),
        _row("box", "paint", (0, 0.7, 0.8), (0.2, 0.12, 0.2), color=p),
        _row("panel", "headlight", (0, 0.765, 0.83), (0.15, 0, 0.14)),
        _row("panel", "taillight", (0, -0.975, 0.64), (0.12, 0, 0.06), 180),
    ]
    return rows, [(0.0, 0.85, 0.9)]


def _bicycle(p, s):
    frame = p
    rows = [
        _row("xring", "rubber", (0, 0.53, 0), (0.04, 0.68, 0.68)),
        _row("xring", "rubber", (0, -0.53, 0), (0.04, 0.68, 0.68)),
        _row("box", "paint", (0, 0.05, 0.76), (0.04, 0.6, 0.04), color=frame),
        _row("box", "paint", (0, 0.06, 0.44), (0.04, 0.56, 0.04), color=frame),
        _row("box", "paint", (0, -0.22, 0.34), (0.04, 0.04, 0.44), color=frame),
        _row("box", "paint", (0, 0.35, 0.42), (0.04, 0.04, 0.4), color=frame),
        _row("box", "paint", (0, -0.38, 0.33), (0.03, 0.32, 0.03), color=frame),
        _row("box", "metal", (0, 0.5, 0.34), (0.03, 0.03, 0.28), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.35, 0.82), (0.03, 0.03, 0.16), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.35, 0.97), (0.56, 0.03, 0.03), color=(0.2, 0.2, 0.2)),
        _row("box", "metal", (0, -0.22, 0.78), (0.03, 0.03, 0.08), color=(0.6, 0.6, 0.62)),
        _row("box", "rubber", (0, -0.24, 0.85), (0.12, 0.26, 0.05)),
    ]
    return rows, []


_SKIN = ((0.94, 0.78, 0.66), (0.80, 0.60, 0.45), (0.58, 0.40, 0.28), (0.36, 0.24, 0.17))
_HAIR = ((0.10, 0.08, 0.06), (0.35, 0.22, 0.12), (0.70, 0.58, 0.35), (0.25, 0.25, 0.25))


def _limb(rows, material, color, top, length, size, pitch, parts=1):
    """A limb hanging from `top` (x, y, z), swung by `pitch` degrees (+ = forward); returns its end."""
    x, y, z = top
    a = math.radians(180.0 + pitch)
    rows.append(_row("box", material, (x, y, z), (size[0], size[1], length), color=color, pitch=180.0 + pitch))
    return x, y - math.sin(a) * length, z + math.cos(a) * length


def _person(p, s, model, scale=1.0, pose=0.0):
    """Head, hair, neck, torso, hips, two-part arms with hands, legs with shoes. `pose` in [-1, 1]
    swings the legs (and the arms against them) by up to 24 degrees; `scale` sets the height
    (1.0 = 1.75 m). Skin, hair, sleeves and a bag follow the model name."""
    h = zlib.crc32(model.encode())
    skin, hair = _SKIN[h % 4], _HAIR[(h // 4) % 4]
    long_hair = "_f_" in model
    short_sleeves, bag = (h >> 4) % 3 == 0, (h >> 6) % 4 == 0
    k = scale
    swing = 24.0 * max(-1.0, min(1.0, pose))
    leg = 0.84 * k
    hip = leg * math.cos(math.radians(swing)) + 0.06 * k
    rows = []
    for sx in (-1, 1):
        fx, fy, fz = _limb(rows, "matte", s, (sx * 0.1 * k, 0.0, hip), leg, (0.15 * k, 0.17 * k), sx * swing)
        rows.append(_row("box", "rubber", (fx, fy + 0.05 * k, max(fz - 0.06 * k, 0.0)), (0.12 * k, 0.27 * k, 0.08 * k)))
    chest = hip + 0.55 * k
    rows += [
        _row("box", "matte", (0, 0, hip - 0.1 * k), (0.36 * k, 0.21 * k, 0.18 * k), color=s),
        _row("box", "matte", (0, 0, hip - 0.02 * k), (0.4 * k, 0.23 * k, 0.57 * k), color=p),
        _row("box", "matte", (0, 0, chest - 0.02 * k), (0.1 * k, 0.1 * k, 0.09 * k), color=skin),
        _row("sphere", "matte", (0, 0.01 * k, chest + 0.04 * k), (0.2 * k, 0.23 * k, 0.25 * k), color=skin),
        _row("sphere", "matte", (0, -0.015 * k, chest + 0.15 * k), (0.215 * k, 0.245 * k, 0.15 * k), color=hair),
    ]
    if long_hair:
        rows.append(_row("box", "matte", (0, -0.08 * k, chest - 0.06 * k), (0.2 * k, 0.07 * k, 0.24 * k), color=hair))
    if bag:
        rows.append(_row("box", "matte", (0, -0.17 * k, hip + 0.2 * k), (0.3 * k, 0.14 * k, 0.34 * k),
                         color=(0.12, 0.12, 0.14)))
    for sx in (-1, 1):
        shoulder = (sx * 0.255 * k, 0.0, chest - 0.06 * k)
        a = -sx * swing * 0.8
        elbow = _limb(rows, "matte", p, shoulder, 0.3 * k, (0.095 * k, 0.11 * k), a)
        wrist = _limb(rows, "matte", skin if short_sleeves else p, elbow, 0.27 * k, (0.085 * k, 0.095 * k), a)
        _limb(rows, "matte", skin, wrist, 0.09 * k, (0.08 * k, 0.09 * k), a)
    return rows, []


def _rider_body(p, s, model, seat_y, hip, reach, helmet):
    h = zlib.crc32(model.encode())
    skin = _SKIN[h % 4]
    rows = [
        _row("box", "matte", (x, seat_y + 0.2, hip - 0.12), (0.14, 0.42, 0.16), color=s) for x in (-0.12, 0.12)
    ] + [
        _row("box", "matte", (x, seat_y + 0.4, 0.22), (0.13, 0.14, hip - 0.3), color=s) for x in (-0.13, 0.13)
    ] + [
        _row("box", "matte", (0, seat_y + 0.08, hip), (0.4, 0.24, 0.58), color=p),
        _row("box", "matte", (0.24, seat_y + 0.08 + reach / 2, hip + 0.4), (0.09, reach, 0.09), color=p),
        _row("box", "matte", (-0.24, seat_y + 0.08 + reach / 2, hip + 0.4), (0.09, reach, 0.09), color=p),
        _row("box", "matte", (0, seat_y + 0.08, hip + 0.58), (0.1, 0.1, 0.07), color=skin),
        _row("sphere", "matte", (0, seat_y + 0.08, hip + 0.63), (0.21, 0.24, 0.25), color=skin),
    ]
    if helmet:
        rows.append(_row("sphere", "paint", (0, seat_y + 0.07, hip + 0.68), (0.29, 0.32, 0.25), color=s))
    return rows


# rider models of GTA V and the vehicle each one rides
RIDER_VEHICLE = {
    "a_m_y_motox_01": "motorcycle", "a_m_y_motox_02": "motorcycle", "u_m_y_baygor": "motorcycle",
    "a_m_y_cyclist_01": "bicycle", "a_m_y_roadcyc_01": "bicycle", "a_m_y_bikerider": "bicycle",
}


def rider_vehicle(model: str) -> str:
    """'motorcycle' or 'bicycle': the known rider models, else motorbike words in the name."""
    name = model.lower()
    if name in RIDER_VEHICLE:
        return RIDER_VEHICLE[name]
    return "motorcycle" if any(w in name for w in ("moto", "biker", "chopper", "scooter")) else "bicycle"


_BIKE_PAINTS = ((0.7, 0.05, 0.05), (0.05, 0.05, 0.06), (0.9, 0.9, 0.9), (0.1, 0.25, 0.6), (0.9, 0.5, 0.05),
                (0.15, 0.5, 0.15))
_UNLIT = {"headlight": "headlight_off", "taillight": "taillight_off"}


def model_parts(category: str, model: str, color, secondary, scale: float = 1.0, pose: float = 0.0,
                lit: bool = True) -> tuple[list[tuple[str, str, str, tuple]], list[tuple]]:
    """Parts (label, shape, material, row) and head-light spots of one object. `scale`/`pose` shape
    people (height, walking phase); `lit=False` (parked vehicles) keeps head and tail lights dark."""
    parts, spots = _parts(category, model, color, secondary, scale, pose)
    if not lit:
        parts = [(label, shape, _UNLIT.get(m, m), row) for label, shape, m, row in parts]
        spots = []
    return parts, spots


def _parts(category, model, color, secondary, scale, pose):
    p, s = _rgb(color), _rgb(secondary)
    if category == "car":
        rows, spots = _car(p, s, CAR_MODELS.get(model, CAR_DEFAULT))
    elif category == "truck":
        rows, spots = _truck(p, s)
    elif category == "bus":
        rows, spots = _bus(p, s)
    elif category == "motorcycle":
        rows, spots = _motorcycle(p, s)
    elif category == "bicycle":
        rows, spots = _bicycle(p, s)
    elif category == "person":
        rows, spots = _person(p, s, model, scale, pose)
    elif category == "rider":
        # a rider is drawn on the vehicle it rides (rider_vehicle); the vehicle keeps its own class
        # and shares the rider's instance id
        moto = rider_vehicle(model) == "motorcycle"
        frame = _BIKE_PAINTS[zlib.crc32(f"{model}{color}".encode()) % len(_BIKE_PAINTS)] if moto else (0.2, 0.2, 0.22)
        vehicle, spots = (_motorcycle if moto else _bicycle)(frame, (0.1, 0.1, 0.1))
        vlabel = "motorcycle" if moto else "bicycle"
        body = _rider_body(p, s, model, -0.3 if moto else -0.24, 0.86 if moto else 0.9, 0.55 if moto else 0.5, moto)
        parts = [(vlabel, *r) for r in vehicle] + [("rider", *r) for r in body]
        return parts, spots
    else:
        raise RendererError(
            f"dynamic object category '{category}' has no Blender model; use one of "
            "car, truck, bus, motorcycle, bicycle, person, rider"
        )
    return [(category, *r) for r in rows], spots


__all__ = ["RIDER_VEHICLE", "model_parts", "rider_vehicle"]
