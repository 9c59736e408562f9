"""The hard family: street scenes randomised on purpose, so that façade extraction is judged on what it was not
tuned to (docs/simulator.md, "Hard family").

Against the standard scene it adds: set-backs of 0-5 m and gaps of 1-14 m between buildings (side walls and
gables scanned at grazing angles; about half of the side walls blank), corner plots whose side wall is a full
façade, irregular window grids with sizes varying inside a façade, ground-floor sills from 0.1 to 1.2 m, shop
fronts with full-height glazing, flush / recessed / garage doors, three kinds of glazing (glass panes a few cm
behind the wall plane that return only a share of the pulses, curtains that return them all, open windows with
a room behind), frames, shutters, balconies, cornices, vans and more trees in front. Campaigns differ in lane,
speed, sensor height, profile rate and scanner (one yawed profiler or two crossed ones) and carry GPS drift
(:func:`campaign_setup`, :func:`gps_drift`).

Everything is drawn from ``params.seed`` with streams of its own, so the standard scene is unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pyproj import CRS
from shapely.geometry import Polygon

from lidarmap.frame import LocalFrame
from lidarmap.sim.buildings import (
    ROOM_HEIGHT,
    Building,
    Element,
    Facade,
    building_soup,
    inward_depth,
    make_building,
    make_facades,
    make_shell,
    row_to_local,
)
from lidarmap.sim.city import (
    CRS_EPSG,
    Car,
    City,
    _layout_rows,
    _rotation,
    _streets_and_terrain,
    _street_trees,
    _yard_trees,
    cars_soup,
    ground_colour,
    trees_soup,
)
from lidarmap.sim.mesh import (
    CLASS_BUILDING,
    CLASS_OTHER,
    GLASS,
    KIND,
    Labels,
    SceneMesh,
    Soup,
    boxes,
    rotate_z,
)
from lidarmap.sim.params import SimParams
from lidarmap.sim.terrain import Terrain

SETBACK = (0.0, 5.0)  # metres behind the building line
GAP = (1.0, 14.0)  # metres between neighbouring buildings of a row
BLANK_SIDE_WALLS = 0.5  # share of side and rear walls without any opening
VAN_SHARE = 0.35  # share of parked vehicles that are vans (2.2-2.7 m tall: they hide ground floors)
TREES_FACTOR = 1.4  # street trees per 100 m, relative to params.trees_per_100m
SILL = (0.1, 1.2)  # ground-floor window sills above the floor, metres
GLASS_DEPTH = (0.03, 0.20)  # glass pane behind the wall plane, metres
CURTAIN_DEPTH = (0.10, 0.20)  # curtain behind the wall plane, metres
GLAZING = (("glass", 0.5), ("curtain", 0.25), ("open", 0.25))  # kinds of window and their shares
GLASS_REFLECTANCE = 0.06  # glass returns are weak (low intensity)
EDGE_MARGIN = 0.5  # openings keep this far from a façade's ends
# campaigns
LANE = (0.6, 3.2)  # |lane offset| from the street axis, metres
SPEED = (4.0, 10.0)  # m/s
SENSOR_HEIGHT = (1.9, 3.4)  # m above the road
RATE = (60.0, 140.0)  # profiles per second
SINGLE_YAW = (5.0, 20.0)  # one profiler yawed this far from "across the driving direction", degrees
PAIR_YAW = (30.0, 45.0)  # two profilers yawed ±this, degrees
PAIR_ANGULAR_STEP = 0.6  # degrees between pulses of each of the two profilers (two heads share the pulse budget)


@dataclasses.dataclass
class Van(Car):
    """A parked van: one tall box on wheels."""


@dataclasses.dataclass
class HardCity(City):
    """A :class:`City` whose parked vehicles include vans."""

    def draw_cars(self, rng: np.random.Generator) -> list[Car]:
        cars = super().draw_cars(rng)
        vans = rng.random(len(cars)) < VAN_SHARE
        out: list[Car] = []
        for car, van in zip(cars, vans):
            if van:
                car = Van(x=car.x, y=car.y, ground_z=car.ground_z, heading=car.heading,
                          length=float(rng.uniform(5.0, 6.2)), width=float(rng.uniform(1.95, 2.1)),
                          height=float(rng.uniform(2.2, 2.7)), rgb=(235, 235, 238))
            out.append(car)
        return out

    def scene(self, cars: list[Car]) -> SceneMesh:
        vans = [c for c in cars if isinstance(c, Van)]
        others = [c for c in cars if not isinstance(c, Van)]
        parts = [self.static]
        if others:
            parts.append(cars_soup(others).build())
        if vans:
            parts.append(vans_soup(vans).build())
        return SceneMesh.concatenate(parts) if len(parts) > 1 else self.static


def vans_soup(vans: list[Van]) -> Soup:
    """Vans as one box from 0.35 m above the ground to their roof (rays pass under them between the wheels)."""
    lo = np.array([[-v.length / 2, -v.width / 2, 0.35] for v in vans])
    hi = np.array([[v.length / 2, v.width / 2, v.height] for v in vans])
    tris, owner = boxes(lo, hi)
    centre = np.array([[v.x, v.y, v.ground_z] for v in vans])
    heading = np.array([v.heading for v in vans])
    tris = rotate_z(tris, heading[owner][:, None]) + centre[owner][:, None, :]
    soup = Soup()
    soup.add(tris, Labels(classification=CLASS_OTHER, kind=KIND["car"], rgb=np.array([v.rgb for v in vans]),
                          reflectance=0.55), index=owner)
    return soup


# --- the city ----------------------------------------------------------------------------------------------------

def build_hard_city(params: SimParams) -> HardCity:
    """The deterministic hard-family city of ``params.seed``."""
    rng = np.random.default_rng([params.seed, 1, 18])
    n_streets = params.streets or (1 if params.buildings <= 10 else 2)
    rows = _layout_rows(rng, params.buildings, n_streets, setback=SETBACK, l_share=0.3, gap=GAP)
    street_ys, shifts, streets, bounds, terrain = _streets_and_terrain(rng, rows, n_streets)
    glass_return = (params.glass_return_min, params.glass_return_max)
    buildings = _place_buildings(rng, rows, street_ys, shifts, terrain, glass_return)
    trees = (_street_trees(rng, streets, terrain, TREES_FACTOR * params.trees_per_100m)
             + _yard_trees(rng, buildings, streets, terrain, bounds))
    angle = _rotation(rng)
    origin = (500000.0 + rng.uniform(200.0, 800.0), 5800000.0 + rng.uniform(200.0, 800.0), 0.0)
    soup = terrain.soup(lambda xy: ground_colour(xy, streets))
    for b in buildings:
        soup.extend(building_soup(b))
        soup.extend(_glazing_soup(b))
    soup.extend(trees_soup(rng, trees))
    return HardCity(params=params, crs=CRS.from_epsg(CRS_EPSG), frame=LocalFrame(offset=origin, rotation_deg=angle),
                    terrain=terrain, streets=streets, buildings=buildings, trees=trees, static=soup.build())


def _place_buildings(rng: np.random.Generator, rows: dict, street_ys: list[float], shifts: dict,
                     terrain: Terrain, glass_return: tuple[float, float]) -> list[Building]:
    buildings: list[Building] = []
    shells = []
    next_facade, next_element = 1, 1
    for (s, side), row in rows.items():
        houses = [i for i, (_, shape) in enumerate(row["rings"]) if shape != "shell"]
        for i, (ring_rc, shape) in enumerate(row["rings"]):
            ring = row_to_local(ring_rc, street_ys[s], side, shifts[(s, side)])
            if shape == "shell":
                shells.append((ring, (street_ys[s], side)))
                continue
            b = make_building(rng, len(buildings) + 1, ring, terrain, shape)
            b.facades = make_facades(b, terrain, (street_ys[s], side), next_facade)
            next_facade += len(b.facades)
            corner = -1 if i == houses[0] else (1 if i == houses[-1] else 0)  # row end: a corner plot
            for f in b.facades:
                role = facade_role(b, f, corner)
                next_element = fill_facade(rng, b, f, role, next_element, glass_return)
            buildings.append(b)
    for ring, street_side in shells:
        b = make_shell(rng, len(buildings) + 1, ring, terrain)
        b.facades = make_facades(b, terrain, street_side, next_facade)
        next_facade += len(b.facades)
        buildings.append(b)
    return buildings


def facade_role(b: Building, f: Facade, corner: int) -> str:
    """"street", "corner" (the outer side wall of a row's end: a full façade), "side" or "rear"."""
    if f.street_facing:
        return "street"
    nx = f.normal[0]
    if abs(nx) > 0.99:  # walls across the street: seen (if at all) at grazing angles
        xs = b.ring[:, 0]
        outer = (corner < 0 and nx < 0 and abs(f.origin[0] - xs.min()) < 1e-6) or \
                (corner > 0 and nx > 0 and abs(f.origin[0] - xs.max()) < 1e-6)
        return "corner" if outer else "side"
    return "rear"


# --- façades -------------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class _Rhythm:
    """Per-façade randomised rhythm (drawn for each façade, so walls of one building differ)."""

    ground_h: float
    floor_h: float
    sill: float  # ground-floor sill above the floor
    upper_sill: float
    win_h: float
    spacing: float
    frames: bool
    shutters: bool
    balconies: bool
    cornice: bool
    glass_return: tuple[float, float]  # bounds of the share of pulses a glass pane returns

    @classmethod
    def draw(cls, rng: np.random.Generator, glass_return: tuple[float, float]) -> _Rhythm:
        return cls(glass_return=glass_return, ground_h=rng.uniform(3.3, 4.5), floor_h=rng.uniform(2.8, 3.4),
                   sill=rng.uniform(*SILL),
                   upper_sill=rng.uniform(0.75, 1.1), win_h=rng.uniform(1.2, 1.8), spacing=rng.uniform(2.2, 3.8),
                   frames=rng.random() < 0.6, shutters=rng.random() < 0.3, balconies=rng.random() < 0.3,
                   cornice=rng.random() < 0.6)

    def levels(self, b: Building) -> np.ndarray:
        levels = [b.floor_z]
        while levels[-1] + (self.ground_h if len(levels) == 1 else self.floor_h) + ROOM_HEIGHT <= b.eave_z - 0.6:
            levels.append(levels[-1] + (self.ground_h if len(levels) == 1 else self.floor_h))
        return np.array(levels)


def fill_facade(rng: np.random.Generator, b: Building, f: Facade, role: str, next_id: int,
                glass_return: tuple[float, float]) -> int:
    """Openings and structures of one façade by its role; returns the next free element id."""
    if f.width < 2 * EDGE_MARGIN + 0.8:
        return next_id
    if role in ("side", "rear") and rng.random() < BLANK_SIDE_WALLS:
        return next_id
    r = _Rhythm.draw(rng, glass_return)
    levels = r.levels(b)
    o_z = f.origin[2]
    top_limit = b.eave_z - o_z - (0.7 if r.cornice else 0.3)
    openings: list[Element] = []
    full = role in ("street", "corner")
    openings += _ground_floor(rng, f, r, levels, role, top_limit)
    for k, level in enumerate(levels[1:], start=1):
        height = levels[k + 1] - level if k + 1 < len(levels) else b.eave_z - level
        openings += _upper_floor(rng, f, r, level - o_z, min(level - o_z + height - 0.25, top_limit),
                                 sparse=not full)
    elements: list[Element] = []
    for e in openings:
        e.id = next_id + len(elements)
        elements.append(e)
    _rooms(rng, b, f, elements, levels)
    structures = _structures(rng, f, r, elements, levels, b) if full else []
    for e in structures:
        e.id = next_id + len(elements)
        elements.append(e)
    f.elements = elements
    return next_id + len(elements)


def _opening(f: Facade, kind: str, subtype: str, s0: float, s1: float, t0: float, t1: float, depth: float,
             glazing: str, return_fraction: float = 1.0) -> Element:
    return Element(id=-1, facade_id=f.id, kind=kind, subtype=subtype, s0=float(s0), s1=float(s1), t0=float(t0),
                   t1=float(t1), depth=float(depth), glazing=glazing, return_fraction=float(return_fraction))


def _window(rng: np.random.Generator, f: Facade, r: _Rhythm, s0: float, s1: float, t0: float, t1: float,
            subtype: str = "window", glazing: str | None = None) -> Element:
    """A window with a drawn glazing: glass (partial returns), curtain (full returns) or open (room behind)."""
    names = [g for g, _ in GLAZING]
    kind = glazing or str(rng.choice(names, p=[p for _, p in GLAZING]))
    fraction = 1.0
    if kind == "glass":
        depth = -rng.uniform(*GLASS_DEPTH)
        fraction = rng.uniform(*r.glass_return)
    elif kind == "curtain":
        depth = -rng.uniform(*CURTAIN_DEPTH)
    else:
        depth = -rng.uniform(0.08, 0.25)  # the reveal of an open window: its sill and jambs are this deep
    e = _opening(f, "window", subtype, s0, s1, t0, t1, depth, kind, fraction)
    if r.frames and depth < -0.06 and min(s1 - s0, t1 - t0) > 0.5:
        e.frame = (float(rng.uniform(0.05, 0.09)), float(-rng.uniform(0.02, min(0.05, -depth - 0.02))))
    return e


def _pack(rng: np.random.Generator, widths: list[float], width: float) -> list[tuple[int, float]]:
    """Place items of ``widths`` left to right with random gaps; (item index, s0) of those that fit, centred."""
    placed, s = [], 0.0
    for i, w in enumerate(widths):
        gap = rng.uniform(0.5, 1.6) if placed else 0.0
        if s + gap + w > width - 2 * EDGE_MARGIN:
            continue
        placed.append((i, s + gap))
        s += gap + w
    offset = EDGE_MARGIN + rng.uniform(0.0, max(0.0, width - 2 * EDGE_MARGIN - s))
    return [(i, offset + s0) for i, s0 in placed]


def _ground_floor(rng: np.random.Generator, f: Facade, r: _Rhythm, levels: np.ndarray, role: str,
                  top_limit: float) -> list[Element]:
    """Doors (flush, recessed, garage), shop windows with full-height glazing and windows with low to high sills."""
    floor = levels[0] - f.origin[2]
    ceiling = min(floor + (r.ground_h if len(levels) > 1 else top_limit - floor) - 0.3, top_limit)
    items: list[tuple[str, float]] = []
    if role == "street" or (role == "corner" and rng.random() < 0.5) or (role == "side" and rng.random() < 0.25):
        items.append(("door", rng.uniform(0.9, 1.5)))
        if role == "street" and rng.random() < 0.3:
            items.append(("door", rng.uniform(0.9, 1.3)))
    if role == "street" and rng.random() < 0.25:
        items.append(("garage", rng.uniform(2.4, 3.0)))
    shop = role == "street" and rng.random() < 0.35
    n_windows = int(rng.integers(1, 6)) if role in ("street", "corner") else int(rng.integers(0, 3))
    for _ in range(n_windows):
        items.append(("shop", rng.uniform(2.0, 4.5)) if shop and rng.random() < 0.7
                     else ("window", rng.uniform(0.6, 1.8)))
    order = rng.permutation(len(items))
    items = [items[i] for i in order]
    out = []
    for i, s0 in _pack(rng, [w for _, w in items], f.width):
        name, w = items[i]
        if name == "door":
            h = min(rng.uniform(2.05, 2.5), ceiling - floor)
            style = "flush" if rng.random() < 0.4 else "recessed"
            depth = -rng.uniform(0.02, 0.05) if style == "flush" else -rng.uniform(0.15, 0.5)
            out.append(_opening(f, "door", "door", s0, s0 + w, floor, floor + h, depth, style))
        elif name == "garage":
            h = min(rng.uniform(2.1, 2.5), ceiling - floor)
            out.append(_opening(f, "door", "garage", s0, s0 + w, floor, floor + h, -rng.uniform(0.02, 0.12),
                                "garage"))
        elif name == "shop":
            t0 = floor + rng.uniform(0.05, 0.45)
            t1 = min(floor + rng.uniform(2.4, 3.0), ceiling)
            if t1 - t0 > 1.2:
                out.append(_window(rng, f, r, s0, s0 + w, t0, t1, subtype="shop_window", glazing="glass"))
        else:
            t0 = floor + float(np.clip(r.sill + rng.normal(0.0, 0.06), *SILL))
            t1 = min(t0 + rng.uniform(1.0, 1.9), ceiling)
            if t1 - t0 > 0.5:
                out.append(_window(rng, f, r, s0, s0 + w, t0, t1))
    return out


def _upper_floor(rng: np.random.Generator, f: Facade, r: _Rhythm, floor: float, ceiling: float,
                 sparse: bool) -> list[Element]:
    """An irregular row of windows: jittered columns, widths varying per column, some skipped, some tall."""
    n_cols = int((f.width - 2 * EDGE_MARGIN) // r.spacing)
    if n_cols < 1 or ceiling - floor < 1.2:
        return []
    centres = f.width / 2 + (np.arange(n_cols) - (n_cols - 1) / 2) * r.spacing
    centres = centres + rng.uniform(-0.25, 0.25, n_cols)
    widths = rng.uniform(0.6, 1.8, n_cols)
    widths = np.minimum(widths, r.spacing - 0.6)
    skip = rng.random(n_cols) < (0.6 if sparse else 0.12)
    out = []
    for c, w, gone in zip(centres, widths, skip):
        if gone:
            continue
        s0, s1 = max(EDGE_MARGIN, c - w / 2), min(f.width - EDGE_MARGIN, c + w / 2)
        tall = rng.random() < 0.15
        t0 = floor + (rng.uniform(0.05, 0.2) if tall else r.upper_sill + rng.normal(0.0, 0.05))
        t1 = min(t0 + (rng.uniform(2.0, 2.4) if tall else r.win_h + rng.normal(0.0, 0.08)), ceiling)
        if s1 - s0 > 0.45 and t1 - t0 > 0.6:
            out.append(_window(rng, f, r, s0, s1, t0, t1))
    return out


def _rooms(rng: np.random.Generator, b: Building, f: Facade, elements: list[Element], levels: np.ndarray) -> None:
    """Rooms behind open windows and half of the glass ones (the rest show a dark absorber)."""
    poly: Polygon = b.polygon
    inward = -f.normal[:2]
    floors = levels - f.origin[2]
    for e in elements:
        if e.kind != "window" or e.glazing == "curtain" or (e.glazing == "glass" and rng.random() < 0.5):
            continue
        others = [o for o in elements if o is not e and o.t0 < e.t1 and o.t1 > e.t0]
        left = min([e.s0 - o.s1 for o in others if o.s1 <= e.s0] + [e.s0 - 0.3])
        right = min([o.s0 - e.s1 for o in others if o.s0 >= e.s1] + [f.width - 0.3 - e.s1])
        rs0, rs1 = e.s0 - max(0.0, min(0.5, left / 2 - 0.05)), e.s1 + max(0.0, min(0.5, right / 2 - 0.05))
        base = f.origin[:2]
        available = min(inward_depth(poly, base + s * f.u[:2], inward) for s in (rs0, (rs0 + rs1) / 2, rs1))
        depth = min(rng.uniform(2.0, 5.0), available + e.depth - 0.4)
        if depth < 1.5:
            continue
        below = floors[floors <= e.t0 + 1e-9]
        t_floor = (below.max() if len(below) else e.t0 - 0.05) + 0.02
        t_ceiling = max(t_floor + ROOM_HEIGHT - 0.02, e.t1 + 0.2)
        e.room = (float(rs0), float(rs1), float(t_floor), float(t_ceiling), float(e.depth - depth))
        e.has_interior = True


def _structures(rng: np.random.Generator, f: Facade, r: _Rhythm, openings: list[Element], levels: np.ndarray,
                b: Building) -> list[Element]:
    """Shutters beside upper windows, balconies under some of them, cornices under the eave and the first floor."""
    o_z = f.origin[2]
    rects: list[tuple[str, float, float, float, float, float]] = []
    windows = [e for e in openings if e.kind == "window" and e.t0 > levels[0] - o_z + 2.0]
    for e in windows:
        others = [o for o in openings if o is not e and o.t0 < e.t1 and o.t1 > e.t0]
        left = min([e.s0 - o.s1 for o in others if o.s1 <= e.s0] + [e.s0])
        right = min([o.s0 - e.s1 for o in others if o.s0 >= e.s1] + [f.width - e.s1])
        leaf = (e.s1 - e.s0) / 2
        if r.shutters and min(left, right) / 2 - 0.05 >= leaf:
            proud = rng.uniform(0.03, 0.06)
            rects.append(("shutter", e.s0 - 0.03 - leaf, e.s0 - 0.03, e.t0, e.t1, proud))
            rects.append(("shutter", e.s1 + 0.03, e.s1 + 0.03 + leaf, e.t0, e.t1, proud))
        elif r.balconies and rng.random() < 0.5 and min(left, right) > 0.7:
            level = levels[levels <= e.t0 + o_z + 1e-9].max() - o_z
            rects.append(("balcony", e.s0 - 0.3, e.s1 + 0.3, level - 0.15, level + 1.0, rng.uniform(0.6, 1.2)))
    if r.cornice:
        eave = b.eave_z - o_z
        rects.append(("cornice", 0.0, f.width, eave - 0.5, eave - 0.1, rng.uniform(0.2, 0.4)))
        if len(levels) > 1:
            band = levels[1] - o_z
            clear = all(not (o.t0 < band - 0.05 and o.t1 > band - 0.35) for o in openings)
            if clear:
                rects.append(("cornice", 0.0, f.width, band - 0.35, band - 0.05, rng.uniform(0.12, 0.25)))
    return [Element(id=-1, facade_id=f.id, kind="structure", subtype=name, s0=float(s0), s1=float(s1),
                    t0=float(t0), t1=float(t1), depth=float(proud)) for name, s0, s1, t0, t1, proud in rects]


# --- glazing and frames in the ray-casting mesh ----------------------------------------------------------------------

def _glazing_soup(b: Building) -> Soup:
    """Glass panes (partial returns, low intensity), curtains (full returns) and window frames."""
    soup = Soup()
    for f in b.facades:
        windows = [e for e in f.elements if e.kind == "window"]
        for glazing, kind in (("glass", "glass"), ("curtain", "curtain")):
            panes = [e for e in windows if e.glazing == glazing]
            if not panes:
                continue
            lo = np.array([[e.s0, e.t0, e.depth] for e in panes])
            hi = np.array([[e.s1, e.t1, 0.0] for e in panes])
            tris, owner = boxes(lo, hi, faces=("z0",))
            glass = glazing == "glass"
            soup.add(f.to_local(tris), Labels(
                classification=CLASS_BUILDING, kind=KIND[kind], building_id=b.id, facade_id=f.id,
                element_id=np.array([e.id for e in panes]), behaviour=GLASS if glass else 0,
                rgb=(70, 90, 100) if glass else (225, 215, 200), reflectance=GLASS_REFLECTANCE if glass else 0.5,
                return_fraction=np.array([e.return_fraction for e in panes])), index=owner)
        framed = [e for e in windows if e.frame is not None]
        if framed:
            lo, hi, ids = [], [], []
            for e in framed:
                w, front = e.frame
                for s0, s1, t0, t1 in ((e.s0, e.s0 + w, e.t0, e.t1), (e.s1 - w, e.s1, e.t0, e.t1),
                                       (e.s0 + w, e.s1 - w, e.t0, e.t0 + w), (e.s0 + w, e.s1 - w, e.t1 - w, e.t1)):
                    lo.append([s0, t0, e.depth])
                    hi.append([s1, t1, front])
                    ids.append(e.id)
            tris, owner = boxes(np.array(lo), np.array(hi), faces=("x0", "x1", "y0", "y1", "z1"))
            soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["window_reveal"],
                                              building_id=b.id, facade_id=f.id, element_id=np.array(ids),
                                              rgb=(235, 235, 230), reflectance=0.5), index=owner)
    return soup


