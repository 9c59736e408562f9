"""Procedural buildings: footprints, roofs, façades with windows, doors and structures, and their meshes.

All geometry is built in the local (street-aligned) frame. Façade elements are made in façade coordinates
(s, t, d) -- s along u, t up, d along the outward normal n = u x z -- and mapped to the frame at the end, so
the truth rectangles and the meshes cannot disagree.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from shapely.geometry import LineString, Polygon

from lidarmap.facade.model import FacadeFrame
from lidarmap.sim.mesh import (
    ABSORBER,
    CLASS_BUILDING,
    KIND,
    Labels,
    Soup,
    boxes,
    holed_rectangle,
    quads,
)
from lidarmap.sim.terrain import Terrain

UP = np.array([0.0, 0.0, 1.0])
WALL_BELOW = 0.5  # walls reach this far below the lowest terrain point of the footprint
ROOM_HEIGHT = 2.7  # floor-to-ceiling height of the rooms seen through windows
ABSORBER_DEPTH = 0.3  # depth of the dark box behind windows that show nothing

WALL_COLOURS = [((232, 222, 198), 0.55), ((240, 240, 234), 0.6), ((166, 86, 64), 0.35), ((222, 196, 130), 0.5),
                ((176, 176, 170), 0.45), ((200, 170, 150), 0.45)]
FLAT_ROOF_COLOURS = [((118, 118, 112), 0.3), ((72, 72, 78), 0.15), ((150, 146, 138), 0.35)]
PITCHED_ROOF_COLOURS = [((150, 62, 46), 0.25), ((62, 66, 76), 0.15), ((120, 80, 60), 0.25)]


@dataclasses.dataclass
class Element:
    """A window, door or structure of a façade: rectangle [s0, s1] x [t0, t1] at depth ``depth``.

    ``depth`` is d of the element's own surface: the glass plane / door leaf (negative, recessed) or the front of a
    structure (positive). Windows with ``has_interior`` show a room whose back wall is at d = ``room[4]``.
    """

    id: int
    facade_id: int
    kind: str  # "window" | "door" | "structure"
    subtype: str  # "window" | "door" | "balcony" | "pilaster"
    s0: float
    s1: float
    t0: float
    t1: float
    depth: float
    has_interior: bool = False
    room: tuple[float, float, float, float, float] | None = None  # s0, s1, t0, t1, d_back
    glazing: str = ""  # hard family windows: "glass" | "curtain" | "open"; doors: "flush" | "recessed" | "garage"
    return_fraction: float = 1.0  # glass: share of the pulses the pane returns
    frame: tuple[float, float] | None = None  # hard family: frame width and the depth of its front (d, negative)

    @property
    def rect(self) -> tuple[float, float, float, float]:
        return (self.s0, self.s1, self.t0, self.t1)


@dataclasses.dataclass
class Facade:
    """One wall of a building: origin (bottom-left seen from outside, at the lowest terrain along it) and u."""

    id: int
    building_id: int
    origin: np.ndarray
    u: np.ndarray
    width: float
    t_bottom: float
    t_eave: float
    t_top: float
    street_facing: bool
    elements: list[Element] = dataclasses.field(default_factory=list)

    @property
    def frame(self) -> FacadeFrame:
        """The façade's frame (in the city's local coordinates): the same conventions as the map's."""
        return FacadeFrame(origin=self.origin, u=self.u)

    @property
    def normal(self) -> np.ndarray:
        return self.frame.normal

    def basis(self) -> np.ndarray:
        return self.frame.basis()

    def to_local(self, sdt: np.ndarray) -> np.ndarray:
        """Façade coordinates (..., 3) to the local frame (triangles (M, 3, 3) too: FacadeFrame takes (N, 3))."""
        sdt = np.asarray(sdt, dtype=np.float64)
        return self.frame.to_crs(sdt.reshape(-1, 3)).reshape(sdt.shape)

    def to_facade(self, xyz: np.ndarray) -> np.ndarray:
        """Local points (..., 3) to façade coordinates."""
        xyz = np.asarray(xyz, dtype=np.float64)
        return self.frame.to_facade(xyz.reshape(-1, 3)).reshape(xyz.shape)


