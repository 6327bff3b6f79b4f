"""Geometry of the procedural town: where its roads, markings, street furniture, buildings, walls,
fences, parks and countryside trees go, as primitives (pairedgta/scene/town_primitives.py).

`build_layout(town)` reads the parameters and the street grid of a ProceduralTownRegion
(pairedgta/scene/town.py, which calls it and is not imported here, so the imports point one way).
Every random draw comes from the town seed, so a layout is a function of the town's parameters.
"""
from __future__ import annotations

import numpy as np

from pairedgta.scene.town_primitives import COLUMNS, Builder, TownLayout, facing_vec, jitter, town_palette

_FACADES = (
    (0.70, 0.70, 0.68), (0.80, 0.72, 0.58), (0.55, 0.30, 0.24), (0.86, 0.85, 0.82),
    (0.42, 0.43, 0.45), (0.76, 0.60, 0.38), (0.62, 0.68, 0.74), (0.80, 0.56, 0.46),
    (0.60, 0.52, 0.44), (0.35, 0.30, 0.28),
)
_WALLS = ((0.62, 0.60, 0.56), (0.55, 0.36, 0.30), (0.74, 0.72, 0.66))  # concrete, brick, render
_FENCES = ((0.45, 0.40, 0.35), (0.30, 0.22, 0.15), (0.25, 0.28, 0.26), (0.62, 0.62, 0.60))  # wood, painted, metal


def build_layout(t) -> TownLayout:
    """The layout of town `t`: ground, roads and sidewalks, then markings, furniture, lots and countryside,
    in this order (each part draws from the seeded streams in turn, so reordering changes every town)."""
    rng = np.random.default_rng(t.town_seed)
    pal = town_palette(t.town_seed, t.material_variation)
    b = Builder()
    c = t.road_centres
    n = len(c)
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    length = t.road_half_length
    half = t.half_extent

    # terrain reaching the horizon, then lot ground inside the town
    far = length + 1500.0
    b.plane("grass", "terrain", -far, far, -far, far, -0.02, color=pal["grass"])

    # roads: east-west roads run the full length, north-south ones are cut at the junctions
    for cj in c:
        b.plane("asphalt", "road", -length, length, cj - hw, cj + hw, 0.0, pal["asphalt"])
    ns_spans = _spans(c, hw, length)
    for ci in c:
        for y0, y1 in ns_spans:
            b.plane("asphalt", "road", ci - hw, ci + hw, y0, y1, 0.0, pal["asphalt"])

    # sidewalks: north-south strips run through the corners, east-west strips fill between them
    ew_spans = _spans(c, hw + sw, length)
    for ci in c:
        for y0, y1 in ns_spans:
            for side in (-1, 1):
                x0, x1 = sorted((ci + side * hw, ci + side * (hw + sw)))
                b.box("sidewalk", "sidewalk", x0, x1, y0, y1, 0.0, kh, pal["paving"])
                kx0, kx1 = sorted((ci + side * hw, ci + side * (hw + 0.25)))
                b.box("kerb", "sidewalk", kx0, kx1, y0, y1, 0.0, kh + 0.01, pal["kerb"])
    for cj in c:
        for x0, x1 in ew_spans:
            for side in (-1, 1):
                y0, y1 = sorted((cj + side * hw, cj + side * (hw + sw)))
                b.box("sidewalk", "sidewalk", x0, x1, y0, y1, 0.0, kh, pal["paving"])
                ky0, ky1 = sorted((cj + side * hw, cj + side * (hw + 0.25)))
                b.box("kerb", "sidewalk", x0, x1, ky0, ky1, 0.0, kh + 0.01, pal["kerb"])

    _road_wear(t, b, pal)
    _markings(t, b, rng, pal["marking"])
    _street_furniture(t, b, rng)
    for i in range(n - 1):
        for j in range(n - 1):
            x0, x1 = c[i] + hw + sw, c[i + 1] - hw - sw
            y0, y1 = c[j] + hw + sw, c[j + 1] - hw - sw
            b.box("lot", "terrain", x0, x1, y0, y1, 0.0, kh, color=pal["grass"])
            if rng.random() < t.park_fraction:
                _park(t, b, rng, x0, x1, y0, y1)
            else:
                _urban_block(t, b, rng, x0, x1, y0, y1)
    _countryside(t, b, rng, half, length)
    return b.build(t.params(), half, length)


