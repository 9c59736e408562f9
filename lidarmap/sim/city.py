"""The procedural city: streets lined with buildings, street trees, parked cars, on sloped terrain.

The city is laid out in a local street-aligned frame (streets run along local x) and placed in EPSG:32632 by a
seed-chosen rotation and offset (:class:`lidarmap.frame.LocalFrame`), so façades have arbitrary orientations in
the CRS. Street cross-section (distance from a street's axis): driving lanes to 3.5 m (lane centres at 1.75 m),
parking lanes 3.6-5.6 m, curb at 5.8 m, trees at 7.0 m, building lines from 10 m (+ a 0-2.5 m setback).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pyproj import CRS
from shapely.geometry import Point

from lidarmap.frame import LocalFrame
from lidarmap.sim.buildings import (
    Building,
    Style,
    add_elements,
    building_soup,
    footprint_ring,
    make_building,
    make_facades,
    make_shell,
    row_to_local,
)
from lidarmap.sim.mesh import (
    CLASS_OTHER,
    CLASS_VEGETATION,
    KIND,
    LEAF,
    Labels,
    SceneMesh,
    Soup,
    boxes,
    prism,
    rotate_z,
)
from lidarmap.sim.params import SimParams
from lidarmap.sim.terrain import Terrain
from lidarmap.sim.trees import crown_leaves, touching_spots

CRS_EPSG = 32632
LANE_CENTRE = 1.75
PARK_CENTRE = 4.6
CURB = 5.8
TREE_LINE = 7.0
BUILDING_LINE = 10.0
SLOT = 6.0  # parking slot length along the street


@dataclasses.dataclass
class Street:
    """A street along local x at ``y``, driven from ``x0`` to ``x1``."""

    id: int
    y: float
    x0: float
    x1: float


@dataclasses.dataclass
class Tree:
    """Trunk (vertical cylinder) and an ellipsoidal crown of randomly oriented leaves."""

    x: float
    y: float
    ground_z: float
    trunk_height: float
    trunk_radius: float
    crown_radius: float
    crown_half_height: float


@dataclasses.dataclass
class Car:
    """A parked car: centre on the ground, heading, size and colour."""

    x: float
    y: float
    ground_z: float
    heading: float
    length: float
    width: float
    height: float
    rgb: tuple[int, int, int]


@dataclasses.dataclass
class City:
    """Everything static in the scene plus the information needed to draw parked cars per acquisition."""

    params: SimParams
    crs: CRS
    frame: LocalFrame
    terrain: Terrain
    streets: list[Street]
    buildings: list[Building]
    trees: list[Tree]
    static: SceneMesh

    @property
    def facades(self):
        return [f for b in self.buildings for f in b.facades]

    def draw_cars(self, rng: np.random.Generator) -> list[Car]:
        """Parked cars of one acquisition: every slot along both curbs is taken with the configured probability."""
        cars = []
        for street in self.streets:
            slots = np.arange(street.x0 + 8.0, street.x1 - 8.0, SLOT)
            for side in (-1, 1):
                taken = rng.random(len(slots)) < self.params.parking_occupancy
                for x in slots[taken]:
                    cars.append(_random_car(rng, self.terrain, x + rng.uniform(-0.6, 0.6),
                                            street.y + side * (PARK_CENTRE + rng.uniform(-0.15, 0.15))))
        return cars

    def scene(self, cars: list[Car]) -> SceneMesh:
        """The static scene plus these cars."""
        return SceneMesh.concatenate([self.static, cars_soup(cars).build()]) if cars else self.static


def _streets_and_terrain(rng: np.random.Generator, rows: dict, n_streets: int) -> tuple:
    """Street axes, the x shift that centres every row on x = 0, the streets, the city bounds and its terrain
    (shared by both families, so they draw from ``rng`` in the same order)."""
    street_ys = _street_positions(rows, n_streets)
    shifts = {key: -row["length"] / 2 for key, row in rows.items()}
    xs = [ring[:, 0] + shifts[key] for key, row in rows.items() for ring, _ in row["rings"]]
    x_lo, x_hi = min(x.min() for x in xs), max(x.max() for x in xs)
    streets = [Street(id=s + 1, y=street_ys[s], x0=x_lo - 14.0, x1=x_hi + 14.0) for s in range(n_streets)]
    margin = 25.0
    ys = [street_ys[s] + side * (BUILDING_LINE + row["depth"]) for (s, side), row in rows.items()]
    bounds = (x_lo - margin, min(ys + street_ys) - margin, x_hi + margin, max(ys + street_ys) + margin)
    terrain = Terrain.random(rng, bounds)
    return street_ys, shifts, streets, bounds, terrain


def build_city(params: SimParams) -> City:
    """The deterministic city of ``params.seed`` (same seed, same city)."""
    rng = np.random.default_rng([params.seed, 1])
    n_streets = params.streets or (1 if params.buildings <= 10 else 2)
    rows = _layout_rows(rng, params.buildings, n_streets)
    street_ys, shifts, streets, bounds, terrain = _streets_and_terrain(rng, rows, n_streets)
    buildings = _place_buildings(rng, rows, street_ys, shifts, terrain)
    trees = (_street_trees(rng, streets, terrain, params.trees_per_100m)
             + _yard_trees(rng, buildings, streets, terrain, bounds)
             + _touching_trees(params, buildings, terrain))
    angle = _rotation(rng)
    origin = (500000.0 + rng.uniform(200.0, 800.0), 5800000.0 + rng.uniform(200.0, 800.0), 0.0)
    soup = terrain.soup(lambda xy: ground_colour(xy, streets))
    for b in buildings:
        soup.extend(building_soup(b))
    soup.extend(trees_soup(rng, trees, **crown_leaves(params.leaf_off)))
    return City(params=params, crs=CRS.from_epsg(CRS_EPSG), frame=LocalFrame(offset=origin, rotation_deg=angle),
                terrain=terrain, streets=streets, buildings=buildings, trees=trees, static=soup.build())


def _rotation(rng: np.random.Generator) -> float:
    """A layout rotation (degrees) at least 8° away from the CRS axes, so façades are never axis-aligned."""
    return float((rng.integers(4) * 90 + rng.uniform(8.0, 82.0)) % 360)


def _layout_rows(rng: np.random.Generator, n_buildings: int, n_streets: int, setback: tuple[float, float] = (0.0, 2.5),
                 l_share: float = 0.35, gap: tuple[float, float] = (3.5, 7.0)) -> dict:
    """Footprints per row (street, side) in row coordinates: fronts ``setback`` metres behind the building line, an
    L-shape with probability ``l_share``, ``gap`` metres between neighbours; the construction lot ends a random row.
    (The hard family calls it with its own ranges: lidarmap/sim/hard.py.)"""
    keys = [(s, side) for s in range(n_streets) for side in (1, -1)]
    counts = [n_buildings // len(keys) + (1 if i < n_buildings % len(keys) else 0) for i in range(len(keys))]
    lot_row = int(rng.integers(len(keys)))
    rows = {}
    for key, count in zip(keys, counts):
        a, rings, depth = 0.0, [], 0.0
        for _ in range(count + (1 if key == keys[lot_row] else 0)):
            front = BUILDING_LINE + rng.uniform(*setback)
            is_lot = key == keys[lot_row] and len(rings) == count
            ring, width, d = footprint_ring(rng, a, front, l_shape=not is_lot and rng.random() < l_share)
            rings.append((ring, "shell" if is_lot else ("L" if len(ring) == 6 else "rectangle")))
            depth = max(depth, front - BUILDING_LINE + d)
            a += width + rng.uniform(*gap)
        rows[key] = {"rings": rings, "length": max(a - 5.0, 0.0), "depth": depth}
    return rows


def _street_positions(rows: dict, n_streets: int) -> list[float]:
    """Street axes: the second street runs behind the first street's northern row, back to back with its own."""
    ys = [0.0]
    if n_streets == 2:
        gap = rows[(0, 1)]["depth"] + rows[(1, -1)]["depth"] + 2 * BUILDING_LINE + 8.0
        ys.append(gap)
    return ys