@dataclasses.dataclass
class Building:
    """A building (or the construction site): footprint ring (CCW, local), levels, roof and façades."""

    id: int
    status: str  # "existing" | "under construction"
    shape: str  # "rectangle" | "L" | "shell"
    ring: np.ndarray  # (N, 2) CCW, not closed
    base_z: float  # lowest terrain point along the outline
    floor_z: float  # ground-floor level
    eave_z: float
    top_z: float
    roof_type: str  # "flat" | "gabled" | "hipped" | "none"
    ridge_edge: int = -1  # gabled/hipped: index of the footprint edge the ridge runs parallel to
    planned_height: float | None = None
    facades: list[Facade] = dataclasses.field(default_factory=list)
    wall_rgb: tuple[int, int, int] = (200, 200, 200)
    wall_reflectance: float = 0.5
    roof_rgb: tuple[int, int, int] = (120, 120, 120)
    roof_reflectance: float = 0.3

    @property
    def polygon(self) -> Polygon:
        return Polygon(self.ring)

    @property
    def height(self) -> float:
        return self.top_z - self.base_z


# --- footprints ------------------------------------------------------------------------------------------------

def footprint_ring(rng: np.random.Generator, a0: float, front: float, l_shape: bool) -> tuple[np.ndarray, float, float]:
    """A rectangle or L footprint in row coordinates (a along the street, b away from it); CCW ring, width, depth.

    The wing of an L sits behind the main block so the street façade stays one straight wall.
    """
    w = rng.uniform(10.0, 20.0)
    d = rng.uniform(8.0, 14.0)
    if not l_shape:
        ring = [(a0, front), (a0 + w, front), (a0 + w, front + d), (a0, front + d)]
        return np.array(ring), w, d
    ww = rng.uniform(0.35, 0.5) * w
    wd = rng.uniform(5.0, 9.0)
    if rng.random() < 0.5:
        ring = [(a0, front), (a0 + w, front), (a0 + w, front + d), (a0 + ww, front + d), (a0 + ww, front + d + wd),
                (a0, front + d + wd)]
    else:
        ring = [(a0, front), (a0 + w, front), (a0 + w, front + d + wd), (a0 + w - ww, front + d + wd),
                (a0 + w - ww, front + d), (a0, front + d)]
    return np.array(ring), w, d + wd


def row_to_local(ring: np.ndarray, street_y: float, side: int, shift: float) -> np.ndarray:
    """Row coordinates to the local frame (x = a + shift, y = street_y + side * b), kept counter-clockwise."""
    xy = np.column_stack([ring[:, 0] + shift, street_y + side * ring[:, 1]])
    return xy if side > 0 else xy[::-1].copy()


def outline_heights(terrain: Terrain, ring: np.ndarray, step: float = 0.25) -> list[np.ndarray]:
    """Terrain heights sampled along each edge of a ring."""
    out = []
    for p, q in zip(ring, np.roll(ring, -1, axis=0)):
        n = max(2, int(np.ceil(np.linalg.norm(q - p) / step)) + 1)
        f = np.linspace(0.0, 1.0, n)[:, None]
        out.append(terrain.height(p + f * (q - p)))
    return out