def _road_wear(t, b: Builder, pal) -> None:
    """Repair patches and resurfaced lanes in a darker or lighter asphalt, still labelled road."""
    rate = pal["wear"]
    if rate <= 0:
        return
    rng = np.random.default_rng([t.town_seed, 104729])
    hw = t.road_width / 2
    length = t.road_half_length
    spans = _spans(t.road_centres, hw + t.sidewalk_width, length)
    for axis in (0, 1):
        for rc in t.road_centres:
            for s0, s1 in spans:
                for _ in range(int(rng.poisson(rate * (s1 - s0) / 100.0))):
                    size = rng.uniform(1.5, 14.0)
                    a0 = rng.uniform(s0, max(s0, s1 - size))
                    lane = rng.uniform(0.6, 1.0) * hw
                    o0 = rng.uniform(-hw, hw - lane)
                    shade = rng.uniform(0.65, 1.5)
                    colour = tuple(float(np.clip(c * shade, 0, 1)) for c in pal["asphalt"])
                    z = float(rng.uniform(0.001, 0.003))  # below the markings (0.004), apart from each other
                    if axis == 0:
                        b.plane("asphalt", "road", rc + o0, rc + o0 + lane, a0, min(s1, a0 + size), z, colour)
                    else:
                        b.plane("asphalt", "road", a0, min(s1, a0 + size), rc + o0, rc + o0 + lane, z, colour)


def _markings(t, b: Builder, rng: np.random.Generator, white) -> None:
    c = t.road_centres
    hw, sw = t.road_width / 2, t.sidewalk_width
    length = t.road_half_length
    z = 0.004
    spans = _spans(c, hw + sw, length)
    for axis in (0, 1):
        for rc in c:
            for s0, s1 in spans:
                # dashed centre line, solid edge lines
                for d0 in np.arange(s0 + 1.5, s1 - 3.0, 9.0):
                    _strip(b, axis, rc, d0, d0 + 3.0, -0.075, 0.075, z, white)
                for e in (-1, 1):
                    _strip(b, axis, rc, s0, s1, e * (hw - 0.35), e * (hw - 0.23), z, white)
    # stop lines and zebra crossings at the junction mouths, right-hand lanes
    for xi in c:
        for yj in c:
            zebra = rng.random() < 0.6
            for axis in (0, 1):
                road, cross = (xi, yj) if axis == 0 else (yj, xi)
                for direction in (-1, 1):
                    mouth = cross + direction * (hw + sw)
                    if zebra:
                        b.crossings.append((axis, road, min(mouth, mouth - direction * 3.0),
                                            max(mouth, mouth - direction * 3.0), -hw + 0.6, hw - 0.1))
                        for k in np.arange(-hw + 0.6, hw - 0.4, 1.0):
                            _strip(b, axis, road, min(mouth, mouth - direction * 3.0),
                                   max(mouth, mouth - direction * 3.0), k, k + 0.5, z, white)
                    stop = mouth + direction * (3.6 if zebra else 0.3)
                    lane_sign = 1 if direction < 0 else -1  # traffic approaching this mouth keeps right
                    if axis == 1:
                        lane_sign = -lane_sign
                    _strip(b, axis, road, min(stop, stop + direction * 0.4), max(stop, stop + direction * 0.4),
                           *sorted((lane_sign * 0.15, lane_sign * (hw - 0.3))), z, white)


def _spans(c: np.ndarray, inset: float, length: float) -> list[tuple[float, float]]:
    """Intervals along a road between the junction bands (half width `inset`) and out to +-length."""
    inner = [(c[k] + inset, c[k + 1] - inset) for k in range(len(c) - 1)]
    return [(-length, c[0] - inset), *inner, (c[-1] + inset, length)]


def _strip(b: Builder, axis: int, road: float, a0: float, a1: float, o0: float, o1: float, z: float, color) -> None:
    """A marking rectangle spanning [a0, a1] along a road and [o0, o1] across it."""
    if a1 - a0 <= 0.01:
        return
    if axis == 0:  # north-south road at x=road
        b.plane("marking", "road", road + o0, road + o1, a0, a1, z, color)
    else:
        b.plane("marking", "road", a0, a1, road + o0, road + o1, z, color)