def _place_buildings(rng: np.random.Generator, rows: dict, street_ys: list[float], shifts: dict,
                     terrain: Terrain) -> list[Building]:
    buildings: list[Building] = []
    shell_rows = []
    next_facade, next_element = 1, 1
    for (s, side), row in rows.items():
        for ring_rc, shape in row["rings"]:
            ring = row_to_local(ring_rc, street_ys[s], side, shifts[(s, side)])
            if shape == "shell":
                shell_rows.append((ring, (street_ys[s], side)))
                continue
            b = make_building(rng, len(buildings) + 1, ring, terrain, shape)
            b.facades = make_facades(b, terrain, (street_ys[s], side), next_facade)
            next_facade += len(b.facades)
            style = Style.random(rng)
            for f in b.facades:
                next_element = add_elements(rng, b, f, style, next_element)
            buildings.append(b)
    for ring, street_side in shell_rows:  # the construction site gets the last id
        b = make_shell(rng, len(buildings) + 1, ring, terrain)
        b.facades = make_facades(b, terrain, street_side, next_facade)
        next_facade += len(b.facades)
        buildings.append(b)
    return buildings


def ground_colour(xy: np.ndarray, streets: list[Street]) -> tuple[np.ndarray, np.ndarray]:
    """Asphalt on the carriageway, paving on sidewalks, grass elsewhere (RGB 0-255 and reflectance)."""
    dist = np.min(np.abs(xy[:, 1][:, None] - np.array([s.y for s in streets])[None]), axis=1)
    rgb = np.where((dist < CURB)[:, None], np.array([62, 62, 66]),
                   np.where((dist < BUILDING_LINE)[:, None], np.array([158, 152, 146]), np.array([86, 124, 62])))
    refl = np.where(dist < CURB, 0.12, np.where(dist < BUILDING_LINE, 0.3, 0.4))
    return rgb, refl