def make_building(rng: np.random.Generator, bid: int, ring: np.ndarray, terrain: Terrain, shape: str) -> Building:
    """Levels, roof and colours of an existing building on ``ring`` (façades are added separately)."""
    heights = outline_heights(terrain, ring)
    base_z = float(min(h.min() for h in heights))
    floor_z = float(max(h.max() for h in heights)) + 0.15
    total = rng.uniform(6.5, 28.0)
    roof_type = "flat" if shape == "L" else str(rng.choice(["flat", "gabled", "hipped"], p=[0.3, 0.4, 0.3]))
    edges = np.roll(ring, -1, axis=0) - ring
    lengths = np.linalg.norm(edges, axis=1)
    ridge_edge, rise = -1, 0.0
    if roof_type == "hipped" and abs(lengths[0] - lengths[1]) < 2.0:
        roof_type = "gabled"  # a near-square hip roof degenerates into a pyramid; keep the ridge well defined
    if roof_type == "gabled":
        ridge_edge = 0 if rng.random() < 0.7 else 1  # edge 0 is along the street: ridge parallel to it mostly
    elif roof_type == "hipped":
        ridge_edge = int(np.argmax(lengths[:2]))
    if roof_type != "flat":
        half_span = lengths[(ridge_edge + 1) % 4] / 2
        rise = half_span * np.tan(np.radians(rng.uniform(25.0, 42.0)))
    eave_z = max(base_z + total - rise, floor_z + 3.3)
    wall, wall_r = WALL_COLOURS[rng.integers(len(WALL_COLOURS))]
    roofs = FLAT_ROOF_COLOURS if roof_type == "flat" else PITCHED_ROOF_COLOURS
    roof, roof_r = roofs[rng.integers(len(roofs))]
    return Building(id=bid, status="existing", shape=shape, ring=ring, base_z=base_z, floor_z=floor_z,
                    eave_z=float(eave_z), top_z=float(eave_z + rise), roof_type=roof_type, ridge_edge=ridge_edge,
                    wall_rgb=wall, wall_reflectance=wall_r, roof_rgb=roof, roof_reflectance=roof_r)


def make_shell(rng: np.random.Generator, bid: int, ring: np.ndarray, terrain: Terrain) -> Building:
    """The construction site: a roofless shell of walls a few metres high; its footprint carries the planned height."""
    heights = outline_heights(terrain, ring)
    base_z = float(min(h.min() for h in heights))
    floor_z = float(max(h.max() for h in heights)) + 0.15
    top = floor_z + rng.uniform(3.0, 6.0)
    return Building(id=bid, status="under construction", shape="shell", ring=ring, base_z=base_z, floor_z=floor_z,
                    eave_z=float(top), top_z=float(top), roof_type="none",
                    planned_height=float(round(rng.uniform(10.0, 18.0), 2)), wall_rgb=(185, 182, 175),
                    wall_reflectance=0.4, roof_rgb=(185, 182, 175), roof_reflectance=0.4)


# --- façades and their elements --------------------------------------------------------------------------------

def gable_edges(b: Building) -> set[int]:
    """Footprint edges that end in a gable (wall up to the ridge)."""
    if b.roof_type != "gabled":
        return set()
    return {(b.ridge_edge + 1) % 4, (b.ridge_edge + 3) % 4}


def make_facades(b: Building, terrain: Terrain, street_side: tuple[float, int], first_id: int) -> list[Facade]:
    """One façade per footprint edge; the street façade is the one on the street's building line."""
    street_y, side = street_side
    toward_street = np.array([0.0, -float(side), 0.0])
    heights = outline_heights(terrain, b.ring)
    front_y = b.ring[:, 1][np.argmin(side * b.ring[:, 1])]
    gables = gable_edges(b)
    facades = []
    for i, (p, q) in enumerate(zip(b.ring, np.roll(b.ring, -1, axis=0))):
        u = np.append((q - p) / np.linalg.norm(q - p), 0.0)
        o_z = float(heights[i].min())
        normal = np.cross(u, UP)
        on_front = abs(p[1] - front_y) < 1e-6 and abs(q[1] - front_y) < 1e-6
        t_eave = b.eave_z - o_z
        facades.append(Facade(id=first_id + i, building_id=b.id, origin=np.array([p[0], p[1], o_z]), u=u,
                              width=float(np.linalg.norm(q - p)), t_bottom=b.base_z - WALL_BELOW - o_z,
                              t_eave=t_eave, t_top=(b.top_z - o_z) if i in gables else t_eave,
                              street_facing=bool(on_front and normal @ toward_street > 0.99)))
    return facades