def _street_furniture(t, b: Builder, rng: np.random.Generator) -> None:
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    half = t.half_extent
    metal = (0.35, 0.36, 0.38)
    for axis in (0, 1):
        for rc in c:
            trees = rng.random() < t.street_tree_fraction
            for side in (-1, 1):
                offset = side * (hw + 0.6)
                phase = rng.uniform(0, t.lamp_spacing) if side > 0 else 0.0
                for s0, s1 in [(c[k] + hw + sw + 1.0, c[k + 1] - hw - sw - 1.0) for k in range(len(c) - 1)]:
                    start = s0 + (phase % t.lamp_spacing) * 0.5 + 2.0
                    for along in np.arange(start, s1 - 1.0, t.lamp_spacing):
                        b.lamp(axis, rc, along, offset, side, kh, metal)
                        mid = along + t.lamp_spacing / 2
                        if trees and mid < s1 - 2.0:
                            across = rc + side * (hw + sw * 0.55)
                            tx, ty = (across, mid) if axis == 0 else (mid, across)
                            b.tree(rng, tx, ty, kh, 0.7)
    # traffic lights and signs at every junction corner, facing the traffic that approaches it
    for xi in c:
        for yj in c:
            phase = int(rng.integers(2))  # 0: north-south green
            for dx, dy in ((1, -1), (-1, 1), (-1, -1), (1, 1)):
                px, py = xi + dx * (hw + 0.5), yj + dy * (hw + 0.5)
                # (1,-1) near-right corner for northbound traffic, (-1,1) for southbound,
                # (-1,-1) for westbound... pick the approach whose right-hand side this corner is
                if (dx, dy) == (1, -1):
                    facing, ns = 180.0, True     # faces south (-y), northbound traffic
                elif (dx, dy) == (-1, 1):
                    facing, ns = 0.0, True
                elif (dx, dy) == (1, 1):
                    facing, ns = 270.0, False    # faces east (+x), westbound traffic
                else:
                    facing, ns = 90.0, False
                if max(abs(px), abs(py)) > half:
                    continue
                green = (phase == 0) == ns
                b.traffic_light(px, py, kh, facing, green, metal)
                if rng.random() < t.junction_sign_fraction:
                    kind = ("disc", "triangle", "panel", "square", "direction", "direction")[int(rng.integers(6))]
                    sx_, sy_ = px + dx * 1.6 * (0 if ns else 1), py + dy * 1.6 * (1 if ns else 0)
                    b.sign(sx_, sy_, kh, facing, kind, metal)
    _street_signs(t, b, metal)
    _guard_railings(t, b)


def _street_signs(t, b: Builder, metal) -> None:
    """Signs along every street, at the kerb and facing the traffic of their side: Cityscapes has
    ~0.5 % sign pixels, which junction corners alone (one sign per approach at most) cannot give.
    Their own random stream, so the rest of the town keeps its draws."""
    rng = np.random.default_rng([t.town_seed, 15485863])
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    poles = np.asarray(b.rows.get(("cylinder", "metal", "pole"), []), dtype=np.float64).reshape(-1, len(COLUMNS))
    kinds = ("disc", "disc", "triangle", "panel", "square")
    for axis in (0, 1):
        for rc in c:
            for side in (-1, 1):
                facing = (180.0 if side > 0 else 0.0) if axis == 0 else (270.0 if side > 0 else 90.0)
                across = rc + side * (hw + 0.45)
                for s0, s1 in [(c[k] + hw + sw + 4.0, c[k + 1] - hw - sw - 4.0) for k in range(len(c) - 1)]:
                    for along in rng.uniform(s0, s1, size=int(rng.poisson(t.signs_per_100m * (s1 - s0) / 100))):
                        x, y = (across, along) if axis == 0 else (along, across)
                        if len(poles) and np.min(np.hypot(poles[:, 0] - x, poles[:, 1] - y)) < 1.5:
                            continue  # not on top of a lamp post or another sign
                        kind = kinds[int(rng.integers(len(kinds)))]
                        below = None
                        if rng.random() < 0.35:
                            below = "plate" if rng.random() < 0.6 else kinds[int(rng.integers(len(kinds)))]
                        b.sign(x, y, kh, facing, kind, metal, below)
                        poles = np.vstack([poles, [[x, y] + [0.0] * (len(COLUMNS) - 2)]])


