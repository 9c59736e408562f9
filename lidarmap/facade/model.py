"""The façade's data types: its frame (s, t, d coordinates, CONTRIBUTING.md), depth layers, elements (windows,
doors, structures, unknown regions) with their uncertainty, and the evidence grids that later campaigns fuse.

An observation (``lidarmap.facade.observe``) produces them; the map (``lidarmap.map``) stores and refines them."""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
from shapely.geometry import Polygon

UP = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass
class FacadeFrame:
    """A vertical façade plane: origin ``o`` (CRS, float64) and horizontal unit axis ``u``; v = +z, n = u x v."""

    origin: np.ndarray
    u: np.ndarray

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        u = np.asarray(self.u, dtype=np.float64).reshape(3).copy()
        u[2] = 0.0  # façades are vertical: u is horizontal by construction
        norm = np.linalg.norm(u)
        if norm == 0:
            raise ValueError("façade axis u must have a horizontal component")
        self.u = u / norm

    @property
    def v(self) -> np.ndarray:
        return UP

    @property
    def normal(self) -> np.ndarray:
        """Outward unit normal n = u x v (horizontal)."""
        return np.cross(self.u, UP)

    @property
    def offset(self) -> float:
        """Plane offset: n . x + offset = 0 for points on the plane."""
        return float(-self.normal @ self.origin)

    def basis(self) -> np.ndarray:
        """Rows u, v, n."""
        return np.stack([self.u, UP, self.normal])

    def to_facade(self, xyz: np.ndarray) -> np.ndarray:
        """CRS points (..., 3) to façade coordinates (s, t, d)."""
        # einsum, not ``@ basis.T``: a BLAS call per (N, 3) x (3, 3) product is 4-6x slower (thread start-up,
        # the transposed operand), and this runs on every point around every façade
        return np.einsum("...j,kj->...k", np.asarray(xyz, dtype=np.float64) - self.origin, self.basis())

    def to_crs(self, sdt: np.ndarray) -> np.ndarray:
        """Façade coordinates (..., 3) (s, t, d) back to CRS points."""
        return np.einsum("...j,jk->...k", np.asarray(sdt, dtype=np.float64), self.basis()) + self.origin

    def polygon_to_crs(self, polygon: Polygon, depth: float = 0.0) -> np.ndarray:
        """Exterior ring of a façade-coordinate polygon as CRS 3D points (closing vertex dropped)."""
        st = np.asarray(polygon.exterior.coords)[:-1]
        return self.to_crs(np.column_stack([st, np.full(len(st), depth)]))


class ElementKind(str, enum.Enum):
    """What a façade element is; UNKNOWN marks occlusions and holes we cannot explain (uncertainty = inf)."""

    WINDOW = "window"
    DOOR = "door"
    STRUCTURE = "structure"
    UNKNOWN = "unknown"


@dataclasses.dataclass
class Layer:
    """A depth layer of a façade: a Gaussian over d (metres along the normal) and its mixture weight."""

    layer_id: int
    mu: float
    sigma: float
    weight: float
    n_points: int = 0
    campaigns: list[int] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Element:
    """A window, door, structure or unknown region on a façade, as a polygon in (s, t)."""

    element_id: int
    kind: ElementKind
    polygon: Polygon
    layer_id: int | None
    uncertainty: float
    n_points: int = 0
    campaigns: list[int] = dataclasses.field(default_factory=list)
    # an observation's window typed so only for want of leaf evidence (openings.door_or_window_verdict); the
    # fusion reads it on the new campaign's shapes only, and the store does not keep it
    kind_undecided: bool = False

    @property
    def is_unknown(self) -> bool:
        return self.kind is ElementKind.UNKNOWN or math.isinf(self.uncertainty)


@dataclasses.dataclass
class FacadeEvidence:
    """Per-pixel evidence on a façade grid, accumulated over campaigns (the refinement's memory).

    Grids have shape (rows, cols): row i covers t in [t0 + i*cell, t0 + (i+1)*cell), column j likewise in s.
    ``window_votes``: campaigns that saw the pixel as window/door opening; ``object_votes``: campaigns that saw
    wall or another object there (count against a window); ``seen``: campaigns that observed the pixel at all.
    """

    cell: float
    s0: float
    t0: float
    window_votes: np.ndarray
    object_votes: np.ndarray
    seen: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.seen.shape  # type: ignore[return-value]


@dataclasses.dataclass
class Facade:
    """A façade: its plane (frame + σ), extent in (s, t), depth layers, elements and evidence."""

    facade_id: int
    frame: FacadeFrame
    sigma: float
    extent: tuple[float, float, float, float]  # s0, s1, t0, t1
    layers: list[Layer] = dataclasses.field(default_factory=list)
    elements: list[Element] = dataclasses.field(default_factory=list)
    main_layer: int | None = None
    n_points: int = 0
    footprint_edge: int | None = None
    campaigns: list[int] = dataclasses.field(default_factory=list)
    evidence: FacadeEvidence | None = None

    def layer(self, layer_id: int | None) -> Layer | None:
        return next((layer for layer in self.layers if layer.layer_id == layer_id), None)