@dataclasses.dataclass
class Style:
    """Per-building façade rhythm shared by all its walls."""

    spacing: float
    win_w: float
    win_h: float
    ground_h: float
    floor_h: float
    recess: float

    @classmethod
    def random(cls, rng: np.random.Generator) -> "Style":
        spacing = rng.uniform(2.6, 3.6)
        return cls(spacing=spacing, win_w=rng.uniform(0.9, min(1.5, spacing - 1.0)), win_h=rng.uniform(1.3, 1.7),
                   ground_h=rng.uniform(3.5, 4.2), floor_h=rng.uniform(2.9, 3.3), recess=rng.uniform(0.15, 0.3))

    def floor_levels(self, b: Building) -> np.ndarray:
        """Floor levels (z) whose rooms fit under the eave."""
        levels = [b.floor_z]
        while levels[-1] + (self.ground_h if len(levels) == 1 else self.floor_h) + ROOM_HEIGHT <= b.eave_z - 0.2:
            levels.append(levels[-1] + (self.ground_h if len(levels) == 1 else self.floor_h))
        return np.array(levels)


def inward_depth(poly: Polygon, point: np.ndarray, direction: np.ndarray) -> float:
    """Distance from a point on the outline to where the footprint ends, going along ``direction``."""
    start = point + 0.01 * direction
    inter = LineString([start, point + 200.0 * direction]).intersection(poly)
    pieces = [g for g in getattr(inter, "geoms", [inter]) if not g.is_empty and g.length > 0]
    if not pieces:
        return 0.0
    nearest = min(pieces, key=lambda g: g.distance(LineString([start, start + 1e-3 * direction])))
    return float(nearest.length) + 0.01


