"""Object models (cars, trucks, buses, two-wheelers, people, riders) as primitive rows in the
object's local frame, real-world dimensions; pure numpy, no bpy."""
from __future__ import annotations

import zlib

from pairedgta.errors import RendererError


def _row(shape, material, c, s, yaw=0.0, color=(1, 1, 1), a=0.0):
    return shape, material, (*c, *s, yaw, *color, a)


def _rgb(c) -> tuple[float, float, float]:
    return tuple(float(v) / 255.0 for v in c)  # type: ignore[return-value]


def _car(p, s):
    rows = [
        _row("box", "paint", (0, 0, 0.22), (1.8, 4.5, 0.62), color=p),
        _row("box", "paint", (0, -0.25, 0.84), (1.56, 2.3, 0.56), color=p),
        _row("panel", "glass", (0, 0.905, 0.9), (1.4, 0, 0.44)),
        _row("panel", "glass", (0, -1.405, 0.9), (1.4, 0, 0.42), 180),
        _row("panel", "glass", (0.785, -0.25, 0.9), (2.0, 0, 0.42), 270),
        _row("panel", "glass", (-0.785, -0.25, 0.9), (2.0, 0, 0.42), 90),
        _row("box", "trim", (0, 2.25, 0.2), (1.82, 0.12, 0.28), color=s),
        _row("box", "trim", (0, -2.25, 0.2), (1.82, 0.12, 0.28), color=s),
        _row("panel", "headlight", (0.6, 2.255, 0.58), (0.35, 0, 0.14)),
        _row("panel", "headlight", (-0.6, 2.255, 0.58), (0.35, 0, 0.14)),
        _row("panel", "taillight", (0.62, -2.255, 0.6), (0.3, 0, 0.14), 180),
        _row("panel", "taillight", (-0.62, -2.255, 0.6), (0.3, 0, 0.14), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.24, 0.66, 0.66)) for x in (-0.8, 0.8) for y in (-1.38, 1.38)]
    return rows, [(0.0, 2.4, 0.6)]


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


def _person(p, s, model):
    h = zlib.crc32(model.encode())
    skin, hair = _SKIN[h % 4], _HAIR[(h // 4) % 4]
    rows = [
        _row("box", "matte", (0.1, 0, 0.05), (0.15, 0.18, 0.83), color=s),
        _row("box", "matte", (-0.1, 0, 0.05), (0.15, 0.18, 0.83), color=s),
        _row("box", "rubber", (0.1, 0.04, 0), (0.14, 0.27, 0.07)),
        _row("box", "rubber", (-0.1, 0.04, 0), (0.14, 0.27, 0.07)),
        _row("box", "matte", (0, 0, 0.86), (0.42, 0.24, 0.6), color=p),
        _row("box", "matte", (0.27, 0, 0.88), (0.1, 0.12, 0.58), color=p),
        _row("box", "matte", (-0.27, 0, 0.88), (0.1, 0.12, 0.58), color=p),
        _row("box", "matte", (0.27, 0, 0.78), (0.08, 0.09, 0.1), color=skin),
        _row("box", "matte", (-0.27, 0, 0.78), (0.08, 0.09, 0.1), color=skin),
        _row("box", "matte", (0, 0, 1.45), (0.1, 0.1, 0.07), color=skin),
        _row("sphere", "matte", (0, 0, 1.5), (0.21, 0.24, 0.25), color=skin),
        _row("sphere", "matte", (0, -0.015, 1.615), (0.22, 0.25, 0.14), color=hair),
    ]
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


def model_parts(category: str, model: str, color, secondary) -> tuple[list[tuple[str, str, str, tuple]], list[tuple]]:
    """Parts (label, shape, material, row) and head-light spots of one dynamic object."""
    p, s = _rgb(color), _rgb(secondary)
    if category == "car":
        rows, spots = _car(p, s)
    elif category == "truck":
        rows, spots = _truck(p, s)
    elif category == "bus":
        rows, spots = _bus(p, s)
    elif category == "motorcycle":
        rows, spots = _motorcycle(p, s)
    elif category == "bicycle":
        rows, spots = _bicycle(p, s)
    elif category == "person":
        rows, spots = _person(p, s, model)
    elif category == "rider":
        # a rider is drawn on the vehicle it rides (bicycle unless the model names a motorbike);
        # the vehicle keeps its own class and shares the rider's instance id
        moto = "motor" in model.lower() or "bike" == model.lower()
        vehicle, spots = (_motorcycle if moto else _bicycle)((0.2, 0.2, 0.22), (0.1, 0.1, 0.1))
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



__all__ = ["model_parts"]