# --- trees -----------------------------------------------------------------------------------------------------

def _street_trees(rng: np.random.Generator, streets: list[Street], terrain: Terrain, per_100m: float) -> list[Tree]:
    trees = []
    for street in streets:
        for side in (-1, 1):
            length = street.x1 - street.x0 - 16.0
            n = rng.poisson(per_100m * length / 100.0)
            xs = np.sort(street.x0 + 8.0 + rng.uniform(0, length, n))
            keep = np.concatenate([[True], np.diff(xs) > 5.0]) if n else np.zeros(0, bool)
            for x in xs[keep]:
                trees.append(_random_tree(rng, terrain, x, street.y + side * TREE_LINE, max_radius=2.6))
    return trees


def _touching_trees(params: SimParams, buildings: list[Building], terrain: Terrain) -> list[Tree]:
    """``params.trees_touching`` trees against walls, crowns over roof edges (:mod:`lidarmap.sim.trees`); their own
    random stream, so a city without them is the city it always was."""
    existing = [b for b in buildings if b.status == "existing"]
    spots = touching_spots(np.random.default_rng([params.seed, 7]), [b.ring for b in existing],
                           [b.eave_z for b in existing], [b.id for b in existing], params.trees_touching)
    trees = []
    for s in spots:
        ground = float(terrain.height(np.array([[s.x, s.y]]))[0])
        trunk = max(1.0, s.crown_centre_z - s.crown_half_height - ground)
        trees.append(Tree(x=s.x, y=s.y, ground_z=ground, trunk_height=trunk, trunk_radius=0.15,
                          crown_radius=s.crown_radius, crown_half_height=s.crown_half_height))
    return trees


