"""Labelled triangle soup: materials, a mesh builder and the few primitives the scene is made of.

Everything is built in the scene's LOCAL frame (street along +x, street axis at y = 0, z up, metres); the writer
maps it to the drawn CRS at the end. Local coordinates stay small (|x| < 250 m), which keeps embree's float32
intersection precise to a few hundredths of a millimetre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

# Surface labels: what the physics does with a hit (see physics.py).
GROUND, WALL, ROOF, REVEAL, FRAME, GLASS, CURTAIN, DOOR, PART, RAILING, INTERIOR, LEAF, TRUNK, CAR, VAN, STREET, \
    PERSON = range(17)
LABEL_NAMES = ("ground", "wall", "roof", "reveal", "frame", "glass", "curtain", "door", "part", "railing",
               "interior", "leaf", "trunk", "car", "van", "street", "person")
#: LAS class of each label (ground 2, building 6, vegetation 5, everything else 1).
LABEL_CLASS = np.array([2, 6, 6, 6, 6, 6, 6, 6, 6, 6, 6, 5, 5, 1, 1, 1, 1], np.uint8)

_FIELDS = {  # name: default
    "label": 0, "refl": 0.3, "cls": -1, "relief": 0.0,
    "rust_period": 0.0, "rust_groove": 0.0, "rust_depth": 0.0, "rust_z0": 0.0, "rust_ztop": -1e9,
    "p0": 0.0, "k": 2.0, "spec": 0.0, "pint": 1.0, "leafq": 1.0, "opening": -1,
}


class Materials:
    """A growing table of surface materials; ``arrays()`` freezes it into one numpy array per field."""

    def __init__(self):
        self.rows: list[dict] = []

    def add(self, label: int, **fields) -> int:
        unknown = set(fields) - set(_FIELDS)
        if unknown:
            raise KeyError(f"unknown material fields {sorted(unknown)}")
        row = dict(_FIELDS, label=label, **fields)
        if row["cls"] < 0:
            row["cls"] = int(LABEL_CLASS[label])
        self.rows.append(row)
        return len(self.rows) - 1

    def arrays(self) -> dict[str, np.ndarray]:
        out = {}
        for name, default in _FIELDS.items():
            dtype = np.int32 if isinstance(default, int) else np.float64
            out[name] = np.array([r[name] for r in self.rows], dtype=dtype)
        return out


class MeshBuilder:
    """Collects triangles (3 vertices each, not shared) with one material id per triangle."""

    def __init__(self):
        self._tris: list[np.ndarray] = []
        self._mats: list[np.ndarray] = []

    def add(self, tris: np.ndarray, material: int) -> None:
        tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
        if len(tris):
            self._tris.append(tris)
            self._mats.append(np.full(len(tris), material, np.int32))

    def extend(self, other: "MeshBuilder") -> None:
        self._tris += other._tris
        self._mats += other._mats

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(triangles (n, 3, 3) float64, material ids (n,) int32); degenerate triangles dropped."""
        if not self._tris:
            return np.zeros((0, 3, 3)), np.zeros(0, np.int32)
        tris = np.concatenate(self._tris)
        mats = np.concatenate(self._mats)
        area2 = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        keep = area2 > 1e-10
        return tris[keep], mats[keep]


# ----------------------------------------------------------------------------------------------------------------------
# Façade frame


@dataclass
class Frame:
    """A wall's coordinates: s along ``u`` from ``o``, t = z - o_z, d along the outward normal ``n``.

    The wall leans by ``lean`` radians about its mid-height line: a point at façade coords (s, t, d) lies at
    d + (t - height / 2) * tan(lean) from the vertical reference plane, which is the plane the truth uses.
    """

    o: np.ndarray
    u: np.ndarray
    n: np.ndarray
    height: float
    lean: float = 0.0

    def xyz(self, s, t, d) -> np.ndarray:
        s, t, d = np.broadcast_arrays(np.asarray(s, float), np.asarray(t, float), np.asarray(d, float))
        d_eff = d + (t - self.height / 2.0) * np.tan(self.lean)
        return (self.o + s[..., None] * self.u + d_eff[..., None] * self.n
                + t[..., None] * np.array([0.0, 0.0, 1.0]))


def frame_from(a: np.ndarray, b: np.ndarray, z0: float, height: float, lean: float = 0.0) -> Frame:
    """Frame of the wall from ground point ``a`` to ``b`` (seen from outside, left to right); normal = u x z."""
    u = np.array([b[0] - a[0], b[1] - a[1], 0.0])
    u /= np.linalg.norm(u)
    n = np.array([u[1], -u[0], 0.0])  # outward: u = z x n  <=>  n = u x z
    return Frame(np.array([a[0], a[1], z0], float), u, n, height, lean)