# --- campaigns -------------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class CampaignSetup:
    """How one hard-family campaign differs: the parameters it scans with, its lane and its scanner heads."""

    params: SimParams  # mls_speed, mls_sensor_height, mls_rate and mls_angular_step of this campaign
    lane_offset: float  # metres right of the street axis (negative: left), seen in the driving direction
    yaws: tuple[float, ...]  # yaw of each scanner head's profile plane, degrees

    def to_json(self) -> dict:
        p = self.params
        return {"scanner": "one yawed profiler" if len(self.yaws) == 1 else "two crossed profilers",
                "yaws_deg": list(self.yaws), "rate": p.mls_rate, "angular_step": p.mls_angular_step,
                "sensor_height": p.mls_sensor_height}


def campaign_setup(params: SimParams, index: int) -> CampaignSetup:
    """Lane, speed, sensor height, profile rate and scanner of campaign ``index`` (its own random stream)."""
    rng = np.random.default_rng([params.seed, 18, index])
    lane = float(rng.choice([-1.0, 1.0]) * rng.uniform(*LANE))
    pair = rng.random() < 0.5
    if pair:
        yaw = float(rng.uniform(*PAIR_YAW))
        yaws: tuple[float, ...] = (yaw, -yaw)
    else:
        yaws = (float(rng.choice([-1.0, 1.0]) * rng.uniform(*SINGLE_YAW)),)
    scan = dataclasses.replace(params, mls_speed=float(rng.uniform(*SPEED)),
                               mls_sensor_height=float(rng.uniform(*SENSOR_HEIGHT)),
                               mls_rate=float(round(rng.uniform(*RATE))),
                               mls_angular_step=PAIR_ANGULAR_STEP if pair else params.mls_angular_step)
    return CampaignSetup(params=scan, lane_offset=lane, yaws=yaws)