def add_elements(rng: np.random.Generator, b: Building, f: Facade, style: Style, next_id: int) -> int:
    """Fill a façade with windows (+ rooms), a door and structures; returns the next free element id."""
    levels = style.floor_levels(b)
    n_cols = int((f.width - 1.6) // style.spacing)
    if n_cols < 1:
        return next_id
    if f.street_facing:
        mode = "full"
    else:
        mode = str(rng.choice(["plain", "sparse", "regular"], p=[0.35, 0.35, 0.3]))
    if mode == "plain":
        return next_id
    centres = f.width / 2 + (np.arange(n_cols) - (n_cols - 1) / 2) * style.spacing
    if mode == "sparse":
        centres = centres[::2]
    door_col = int(rng.integers(len(centres))) if f.street_facing else -1
    o_z = f.origin[2]
    poly = b.polygon
    inward = -f.normal[:2]
    elements: list[Element] = []
    for k, level in enumerate(levels):
        if mode == "sparse" and rng.random() < 0.4:
            continue
        sill = level + (1.0 if k == 0 else 0.9)
        for j, c in enumerate(centres):
            if k == 0 and j == door_col:
                elements.append(_door(rng, f, style, c, level, next_id + len(elements)))
                continue
            s0, s1 = c - style.win_w / 2, c + style.win_w / 2
            t0, t1 = sill - o_z, sill + style.win_h - o_z
            room = _room(rng, f, poly, inward, style, s0, s1, level) if rng.random() < 0.5 else None
            elements.append(Element(id=next_id + len(elements), facade_id=f.id, kind="window", subtype="window",
                                    s0=s0, s1=s1, t0=t0, t1=t1, depth=-style.recess,
                                    has_interior=room is not None, room=room))
    if f.street_facing:
        elements += _structures(rng, f, style, centres, levels, next_id + len(elements))
    f.elements = elements
    return next_id + len(elements)


def _door(rng: np.random.Generator, f: Facade, style: Style, c: float, level: float, eid: int) -> Element:
    width = rng.uniform(1.0, min(1.6, style.spacing - 1.0))
    height = rng.uniform(2.1, 2.4)
    return Element(id=eid, facade_id=f.id, kind="door", subtype="door", s0=c - width / 2, s1=c + width / 2,
                   t0=level - f.origin[2], t1=level + height - f.origin[2], depth=-rng.uniform(0.15, 0.3))


def _room(rng: np.random.Generator, f: Facade, poly: Polygon, inward: np.ndarray, style: Style,
          s0: float, s1: float, level: float) -> tuple[float, float, float, float, float] | None:
    """The room seen through a window: a box behind the glass that stays inside the footprint."""
    margin = min(0.6, (style.spacing - style.win_w) / 2 - 0.05)
    rs0, rs1 = max(0.3, s0 - margin), min(f.width - 0.3, s1 + margin)
    room_depth = rng.uniform(2.0, 5.0)
    base = f.origin[:2]
    u = f.u[:2]
    available = min(inward_depth(poly, base + s * u, inward) for s in (rs0, (s0 + s1) / 2, rs1))
    room_depth = min(room_depth, available - style.recess - 0.4)
    if room_depth < 1.5:
        return None
    t_floor = level + 0.02 - f.origin[2]
    return (rs0, rs1, t_floor, t_floor + ROOM_HEIGHT - 0.02, -style.recess - room_depth)


def _structures(rng: np.random.Generator, f: Facade, style: Style, centres: np.ndarray, levels: np.ndarray,
                first_id: int) -> list[Element]:
    """Pilasters between the window columns, or balconies under upper-floor windows, or nothing."""
    kind = str(rng.choice(["none", "pilaster", "balcony"], p=[0.3, 0.35, 0.35]))
    rects: list[tuple[float, float, float, float]] = []
    if kind == "pilaster" and len(centres) > 1:
        width = rng.uniform(0.3, 0.5)
        proud = rng.uniform(0.1, 0.3)
        for m in (centres[:-1] + centres[1:]) / 2:
            rects.append((m - width / 2, m + width / 2, 0.0, f.t_eave))
    elif kind == "balcony" and len(levels) > 1:
        width = min(style.win_w + 0.8, style.spacing - 0.4)
        proud = rng.uniform(0.3, 0.6)
        columns = rng.random(len(centres)) < 0.6
        for level in levels[1:]:
            for c in centres[columns]:
                rects.append((c - width / 2, c + width / 2, level - 0.15 - f.origin[2], level + 0.85 - f.origin[2]))
    else:
        return []
    return [Element(id=first_id + i, facade_id=f.id, kind="structure", subtype=kind, s0=r[0], s1=r[1], t0=r[2],
                    t1=r[3], depth=float(proud)) for i, r in enumerate(rects)]


# --- roofs and solids ------------------------------------------------------------------------------------------

def fan(poly3: np.ndarray) -> np.ndarray:
    """Triangles of a simple polygon (k, 3) that is convex or an L (fanned from its reflex vertex)."""
    k = len(poly3)
    d1 = np.roll(poly3, -1, axis=0) - poly3
    d0 = poly3 - np.roll(poly3, 1, axis=0)
    cross = d0[:, 0] * d1[:, 1] - d0[:, 1] * d1[:, 0]
    apex = int(np.argmin(cross)) if cross.min() < -1e-9 else 0
    order = np.roll(np.arange(k), -apex)
    p = poly3[order]
    return np.stack([np.broadcast_to(p[0], (k - 2, 3)), p[1:-1], p[2:]], axis=1)


def roof_polygons(b: Building) -> list[np.ndarray]:
    """Roof faces (3D polygons, outward/up orientation)."""
    ring = b.ring
    eave = np.column_stack([ring, np.full(len(ring), b.eave_z)])
    if b.roof_type == "flat":
        return [eave]
    k = b.ridge_edge
    r = [eave[(k + i) % 4] for i in range(4)]  # corners starting at the ridge-parallel edge
    centre = ring.mean(axis=0)
    if b.roof_type == "gabled":
        a_end = np.append((ring[(k + 1) % 4] + ring[(k + 2) % 4]) / 2, b.top_z)  # near corner k+1
        b_end = np.append((ring[(k + 3) % 4] + ring[k % 4]) / 2, b.top_z)  # near corner k
    else:
        along = (ring[(k + 1) % 4] - ring[k % 4])
        half_long = np.linalg.norm(along) / 2
        half_short = np.linalg.norm(ring[(k + 2) % 4] - ring[(k + 1) % 4]) / 2
        unit = along / (2 * half_long)
        a_end = np.append(centre + (half_long - half_short) * unit, b.top_z)
        b_end = np.append(centre - (half_long - half_short) * unit, b.top_z)
    faces = [np.array([r[0], r[1], a_end, b_end]), np.array([r[2], r[3], b_end, a_end])]
    if b.roof_type == "hipped":
        faces += [np.array([r[1], r[2], a_end]), np.array([r[3], r[0], b_end])]
    return faces


def roof_triangles(b: Building) -> np.ndarray:
    return np.concatenate([fan(p) if len(p) > 3 else p[None] for p in roof_polygons(b)])


def wall_triangles(b: Building, z_bottom: float) -> np.ndarray:
    """Closed outer walls (no openings) from ``z_bottom`` up to the eave, plus gable triangles."""
    tris = []
    gables = gable_edges(b)
    for i, (p, q) in enumerate(zip(b.ring, np.roll(b.ring, -1, axis=0))):
        quad = np.array([[*p, z_bottom], [*q, z_bottom], [*q, b.eave_z], [*p, b.eave_z]])
        tris.append(quads(quad[None]))
        if i in gables:
            tris.append(np.array([[[*q, b.eave_z], _ridge_end_near(b, i), [*p, b.eave_z]]]))
    return np.concatenate(tris)


def _ridge_end_near(b: Building, edge: int) -> np.ndarray:
    p, q = b.ring[edge], b.ring[(edge + 1) % len(b.ring)]
    return np.append((p + q) / 2, b.top_z)


def solid_triangles(b: Building) -> np.ndarray:
    """The building as a watertight solid from ``base_z`` (outward-facing triangles, local frame)."""
    if b.shape == "shell":
        return shell_triangles(b, b.base_z)
    floor = np.column_stack([b.ring, np.full(len(b.ring), b.base_z)])
    bottom = fan(floor)[:, ::-1]
    return np.concatenate([bottom, wall_triangles(b, b.base_z), roof_triangles(b)])


def shell_triangles(b: Building, z_bottom: float, thickness: float = 0.3) -> np.ndarray:
    """The construction site's walls as one watertight ring-shaped solid (outer walls, inner walls, top, bottom)."""
    outer = b.ring
    centre = outer.mean(axis=0)
    # the lot is axis-aligned in the local frame: shrinking each corner coordinate towards the centre by the wall
    # thickness gives the inner rectangle with the same corner order
    inner = centre + (outer - centre) * (1 - thickness / np.abs(outer - centre))
    nxt = np.roll(np.arange(len(outer)), -1)

    def at(xy: np.ndarray, z: float) -> np.ndarray:
        return np.column_stack([xy, np.full(len(xy), z)])

    zt = b.top_z
    faces = [
        np.stack([at(outer, z_bottom), at(outer[nxt], z_bottom), at(outer[nxt], zt), at(outer, zt)], 1),
        np.stack([at(inner[nxt], z_bottom), at(inner, z_bottom), at(inner, zt), at(inner[nxt], zt)], 1),
        np.stack([at(outer, zt), at(outer[nxt], zt), at(inner[nxt], zt), at(inner, zt)], 1),
        np.stack([at(inner, z_bottom), at(inner[nxt], z_bottom), at(outer[nxt], z_bottom), at(outer, z_bottom)], 1),
    ]
    return quads(np.concatenate(faces))


# --- meshes for ray casting ------------------------------------------------------------------------------------

def building_soup(b: Building) -> Soup:
    """Every surface a laser can meet on this building, labelled (walls with real holes for the openings)."""
    soup = Soup()
    wall = dict(classification=CLASS_BUILDING, building_id=b.id, rgb=b.wall_rgb, reflectance=b.wall_reflectance)
    if b.shape == "shell":
        _shell_soup(b, soup, wall)
        return soup
    for f in b.facades:
        _facade_soup(b, f, soup, wall)
    roof = Labels(classification=CLASS_BUILDING, kind=KIND["roof"], building_id=b.id, rgb=b.roof_rgb,
                  reflectance=b.roof_reflectance)
    soup.add(roof_triangles(b), roof)
    return soup


def _facade_soup(b: Building, f: Facade, soup: Soup, wall: dict) -> None:
    openings = [e for e in f.elements if e.kind in ("window", "door")]
    holes = np.array([e.rect for e in openings]).reshape(-1, 4)
    cells = holed_rectangle(f.width, f.t_bottom, f.t_eave, holes)  # (M, 4, 2)
    sdt = np.concatenate([cells, np.zeros(cells.shape[:2] + (1,))], axis=-1)
    soup.add(f.to_local(quads(sdt)), Labels(kind=KIND["wall"], facade_id=f.id, **wall))
    if f.t_top > f.t_eave + 1e-9:
        gable = np.array([[[0.0, f.t_eave, 0.0], [f.width, f.t_eave, 0.0], [f.width / 2, f.t_top, 0.0]]])
        soup.add(f.to_local(gable), Labels(kind=KIND["wall"], facade_id=f.id, **wall))
    if openings:
        _openings_soup(b, f, openings, soup)
    structures = [e for e in f.elements if e.kind == "structure"]
    if structures:
        lo = np.array([[e.s0, e.t0, 0.0] for e in structures])
        hi = np.array([[e.s1, e.t1, e.depth] for e in structures])
        tris, owner = boxes(lo, hi, faces=("x0", "x1", "y0", "y1", "z1"))
        rgb = tuple(min(255, int(c * 1.08) + 8) for c in b.wall_rgb)
        soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["structure"], building_id=b.id,
                                          facade_id=f.id, element_id=np.array([e.id for e in structures]),
                                          rgb=rgb, reflectance=b.wall_reflectance), index=owner)