# ----------------------------------------------------------------------------------------------------------------------
# Primitives

_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box_corners_tris(c: np.ndarray) -> np.ndarray:
    """12 triangles of a hexahedron given its 8 corners (bottom ring 0-3, top ring 4-7)."""
    return c[_BOX_FACES]


def facade_box(fr: Frame, s0, s1, t0, t1, d0, d1) -> np.ndarray:
    """A box in façade coordinates (it leans with the wall)."""
    s = np.array([s0, s1, s1, s0, s0, s1, s1, s0])
    d = np.array([d0, d0, d1, d1, d0, d0, d1, d1])
    t = np.array([t0, t0, t0, t0, t1, t1, t1, t1])
    return box_corners_tris(fr.xyz(s, t, d))


def world_box(center, size, yaw: float = 0.0) -> np.ndarray:
    """An axis-aligned (then yawed about z) box: center (x, y, z of the bottom), size (length, width, height)."""
    lx, ly, lz = np.asarray(size, float) / 2.0
    xy = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]])
    c, s = np.cos(yaw), np.sin(yaw)
    xy = xy @ np.array([[c, s], [-s, c]]) + np.asarray(center[:2], float)
    z0 = float(center[2])
    ring = np.hstack([np.vstack([xy, xy]), np.repeat([[z0], [z0 + 2 * lz]], 4, axis=0)])
    return box_corners_tris(ring)


def cylinder(base, height: float, radius: float, sections: int = 8, cap: bool = True) -> np.ndarray:
    """A vertical prism approximating a cylinder standing on ``base``."""
    a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * radius + np.asarray(base, float)
    top = ring + [0, 0, height]
    j = (np.arange(sections) + 1) % sections
    i = np.arange(sections)
    tris = [np.stack([ring[i], ring[j], top[j]], 1), np.stack([ring[i], top[j], top[i]], 1)]
    if cap:
        centre = np.asarray(base, float) + [0, 0, height]
        tris.append(np.stack([np.broadcast_to(centre, top[i].shape), top[i], top[j]], 1))
    return np.concatenate(tris)


def polygon_tris_2d(poly) -> np.ndarray:
    """Constrained Delaunay triangles (m, 3, 2) of a shapely polygon (holes respected)."""
    if poly.is_empty or poly.area < 1e-8:
        return np.zeros((0, 3, 2))
    tris = shapely.constrained_delaunay_triangles(poly)
    parts = [g for g in getattr(tris, "geoms", [tris]) if g.geom_type == "Polygon" and g.area > 1e-10]
    if not parts:
        return np.zeros((0, 3, 2))
    coords = shapely.get_coordinates(parts).reshape(len(parts), 4, 2)[:, :3]
    return coords


def facade_polygon(fr: Frame, poly, d: float) -> np.ndarray:
    """Triangles of a polygon given in (s, t) lying at depth d of the façade."""
    tri2 = polygon_tris_2d(poly)
    return fr.xyz(tri2[..., 0], tri2[..., 1], np.full(tri2.shape[:2], d))


def outline_band(fr: Frame, ring: np.ndarray, d0: float, d1: float) -> np.ndarray:
    """Quads joining a closed (s, t) ring at depth d0 to the same ring at d1: the sides of a hole or a prism."""
    p = np.asarray(ring, float)
    q = np.roll(p, -1, axis=0)
    a0 = fr.xyz(p[:, 0], p[:, 1], np.full(len(p), d0))
    b0 = fr.xyz(q[:, 0], q[:, 1], np.full(len(p), d0))
    a1 = fr.xyz(p[:, 0], p[:, 1], np.full(len(p), d1))
    b1 = fr.xyz(q[:, 0], q[:, 1], np.full(len(p), d1))
    return np.concatenate([np.stack([a0, b0, b1], 1), np.stack([a0, b1, a1], 1)])


def ring_of(poly: Polygon) -> np.ndarray:
    """Exterior ring of a polygon without the closing point."""
    return np.asarray(poly.exterior.coords)[:-1]


def random_leaves(rng, centre, radii, count: int, size: float) -> np.ndarray:
    """``count`` small triangles of edge ~``size`` spread uniformly in an ellipsoid, randomly oriented."""
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = rng.random(count) ** (1 / 3)
    centres = np.asarray(centre, float) + u * r[:, None] * np.asarray(radii, float)
    a = rng.normal(size=(count, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(a, rng.normal(size=(count, 3)))
    b /= np.linalg.norm(b, axis=1, keepdims=True) + 1e-12
    p0 = centres + a * size * 0.6
    p1 = centres - a * size * 0.3 + b * size * 0.5
    p2 = centres - a * size * 0.3 - b * size * 0.5
    return np.stack([p0, p1, p2], 1)