def _guard_railings(t, b: Builder) -> None:
    """Pedestrian guard railings along the kerb after some junctions' crossings (fence)."""
    rng = np.random.default_rng([t.town_seed, 32452843])
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    colour = (0.30, 0.32, 0.33)
    for axis in (0, 1):
        for rc in c:
            for side in (-1, 1):
                o = rc + side * (hw + 0.3)
                for k in range(len(c) - 1):
                    for start, direction in ((c[k] + hw + sw, 1), (c[k + 1] - hw - sw, -1)):
                        if rng.random() >= t.railing_fraction:
                            continue
                        a0 = start + direction * 3.5  # beyond the zebra crossing of the junction mouth
                        a1 = a0 + direction * float(rng.uniform(6.0, 14.0))
                        a0, a1 = sorted((a0, a1))
                        if axis == 0:
                            b.fence(rng, o - 0.03, o + 0.03, a0, a1, kh, 1.0, "railing", colour)
                        else:
                            b.fence(rng, a0, a1, o - 0.03, o + 0.03, kh, 1.0, "railing", colour)


def _split(rng: np.random.Generator, lo: float, hi: float, smin: float, smax: float) -> list[float]:
    """Random cut positions from lo to hi with pieces in [smin, smax] (the last one absorbs slack)."""
    cuts = [lo]
    while hi - cuts[-1] > smax:
        cuts.append(cuts[-1] + rng.uniform(smin, smax))
        if hi - cuts[-1] < smin:
            cuts.pop()
            cuts.append((cuts[-1] + hi) / 2)
            break
    cuts.append(hi)
    return cuts


def _urban_block(t, b: Builder, rng, x0, x1, y0, y1) -> None:
    kh = t.kerb_height
    depth = min(18.0, (x1 - x0) / 2 - 4.0, (y1 - y0) / 2 - 4.0)
    xs = _split(rng, x0, x1, 9.0, 22.0)
    ys = _split(rng, y0, y1, 9.0, 22.0)
    floors_hi = int(rng.integers(t.min_floors, t.max_floors + 1))
    cells = []
    # perimeter parcels: south and north rows span full width, west/east columns fill between
    for k in range(len(xs) - 1):
        cells.append((xs[k], xs[k + 1], y0, y0 + depth, "s"))
        cells.append((xs[k], xs[k + 1], y1 - depth, y1, "n"))
    for k in range(len(ys) - 1):
        a, c_ = max(ys[k], y0 + depth), min(ys[k + 1], y1 - depth)
        if c_ - a > 4.0:
            cells.append((x0, x0 + depth, a, c_, "w"))
            cells.append((x1 - depth, x1, a, c_, "e"))
    for cx0, cx1, cy0, cy1, side in cells:
        if rng.random() < 0.85:
            setback = float(rng.choice([0.0, 0.0, 0.5, 1.5, 3.0]))
            gap = float(rng.choice([0.0, 0.0, 0.6]))
            bx0, bx1, by0, by1 = cx0 + gap / 2, cx1 - gap / 2, cy0 + gap / 2, cy1 - gap / 2
            if side == "s":
                by0 += setback
            elif side == "n":
                by1 -= setback
            elif side == "w":
                bx0 += setback
            else:
                bx1 -= setback
            floors = int(np.clip(floors_hi + rng.integers(-2, 3), t.min_floors, t.max_floors))
            _building(t, b, rng, bx0, bx1, by0, by1, kh, floors, side)
            if setback >= 1.5 and rng.random() < t.front_boundary_fraction:
                _front_boundary(b, rng, cx0, cx1, cy0, cy1, kh, side)
        else:
            _yard(b, rng, cx0, cx1, cy0, cy1, kh, side)
    # courtyard trees
    for _ in range(int(rng.integers(0, 5))):
        b.tree(rng, rng.uniform(x0 + depth + 2, x1 - depth - 2), rng.uniform(y0 + depth + 2, y1 - depth - 2), kh)


