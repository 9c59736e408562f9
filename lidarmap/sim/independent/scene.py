"""The world of one seed: CRS placement, terrain, houses with their façades, static furniture, all as labelled
triangles in the local frame (street along +x).

Random streams: every concern draws from ``numpy.random.default_rng([seed, STREAM, ...])`` so that changing
one part (say, the furniture) never shifts the draws of another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .building import build_interior, build_roof
from .facades import Facade, build_facade, house_walls, plan_front, plan_side
from .furniture import Strip, static_furniture
from .geometry import Materials
from .layout import Street, finish_heights, plan_street
from .structures import build_structures, plan_structures
from .terrain import Terrain, draw_terrain, ground_mesh

STREAMS = {"layout": 1, "terrain": 2, "houses": 3, "facades": 4, "furniture": 5, "objects": 6, "campaign": 7,
           "pulses": 8, "classes": 9, "crs": 10, "cadastre": 11, "time": 12, "geometry": 13}

#: (EPSG, easting, northing, ground height): city centres inside each CRS's area of use.
CRS_SITES = [(25832, 356000.0, 5645000.0, 55.0), (25832, 691000.0, 5335000.0, 520.0),
             (25833, 391000.0, 5820000.0, 35.0), (25833, 411000.0, 5656000.0, 115.0),
             (2154, 652000.0, 6862000.0, 40.0), (2154, 842000.0, 6519000.0, 170.0),
             (28992, 121000.0, 487000.0, 0.5), (28992, 136000.0, 456000.0, 2.0),
             (31467, 3513000.0, 5404000.0, 250.0), (31467, 3477000.0, 5553000.0, 100.0)]


def rng_for(seed: int, stream: str, *more: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), STREAMS[stream], *map(int, more)])


@dataclass
class World:
    seed: int
    terrain: Terrain
    street: Street
    walls: list  # every wall of every house (Facade objects)
    facades: list  # the listed ones, with ids
    openings: list
    mats: Materials
    tris: np.ndarray
    tri_mat: np.ndarray
    strip: Strip
    epsg: int
    origin: np.ndarray  # CRS (E, N, H) of the local origin
    azimuth: float  # CRS angle of the local +x axis (rad, counter-clockwise from CRS +x)
    furniture: bool = True  # street furniture, parked vehicles, people and bicycles

    @property
    def length(self) -> float:
        return self.street.length

    def rot(self) -> np.ndarray:
        c, s = np.cos(self.azimuth), np.sin(self.azimuth)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_crs(self, xyz) -> np.ndarray:
        """Local points (..., 3) to CRS coordinates (float64)."""
        return np.asarray(xyz, float) @ self.rot().T + self.origin

    def vec_to_crs(self, v) -> np.ndarray:
        return np.asarray(v, float) @ self.rot().T


def _plan_walls(seed: int, street: Street, terrain: Terrain) -> list[Facade]:
    walls = []
    for h in street.houses:
        rng = rng_for(seed, "facades", h.id)
        for fac in house_walls(h, terrain, rng):
            if fac.role == "front":
                plan_front(rng, fac)
                plan_structures(rng, fac)
            elif fac.listed:
                plan_side(rng, fac)
            walls.append(fac)
    return walls


def _assign_ids(walls: list[Facade]) -> tuple[list, list]:
    facades, openings = [], []
    for fac in walls:
        if not fac.listed:
            continue
        fac.id = len(facades) + 1
        facades.append(fac)
        for op in fac.openings:
            op.id, op.facade_id = len(openings) + 1, fac.id
            openings.append(op)
    return facades, openings


def _front_lines(walls: list[Facade]) -> dict:
    """Per side: the smallest |y| reached by a house or something on its street wall (tree crowns stay clear)."""
    out = {}
    for fac in walls:
        if fac.role != "front":
            continue
        h = fac.house
        proud = max([0.0] + [st.get("depth", st.get("proud", 0.0)) for st in fac.structures]
                    + [0.3 * op.steps for op in fac.openings])
        out[h.side] = min(out.get(h.side, np.inf), h.y_front - proud)
    return out


def build_world(seed: int, buildings: int = 8, street_length: float | None = None, furniture: bool = True) -> World:
    terrain = draw_terrain(rng_for(seed, "terrain"), 130.0)
    street = plan_street(rng_for(seed, "layout"), buildings, terrain, street_length)
    terrain.length = street.length
    finish_heights(street, terrain, rng_for(seed, "houses"))
    walls = _plan_walls(seed, street, terrain)
    facades, openings = _assign_ids(walls)
    mats = Materials()
    grng = rng_for(seed, "geometry")
    y_extent = max([h.y_back for h in street.houses] + [terrain.road_half + 6]) + 8.0
    mb = ground_mesh(terrain, y_extent, mats, grng)
    for fac in walls:
        build_facade(grng, mb, mats, fac)
        if fac.structures:
            build_structures(grng, mb, mats, fac)
    for h in street.houses:
        build_roof(grng, mb, mats, h)
        build_interior(grng, mb, mats, h)
    strip = Strip()
    if furniture:
        fmb, strip = static_furniture(rng_for(seed, "furniture"), terrain, mats, _front_lines(walls))
        mb.extend(fmb)
    tris, tri_mat = mb.arrays()
    crng = rng_for(seed, "crs")
    epsg, e, n, hgt = CRS_SITES[int(crng.integers(len(CRS_SITES)))]
    origin = np.array([e + crng.uniform(-2000, 2000), n + crng.uniform(-2000, 2000), hgt + crng.uniform(-5, 5)])
    origin[:2] = np.round(origin[:2], 3)
    return World(seed, terrain, street, walls, facades, openings, mats, tris, tri_mat, strip, int(epsg), origin,
                 float(crng.uniform(0, 2 * np.pi)), furniture)
