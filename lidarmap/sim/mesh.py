"""Triangle soups with per-triangle labels, and the small shape builders the city is made of.

Everything is vectorised over many shapes at once: a builder takes (N, ...) arrays and returns (M, 3, 3)
triangles plus, for each triangle, the index of the shape it came from (so labels can follow).
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Surface kinds, by code (per-point truth ``kind``); ``absorber`` never produces a point.
KINDS = ("ground", "wall", "window_reveal", "window_interior", "door", "structure", "roof", "tree", "car",
         "absorber", "glass", "curtain")
KIND = {name: code for code, name in enumerate(KINDS)}

#: How a surface treats a laser pulse: GLASS returns a pulse with the triangle's ``return_fraction`` probability
#: (the pulse ends there) and lets it through otherwise (no return).
OPAQUE, LEAF, ABSORBER, GLASS = 0, 1, 2, 3

#: Truth classes (ASPRS): cars and other objects are 1.
CLASS_OTHER, CLASS_GROUND, CLASS_VEGETATION, CLASS_BUILDING = 1, 2, 5, 6

LABEL_FIELDS = ("classification", "building_id", "facade_id", "element_id", "kind")


@dataclasses.dataclass
class Labels:
    """What a group of triangles is (scalars or per-triangle arrays); see :data:`KINDS`."""

    classification: int | np.ndarray
    kind: int | np.ndarray
    building_id: int | np.ndarray = -1
    facade_id: int | np.ndarray = -1
    element_id: int | np.ndarray = -1
    behaviour: int | np.ndarray = OPAQUE
    rgb: tuple | np.ndarray = (128, 128, 128)
    reflectance: float | np.ndarray = 0.3
    return_fraction: float | np.ndarray = 1.0


class Soup:
    """Accumulates labelled triangles; :meth:`build` concatenates them into a :class:`SceneMesh`."""

    def __init__(self) -> None:
        self._tris: list[np.ndarray] = []
        self._labels: list[dict[str, np.ndarray]] = []

    def add(self, tris: np.ndarray, labels: Labels, index: np.ndarray | None = None) -> None:
        """Add (M, 3, 3) triangles; array-valued labels are per shape and picked with ``index`` (per triangle)."""
        tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
        m = len(tris)
        if m == 0:
            return
        cols: dict[str, np.ndarray] = {}
        for field in dataclasses.fields(Labels):
            value = np.asarray(getattr(labels, field.name))
            per_shape = value.ndim >= (2 if field.name == "rgb" else 1)
            if per_shape:
                value = value[index] if index is not None else value
            else:
                value = np.broadcast_to(value, (m, 3) if field.name == "rgb" else (m,))
            cols[field.name] = np.asarray(value)
        self._tris.append(tris)
        self._labels.append(cols)

    def extend(self, other: "Soup") -> None:
        self._tris.extend(other._tris)
        self._labels.extend(other._labels)

    def build(self) -> "SceneMesh":
        cat = {name: np.concatenate([c[name] for c in self._labels]) for name in self._labels[0]}
        return SceneMesh(
            triangles=np.concatenate(self._tris),
            classification=cat["classification"].astype(np.uint8),
            kind=cat["kind"].astype(np.uint8),
            building_id=cat["building_id"].astype(np.int32),
            facade_id=cat["facade_id"].astype(np.int32),
            element_id=cat["element_id"].astype(np.int32),
            behaviour=cat["behaviour"].astype(np.uint8),
            rgb=cat["rgb"].astype(np.float32).reshape(-1, 3),
            reflectance=cat["reflectance"].astype(np.float32),
            return_fraction=cat["return_fraction"].astype(np.float32),
        )


@dataclasses.dataclass
class SceneMesh:
    """All triangles of a scene (local frame, float64) with their labels and optics."""

    triangles: np.ndarray
    classification: np.ndarray
    kind: np.ndarray
    building_id: np.ndarray
    facade_id: np.ndarray
    element_id: np.ndarray
    behaviour: np.ndarray
    rgb: np.ndarray
    reflectance: np.ndarray
    return_fraction: np.ndarray  # GLASS only: probability that a pulse meeting the triangle returns from it

    def __len__(self) -> int:
        return len(self.triangles)

    @staticmethod
    def concatenate(meshes: list["SceneMesh"]) -> "SceneMesh":
        return SceneMesh(**{f.name: np.concatenate([getattr(m, f.name) for m in meshes])
                            for f in dataclasses.fields(SceneMesh)})

    def select(self, mask: np.ndarray) -> "SceneMesh":
        return SceneMesh(**{f.name: getattr(self, f.name)[mask] for f in dataclasses.fields(SceneMesh)})


# --- shape builders --------------------------------------------------------------------------------------------

def quads(corners: np.ndarray) -> np.ndarray:
    """(N, 4, 3) quads (corners in order around the quad) -> (2N, 3, 3) triangles, quad i -> triangles 2i, 2i+1."""
    c = np.asarray(corners, dtype=np.float64)
    first = c[:, [0, 1, 2]]
    second = c[:, [0, 2, 3]]
    return np.stack([first, second], axis=1).reshape(-1, 3, 3)


#: Faces of an axis-aligned box as corner indices into its 8 corners (bit 0: x/s hi, bit 1: y/t hi, bit 2: z/d hi).
BOX_FACES = {
    "x0": (0, 4, 6, 2), "x1": (1, 3, 7, 5),
    "y0": (0, 1, 5, 4), "y1": (2, 6, 7, 3),
    "z0": (0, 2, 3, 1), "z1": (4, 5, 7, 6),
}


def boxes(lo: np.ndarray, hi: np.ndarray, faces: tuple[str, ...] = tuple(BOX_FACES)) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of axis-aligned boxes [lo, hi] (N, 3); returns (triangles, box index per triangle)."""
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    bits = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], dtype=bool)  # (8, 3)
    corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])  # (N, 8, 3)
    idx = np.array([BOX_FACES[f] for f in faces])  # (F, 4)
    quad = corners[:, idx]  # (N, F, 4, 3)
    tris = quads(quad.reshape(-1, 4, 3))
    owner = np.repeat(np.arange(len(lo)), 2 * len(faces))
    return tris, owner