def _yard_trees(rng: np.random.Generator, buildings: list[Building], streets: list[Street], terrain: Terrain,
                bounds: tuple[float, float, float, float]) -> list[Tree]:
    """A few trees behind the buildings, clear of every footprint (so some crowns stand near walls and roofs)."""
    trees: list[Tree] = []
    wanted = max(1, len(buildings) // 3)
    polygons = [b.polygon for b in buildings]
    for _ in range(30 * wanted):
        if len(trees) == wanted:
            break
        x = rng.uniform(bounds[0] + 15, bounds[2] - 15)
        y = rng.uniform(bounds[1] + 5, bounds[3] - 5)
        radius = rng.uniform(2.0, 3.5)
        p = Point(x, y)
        if min(abs(y - s.y) for s in streets) < BUILDING_LINE + radius:
            continue
        if any(poly.distance(p) < radius + 0.8 for poly in polygons):
            continue
        if any(np.hypot(t.x - x, t.y - y) < radius + t.crown_radius for t in trees):
            continue
        trees.append(_random_tree(rng, terrain, x, y, max_radius=radius))
    return trees


def _random_tree(rng: np.random.Generator, terrain: Terrain, x: float, y: float, max_radius: float) -> Tree:
    return Tree(x=float(x), y=float(y), ground_z=float(terrain.height(np.array([[x, y]]))[0]),
                trunk_height=rng.uniform(2.6, 3.6), trunk_radius=rng.uniform(0.12, 0.22),
                crown_radius=rng.uniform(1.8, max_radius), crown_half_height=rng.uniform(2.0, 3.4))


def trees_soup(rng: np.random.Generator, trees: list[Tree], leaf_size: float = 0.35,
               leaf_area_density: float = 0.8) -> Soup:
    """Trunks (opaque) and crowns made of small leaf triangles that pulses pass between and through.

    Leaf count follows a leaf area density (m² per m³): a pulse crossing a crown meets ~1-2 leaves on average,
    which gives multiple returns and some ground returns below the crown.
    """
    soup = Soup()
    if not trees:
        return soup
    centre = np.array([[t.x, t.y] for t in trees])
    z0 = np.array([t.ground_z - 0.3 for t in trees])
    z1 = np.array([t.ground_z + t.trunk_height + t.crown_half_height for t in trees])
    tris, owner = prism(centre, np.array([t.trunk_radius for t in trees]), z0, z1)
    soup.add(tris, Labels(classification=CLASS_VEGETATION, kind=KIND["tree"], rgb=(92, 72, 52), reflectance=0.3),
             index=owner)
    leaf_area = leaf_size ** 2 * np.sqrt(3) / 4
    for t in trees:
        volume = 4 / 3 * np.pi * t.crown_radius ** 2 * t.crown_half_height
        n = int(leaf_area_density * volume / leaf_area)
        # uniform points in the unit ball, scaled to the crown ellipsoid
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        pos = direction * rng.random((n, 1)) ** (1 / 3)
        pos = pos * np.array([t.crown_radius, t.crown_radius, t.crown_half_height])
        pos += np.array([t.x, t.y, t.ground_z + t.trunk_height + t.crown_half_height])
        soup.add(_leaves(rng, pos, leaf_size), Labels(
            classification=CLASS_VEGETATION, kind=KIND["tree"], behaviour=LEAF,
            rgb=np.column_stack([rng.integers(50, 90, n), rng.integers(100, 150, n), rng.integers(35, 65, n)]),
            reflectance=0.45), index=np.arange(n))
    return soup


def _leaves(rng: np.random.Generator, centres: np.ndarray, size: float) -> np.ndarray:
    """Equilateral triangles of side ``size`` around ``centres`` in random orientations."""
    n = len(centres)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    angles = rng.uniform(0, 2 * np.pi, (n, 1)) + np.array([[0.0, 2 * np.pi / 3, 4 * np.pi / 3]])
    r = size / np.sqrt(3)
    offsets = r * (np.cos(angles)[..., None] * e1[:, None] + np.sin(angles)[..., None] * e2[:, None])
    return centres[:, None, :] + offsets


# --- cars ------------------------------------------------------------------------------------------------------

CAR_COLOURS = [(200, 200, 205), (30, 30, 35), (150, 20, 25), (30, 60, 130), (120, 122, 125), (235, 235, 235)]


def _random_car(rng: np.random.Generator, terrain: Terrain, x: float, y: float) -> Car:
    return Car(x=float(x), y=float(y), ground_z=float(terrain.height(np.array([[x, y]]))[0]),
               heading=float(rng.normal(0, np.radians(1.5))), length=rng.uniform(4.0, 4.7),
               width=rng.uniform(1.7, 1.85), height=rng.uniform(1.4, 1.6),
               rgb=CAR_COLOURS[rng.integers(len(CAR_COLOURS))])


def cars_soup(cars: list[Car]) -> Soup:
    """Cars as boxes: body, cabin and four wheels (rays pass under the body between the wheels)."""
    parts_lo, parts_hi, owner = [], [], []
    for i, c in enumerate(cars):
        hl, hw = c.length / 2, c.width / 2
        body = ([-hl, -hw, 0.3], [hl, hw, 1.0])
        cabin = ([-0.3 * hl, -hw + 0.1, 1.0], [0.45 * hl, hw - 0.1, c.height])
        wheels = [([sx * hl * 0.7 - 0.32, min(sy * hw, sy * (hw - 0.22)), -0.05],
                   [sx * hl * 0.7 + 0.32, max(sy * hw, sy * (hw - 0.22)), 0.62]) for sx in (-1, 1) for sy in (-1, 1)]
        for lo, hi in [body, cabin] + wheels:
            parts_lo.append(lo)
            parts_hi.append(hi)
            owner.append(i)
    soup = Soup()
    if not cars:
        return soup
    tris, part = boxes(np.array(parts_lo), np.array(parts_hi))
    car_of_tri = np.array(owner)[part]
    centre = np.array([[c.x, c.y, c.ground_z] for c in cars])
    heading = np.array([c.heading for c in cars])
    tris = rotate_z(tris, heading[car_of_tri][:, None]) + centre[car_of_tri][:, None, :]
    rgb = np.array([c.rgb for c in cars])
    soup.add(tris, Labels(classification=CLASS_OTHER, kind=KIND["car"], rgb=rgb, reflectance=0.45), index=car_of_tri)
    return soup