def _building(t, b: Builder, rng, x0, x1, y0, y1, z0, floors, street_side) -> None:
    fh = t.floor_height
    height = floors * fh + 0.6
    colour = jitter(rng, _FACADES[int(rng.integers(len(_FACADES)))], 0.04)
    b.box("facade", "building", x0, x1, y0, y1, z0, z0 + height, color=colour, solid=True)
    b.box("roof", "building", x0 + 0.2, x1 - 0.2, y0 + 0.2, y1 - 0.2, z0 + height, z0 + height + 0.5,
          color=jitter(rng, (0.35, 0.34, 0.33), 0.05))
    # windows on every face (street side gets a shop-front ground floor)
    faces = {
        "s": ((x0 + x1) / 2, y0, x1 - x0, 180.0),
        "n": ((x0 + x1) / 2, y1, x1 - x0, 0.0),
        "w": (x0, (y0 + y1) / 2, y1 - y0, 90.0),
        "e": (x1, (y0 + y1) / 2, y1 - y0, 270.0),
    }
    spacing = float(rng.uniform(2.8, 3.6))
    win_w = float(rng.uniform(1.1, 1.6))
    win_h = float(rng.uniform(1.3, 1.8))
    frame = jitter(rng, (0.25, 0.27, 0.30), 0.05)
    for side, (fx, fy, width, facing) in faces.items():
        nx, ny = facing_vec(facing)
        tx, ty = -ny, nx  # along the face
        cols = int((width - 1.0) // spacing)
        if cols < 1:
            continue
        offsets = (np.arange(cols) - (cols - 1) / 2) * spacing
        first = 0
        if side == street_side:
            first = 1
            shop = jitter(rng, (0.20, 0.22, 0.25), 0.04)
            for o in offsets:
                px, py = fx + tx * o + nx * 0.04, fy + ty * o + ny * 0.04
                b.add("panel", "window", "building", (px, py, z0 + 0.4), (min(spacing - 0.5, 2.6), 0, 2.3), facing,
                      shop,
                      a=float(rng.random()))
        for f in range(first, floors):
            zf = z0 + f * fh + 0.9
            for o in offsets:
                px, py = fx + tx * o + nx * 0.04, fy + ty * o + ny * 0.04
                b.add("panel", "window", "building", (px, py, zf), (win_w, 0, win_h), facing, frame,
                      a=float(rng.random()))


def _street_edge(x0, x1, y0, y1, side: str, thickness: float) -> tuple[float, float, float, float]:
    """The strip of a parcel along its street side ('s', 'n', 'w' or 'e'), `thickness` metres deep."""
    return {"s": (x0, x1, y0, y0 + thickness), "n": (x0, x1, y1 - thickness, y1),
            "w": (x0, x0 + thickness, y0, y1), "e": (x1 - thickness, x1, y0, y1)}[side]


def _yard(b: Builder, rng, x0, x1, y0, y1, kh, side) -> None:
    kind = int(rng.choice(3, p=[0.4, 0.3, 0.3]))  # wall, fence, hedge
    edge = _street_edge(x0, x1, y0, y1, side, 0.3)
    if kind == 0:
        b.box("wall", "wall", *edge, kh, kh + rng.uniform(1.4, 2.4), color=jitter(rng, _WALLS[int(rng.integers(3))]),
              solid=True)
    elif kind == 1:
        b.fence(rng, *edge, kh, float(rng.uniform(1.2, 1.9)), ("boards", "railing")[int(rng.integers(2))],
               jitter(rng, _FENCES[int(rng.integers(len(_FENCES)))]))
    else:
        ex0, ex1, ey0, ey1 = edge
        cx, cy = (ex0 + ex1) / 2, (ey0 + ey1) / 2
        if side in "sn":
            b.box("hedge", "vegetation", ex0, ex1, cy - 0.5, cy + 0.5, kh, kh + rng.uniform(1.0, 1.6),
                  color=jitter(rng, (0.18, 0.32, 0.10), 0.04))
        else:
            b.box("hedge", "vegetation", cx - 0.5, cx + 0.5, ey0, ey1, kh, kh + rng.uniform(1.0, 1.6),
                  color=jitter(rng, (0.18, 0.32, 0.10), 0.04))
    for _ in range(int(rng.integers(0, 3))):
        b.tree(rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), kh)