def holed_rectangle(width: float, t0: float, t1: float, holes: np.ndarray) -> np.ndarray:
    """A wall rectangle [0, width] x [t0, t1] in (s, t) minus rectangular holes (K, 4: s0, s1, t0, t1).

    The rectangle is cut along every hole edge into a grid; cells whose centre lies in a hole are dropped.
    Returns (M, 4, 2) cell corners in (s, t).
    """
    holes = np.asarray(holes, dtype=np.float64).reshape(-1, 4)
    s_breaks = np.unique(np.clip(np.concatenate([[0.0, width], holes[:, 0], holes[:, 1]]), 0.0, width))
    t_breaks = np.unique(np.clip(np.concatenate([[t0, t1], holes[:, 2], holes[:, 3]]), t0, t1))
    sa, ta = np.meshgrid(s_breaks[:-1], t_breaks[:-1], indexing="xy")
    sb, tb = np.meshgrid(s_breaks[1:], t_breaks[1:], indexing="xy")
    sa, ta, sb, tb = (a.ravel() for a in (sa, ta, sb, tb))
    sc, tc = (sa + sb) / 2, (ta + tb) / 2
    inside = ((sc[:, None] > holes[None, :, 0]) & (sc[:, None] < holes[None, :, 1])
              & (tc[:, None] > holes[None, :, 2]) & (tc[:, None] < holes[None, :, 3])).any(axis=1)
    keep = ~inside
    sa, ta, sb, tb = sa[keep], ta[keep], sb[keep], tb[keep]
    return np.stack([np.stack([sa, ta], 1), np.stack([sb, ta], 1), np.stack([sb, tb], 1), np.stack([sa, tb], 1)], 1)


def prism(center: np.ndarray, radius: np.ndarray, z0: np.ndarray, z1: np.ndarray,
          sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Closed vertical prisms (cylinders) with ``sides`` faces; returns (triangles, prism index per triangle)."""
    center = np.asarray(center, dtype=np.float64).reshape(-1, 2)
    n = len(center)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], 1)  # (S, 2)
    xy = center[:, None, :] + np.asarray(radius, dtype=np.float64).reshape(-1, 1, 1) * ring[None]  # (N, S, 2)
    zlo = np.broadcast_to(np.asarray(z0, dtype=np.float64).reshape(-1, 1), (n, sides))
    zhi = np.broadcast_to(np.asarray(z1, dtype=np.float64).reshape(-1, 1), (n, sides))
    nxt = np.roll(np.arange(sides), -1)
    bottom = np.concatenate([xy, zlo[..., None]], -1)
    top = np.concatenate([xy, zhi[..., None]], -1)
    sides_q = np.stack([bottom, bottom[:, nxt], top[:, nxt], top], 2)  # (N, S, 4, 3)
    side_tris = quads(sides_q.reshape(-1, 4, 3)).reshape(n, -1, 3, 3)
    c_top = np.concatenate([center, zhi[:, :1]], -1)[:, None, :]
    c_bot = np.concatenate([center, zlo[:, :1]], -1)[:, None, :]
    cap_top = np.stack([np.broadcast_to(c_top, top.shape), top, top[:, nxt]], 2)
    cap_bot = np.stack([np.broadcast_to(c_bot, bottom.shape), bottom[:, nxt], bottom], 2)
    tris = np.concatenate([side_tris, cap_top, cap_bot], 1)  # (N, 4S, 3, 3)
    owner = np.repeat(np.arange(n), tris.shape[1])
    return tris.reshape(-1, 3, 3), owner


def rotate_z(xyz: np.ndarray, angle: np.ndarray | float, about: np.ndarray | None = None) -> np.ndarray:
    """Rotate points (..., 3) about the vertical axis through ``about`` (broadcasting angles)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    about = np.zeros(3) if about is None else np.asarray(about, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    p = xyz - about
    out = np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1], p[..., 2]], -1)
    return out + about