def _openings_soup(b: Building, f: Facade, openings: list[Element], soup: Soup) -> None:
    """Reveals of every opening, door leaves, rooms behind some windows and dark absorbers behind the rest."""
    ids = np.array([e.id for e in openings])
    lo = np.array([[e.s0, e.t0, e.depth] for e in openings])
    hi = np.array([[e.s1, e.t1, 0.0] for e in openings])
    tris, owner = boxes(lo, hi, faces=("x0", "x1", "y0", "y1"))
    reveal_rgb = tuple(int(c * 0.9) for c in b.wall_rgb)
    soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["window_reveal"], building_id=b.id,
                                      facade_id=f.id, element_id=ids, rgb=reveal_rgb,
                                      reflectance=b.wall_reflectance), index=owner)
    doors = np.array([e.kind == "door" for e in openings])
    if doors.any():
        tris, owner = boxes(lo[doors], hi[doors], faces=("z0",))
        soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["door"], building_id=b.id,
                                          facade_id=f.id, element_id=ids[doors], rgb=(96, 60, 40),
                                          reflectance=0.25), index=owner)
    rooms = [e for e in openings if e.room is not None]
    if rooms:
        rlo = np.array([[e.room[0], e.room[2], e.room[4]] for e in rooms])
        rhi = np.array([[e.room[1], e.room[3], e.depth] for e in rooms])
        tris, owner = boxes(rlo, rhi, faces=("x0", "x1", "y0", "y1", "z0"))
        soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["window_interior"],
                                          building_id=b.id, facade_id=f.id,
                                          element_id=np.array([e.id for e in rooms]), rgb=(120, 105, 95),
                                          reflectance=0.2), index=owner)
    dark = [e for e in openings if e.kind == "window" and e.room is None]
    if dark:
        dlo = np.array([[e.s0, e.t0, e.depth - ABSORBER_DEPTH] for e in dark])
        dhi = np.array([[e.s1, e.t1, e.depth] for e in dark])
        tris, owner = boxes(dlo, dhi, faces=("x0", "x1", "y0", "y1", "z0"))
        soup.add(f.to_local(tris), Labels(classification=CLASS_BUILDING, kind=KIND["absorber"], building_id=b.id,
                                          facade_id=f.id, element_id=np.array([e.id for e in dark]),
                                          behaviour=ABSORBER, rgb=(20, 20, 25), reflectance=0.0), index=owner)


def _shell_soup(b: Building, soup: Soup, wall: dict) -> None:
    """Shell walls: outer faces belong to the façades, inner faces and tops to no façade."""
    tris = shell_triangles(b, b.base_z - WALL_BELOW)
    centroid = tris.mean(axis=1)
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    facade_id = np.full(len(tris), -1)
    for f in b.facades:
        on_plane = np.abs((centroid - f.origin) @ f.normal) < 1e-6
        facing = normal @ f.normal > 0.99
        inside = ((centroid - f.origin) @ f.u >= 0) & ((centroid - f.origin) @ f.u <= f.width)
        facade_id[on_plane & facing & inside] = f.id
    soup.add(tris, Labels(kind=KIND["wall"], facade_id=facade_id, **wall), index=np.arange(len(tris)))