def _front_boundary(b: Builder, rng, x0, x1, y0, y1, kh, side) -> None:
    """A low garden wall or a fence along the street edge of a set-back building, with a gate."""
    ex0, ex1, ey0, ey1 = _street_edge(x0, x1, y0, y1, side, 0.25)
    along_x = side in "sn"
    a0, a1 = (ex0, ex1) if along_x else (ey0, ey1)
    gate = float(rng.uniform(a0 + 1.5, a1 - 2.7)) if a1 - a0 > 5.0 else None
    spans = [(a0, a1)] if gate is None else [(a0, gate), (gate + 1.2, a1)]
    wall = rng.random() < 0.55
    colour = jitter(rng, (_WALLS if wall else _FENCES)[int(rng.integers(3))])
    height = float(rng.uniform(0.6, 1.2)) if wall else float(rng.uniform(0.9, 1.5))
    style = ("boards", "railing")[int(rng.integers(2))]
    for s0, s1 in spans:
        px0, px1, py0, py1 = (s0, s1, ey0, ey1) if along_x else (ex0, ex1, s0, s1)
        if wall:
            b.box("wall", "wall", px0, px1, py0, py1, kh, kh + height, color=colour, solid=True)
        else:
            b.fence(rng, px0, px1, py0, py1, kh, height, style, colour)


def _park(t, b: Builder, rng, x0, x1, y0, y1) -> None:
    kh = t.kerb_height
    hedge = jitter(rng, (0.18, 0.32, 0.10), 0.04)
    edges = ((x0, x1, y0, y0 + 0.9), (x0, x1, y1 - 0.9, y1), (x0, x0 + 0.9, y0 + 0.9, y1 - 0.9),
             (x1 - 0.9, x1, y0 + 0.9, y1 - 0.9))
    railing = rng.random() < 0.35  # a metal railing on a low wall instead of a hedge
    colour = jitter(rng, _FENCES[2 + int(rng.integers(2))])
    for (ax0, ax1, ay0, ay1) in edges:
        # hedge or railing with an entrance gap in the middle
        if ax1 - ax0 > ay1 - ay0:
            mid = (ax0 + ax1) / 2
            pieces = ((ax0, mid - 2, ay0 + 0.3, ay1 - 0.3), (mid + 2, ax1, ay0 + 0.3, ay1 - 0.3))
        else:
            mid = (ay0 + ay1) / 2
            pieces = ((ax0 + 0.3, ax1 - 0.3, ay0, mid - 2), (ax0 + 0.3, ax1 - 0.3, mid + 2, ay1))
        for px0, px1, py0, py1 in pieces:
            if railing:
                b.box("wall", "wall", px0, px1, py0, py1, kh, kh + 0.45, color=jitter(rng, _WALLS[0]), solid=True)
                b.fence(rng, px0, px1, py0, py1, kh + 0.45, 1.1, "railing", colour, solid=False)
            else:
                b.box("hedge", "vegetation", px0, px1, py0, py1, kh, kh + 1.2, color=hedge)
    for _ in range(int(rng.integers(8, 18))):
        b.tree(rng, rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3), kh, float(rng.uniform(0.9, 1.4)))


def _countryside(t, b: Builder, rng, half, length) -> None:
    placed = 0
    tries = 0
    while placed < t.countryside_trees and tries < 20 * max(1, t.countryside_trees):
        tries += 1
        x, y = rng.uniform(-length - 60, length + 60, size=2)
        if max(abs(x), abs(y)) < half + 4 or t.surface_at(x, y) != "other":
            continue
        keep_off = t.road_width / 2 + t.sidewalk_width + 3
        if t.road_centre_distance(x) < keep_off or t.road_centre_distance(y) < keep_off:
            continue
        b.tree(rng, x, y, 0.0, float(rng.uniform(1.0, 1.6)))
        placed += 1


__all__ = ["build_layout"]