@dataclasses.dataclass
class Drift:
    """Smooth GPS drift of a campaign: CRS offsets (metres) sampled every second, linear in between."""

    time: np.ndarray
    offset: np.ndarray  # (N, 3)

    def at(self, t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, self.time, self.offset[:, k]) for k in range(3)])

    def to_json(self) -> dict:
        return {"formula": "p_file = misregistration(p_true) + drift(gps_time), linear between samples",
                "samples": [[float(t), *map(float, o)] for t, o in zip(self.time, self.offset)]}


def gps_drift(params: SimParams, index: int, t0: float, t1: float) -> Drift:
    """A drift made of slow sinusoids (periods 15-120 s) reaching 50-100 % of the configured bounds."""
    rng = np.random.default_rng([params.seed, 19, index])
    time = np.arange(np.floor(t0) - 1.0, np.ceil(t1) + 2.0)
    waves = np.zeros((len(time), 3))
    for k in range(3):
        for _ in range(3):
            period = rng.uniform(15.0, 120.0)
            waves[:, k] += rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * time / period + rng.uniform(0, 2 * np.pi))
    horizontal = np.linalg.norm(waves[:, :2], axis=1).max()
    vertical = np.abs(waves[:, 2]).max()
    waves[:, :2] *= rng.uniform(0.5, 1.0) * params.gps_drift_horizontal / max(horizontal, 1e-9)
    waves[:, 2] *= rng.uniform(0.5, 1.0) * params.gps_drift_vertical / max(vertical, 1e-9)
    return Drift(time=time, offset=waves)
