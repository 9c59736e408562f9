"""Façade extraction, part 1: ground removal, the footprint join and vertical planes per building.

Everything here works on numpy arrays; :mod:`lidarmap.facade.observe.observe` orchestrates. Vertical planes are found in 2D (a
vertical plane is a line in xy), either by an efficient-RANSAC variant (Schnabel et al. 2007: normal-verified minimal
sets, scoring on random subsets, connectivity along the wall) or by region growing on a k-NN graph; both return
:class:`VerticalPlane` s that :func:`group_planes` merges into façade groups (parallel planes a few decimetres apart
are layers of one façade, not separate façades).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lidarmap.errors import InputError
from lidarmap.facade.model import FacadeFrame

if TYPE_CHECKING:  # pragma: no cover
    from lidarmap.core import Footprints
    from lidarmap.facade.params import FacadeParams


# ----------------------------------------------------------------------------------------------------------------------
# Ground and building points


class LowestCells:
    """The lowest point of every ``cell`` xy cell of a lattice anchored at ``origin``, gathered chunk by chunk.

    The height rule of :func:`ground_mask` needs, for each point, the lowest point of the 3x3 cells around its own;
    this table holds only the occupied cells (sorted keys), so a campaign streamed in chunks of any size, or any
    part of it read back later, gets exactly the ground of the whole campaign as long as every point went through
    :meth:`add` before :meth:`finish`.
    """

    def __init__(self, origin: np.ndarray, cell: float):
        self.origin = np.asarray(origin, dtype=np.float64)[:2]
        self.cell = float(cell)
        self.keys = np.zeros(0, dtype=np.int64)
        self.z = np.zeros(0)
        self.finished = False

    def cell_keys(self, xy: np.ndarray) -> np.ndarray:
        # +1: the 3x3 neighbours of cells in row/column 0 keep non-negative keys
        ij = np.floor((xy - self.origin) / self.cell).astype(np.int64) + 1
        return (ij[:, 0] << 31) | ij[:, 1]

    def add(self, xyz: np.ndarray) -> None:
        """Fold more points into the table (any order, any chunking)."""
        keys, z = _min_per_key(self.cell_keys(xyz[:, :2]), np.asarray(xyz[:, 2], dtype=np.float64))
        self.keys, self.z = _min_per_key(np.concatenate([self.keys, keys]), np.concatenate([self.z, z]))

    def finish(self) -> "LowestCells":
        """Replace every cell's lowest z by the lowest over the 3x3 cells around it (missing cells: none)."""
        low = self.z.copy()
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                want = self.keys + (di << 31) + dj
                pos = np.minimum(np.searchsorted(self.keys, want), max(len(self.keys) - 1, 0))
                hit = self.keys[pos] == want if len(self.keys) else np.zeros(0, dtype=bool)
                low[hit] = np.minimum(low[hit], self.z[pos[hit]])
        self.z, self.finished = low, True
        return self

    def ground(self, xyz: np.ndarray, height: float) -> np.ndarray:
        """Points less than ``height`` above the lowest point of the 3x3 cells around them."""
        if not self.finished:
            raise RuntimeError("LowestCells.finish() first")
        if not len(xyz):
            return np.zeros(0, dtype=bool)
        pos = np.searchsorted(self.keys, self.cell_keys(xyz[:, :2]))
        return xyz[:, 2] - self.z[np.minimum(pos, len(self.keys) - 1)] < height


def _min_per_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct keys (sorted) and the smallest value of each."""
    if not len(keys):
        return keys, values
    order = np.argsort(keys, kind="stable")
    keys, values = keys[order], values[order]
    first = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    return keys[first], np.minimum.reduceat(values, first)


def ground_mask(xyz: np.ndarray, classification: np.ndarray | None, params: "FacadeParams") -> np.ndarray:
    """True for ground points: class ``params.ground_class`` when the classification has it, else a height rule.

    The height rule (no usable classification): the lowest point of every ``ground_cell`` xy cell (lattice anchored
    at the points' minimum), then the minimum over the 3x3 neighbouring cells (so a cell holding only wall points
    still sees the street next to it); points less than ``ground_height`` above that local lowest point are ground.
    """
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=bool)
    if classification is not None and np.any(classification == params.join.ground_class):
        return classification == params.join.ground_class
    cells = LowestCells(xyz[:, :2].min(axis=0), params.join.ground_cell)
    cells.add(xyz)
    return cells.finish().ground(xyz, params.join.ground_height)


def building_mask(classification: np.ndarray | None, ground: np.ndarray, params: "FacadeParams") -> np.ndarray:
    """Building points: class ``params.building_class`` when present, else every non-ground point."""
    if classification is not None and np.any(classification == params.join.building_class):
        return classification == params.join.building_class
    return ~ground


def join_footprints(xy: np.ndarray, footprints: "Footprints | np.ndarray", max_distance: float,
                    quantum: float = 0.02, origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest footprint of every point within ``max_distance`` (§2.2 spatial join), vectorised.

    ``footprints``: a :class:`Footprints` or an array of polygons. Returns (footprint index per point, -1 beyond
    ``max_distance``; distance to the footprint polygon, 0 inside). A point as near to several footprints (a party
    wall of two terraced houses) goes to the first of them, so the join does not depend on the spatial index.
    Points are snapped to a ``quantum`` xy grid first (façade points share few xy positions), so 5 M points cost one
    ``np.unique`` and a GEOS nearest query on the distinct positions; the snapping moves a point by at most
    ``quantum / sqrt(2)``, on a lattice anchored at ``origin`` (default: the points' minimum; a campaign joined
    building by building passes its own origin so that a point snaps to the same spot in every building's join).
    """
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    polygons = getattr(footprints, "polygons", footprints)
    lo = np.floor((xy.min(axis=0) if origin is None else np.asarray(origin)[:2]) / quantum) * quantum
    keys = np.round((xy - lo) / quantum).astype(np.int64)
    ncol = int(keys[:, 1].max()) + 1
    flat = keys[:, 0] * ncol + keys[:, 1]
    uniq, inverse = np.unique(flat, return_inverse=True)
    centres = np.column_stack([uniq // ncol, uniq % ncol]).astype(np.float64) * quantum + lo
    tree = shapely.STRtree(polygons)
    geoms = shapely.points(centres)
    (qi, ti), dist = tree.query_nearest(geoms, max_distance=max_distance, return_distance=True, all_matches=True)
    index = np.full(len(uniq), len(polygons), dtype=np.int64)
    np.minimum.at(index, qi, ti)  # ties: the lowest footprint index
    distance = np.full(len(uniq), np.inf)
    distance[qi] = dist
    index[index == len(polygons)] = -1
    return index[inverse], distance[inverse]


def boundary_distance(xy: np.ndarray, polygon, quantum: float = 0.02) -> np.ndarray:
    """Distance of points to a footprint's boundary (exterior and interior rings), on a ``quantum`` xy grid."""
    if len(xy) == 0:
        return np.zeros(0)
    lo = np.floor(xy.min(axis=0) / quantum) * quantum
    keys = np.round((xy - lo) / quantum).astype(np.int64)
    ncol = int(keys[:, 1].max()) + 1
    uniq, inverse = np.unique(keys[:, 0] * ncol + keys[:, 1], return_inverse=True)
    centres = np.column_stack([uniq // ncol, uniq % ncol]).astype(np.float64) * quantum + lo
    return shapely.distance(shapely.points(centres), polygon.boundary)[inverse]


# ----------------------------------------------------------------------------------------------------------------------
# Normals and vertical planes


def voxel_subsample(xyz: np.ndarray, voxel: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of one point per ``voxel`` cube (the first of a random order), at most ``max_points`` of them."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    order = rng.permutation(len(xyz))
    keys = np.floor((xyz[order] - xyz.min(axis=0)) / voxel).astype(np.int64)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, first = np.unique(flat, return_index=True)
    chosen = order[first]
    if len(chosen) > max_points:
        chosen = rng.choice(chosen, size=max_points, replace=False)
    return np.sort(chosen)


def estimate_normals(xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals by PCA over the ``k`` nearest neighbours (smallest eigenvector) and the neighbour indices."""
    n = len(xyz)
    k = int(min(k, n))
    if n < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros((n, max(k, 1)), dtype=np.int64)
    _, idx = cKDTree(xyz).query(xyz, k=k)
    nb = xyz[idx] - xyz[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb) / k
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0], idx


@dataclasses.dataclass
class VerticalPlane:
    """A vertical plane found in one building: n . xy + c = 0 (n horizontal unit, 2D), its along-wall range."""

    normal: np.ndarray  # (2,)
    c: float
    s_min: float
    s_max: float
    support: int
    members: np.ndarray  # indices into the detection points

    @property
    def direction(self) -> np.ndarray:
        return np.array([-self.normal[1], self.normal[0]])

    def distance(self, xy: np.ndarray) -> np.ndarray:
        return xy @ self.normal + self.c

    def along(self, xy: np.ndarray) -> np.ndarray:
        return xy @ self.direction

    @property
    def centre(self) -> np.ndarray:
        mid = 0.5 * (self.s_min + self.s_max)
        return mid * self.direction - self.c * self.normal


def fit_line_2d(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares line through xy points: unit normal n and c with n . xy + c = 0."""
    centre = xy.mean(axis=0)
    cov = np.cov((xy - centre).T) if len(xy) > 1 else np.eye(2)
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, 0]
    return normal, float(-normal @ centre)


def _largest_run(s: np.ndarray, max_gap: float) -> np.ndarray:
    """Boolean mask of the points in the most populated run of sorted-by-s points without gaps > ``max_gap``."""
    if len(s) == 0:
        return np.zeros(0, dtype=bool)
    order = np.argsort(s)
    breaks = np.flatnonzero(np.diff(s[order]) > max_gap)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks + 1, [len(s)]])
    best = int(np.argmax(ends - starts))
    keep = np.zeros(len(s), dtype=bool)
    keep[order[starts[best]:ends[best]]] = True
    return keep


def _make_plane(xy: np.ndarray, members: np.ndarray) -> VerticalPlane:
    normal, c = fit_line_2d(xy[members])
    direction = np.array([-normal[1], normal[0]])
    s = xy[members] @ direction
    return VerticalPlane(normal, c, float(s.min()), float(s.max()), len(members), members)


def ransac_vertical_planes(xyz: np.ndarray, normals: np.ndarray, params: "FacadeParams",
                           rng: np.random.Generator) -> list[VerticalPlane]:
    """Vertical planes by efficient RANSAC (Schnabel et al. 2007) reduced to 2D lines.

    Candidates are minimal sets of two points whose normals agree and are perpendicular to the line through them
    (normal verification), scored on a random subset of the remaining points (distance < ``ransac_threshold`` and
    normal within ``ransac_normal_deg``); the best candidate is refitted by least squares on all its inliers, cut to
    its largest connected run along the wall (gaps > ``facade_max_gap`` split) and removed; repeat until the best
    candidate has fewer than ``min_facade_points`` points.
    """
    keep = np.abs(normals[:, 2]) < np.sin(np.radians(params.planes.vertical_tolerance_deg))
    idx_all = np.flatnonzero(keep)
    xy = xyz[:, :2]
    n2 = normals[:, :2] / np.maximum(np.linalg.norm(normals[:, :2], axis=1, keepdims=True), 1e-12)
    cos_n = np.cos(np.radians(params.planes.ransac_normal_deg))
    thr = params.planes.ransac_threshold
    remaining = idx_all.copy()
    planes: list[VerticalPlane] = []
    failures = 0
    while len(remaining) >= params.planes.min_facade_points and failures < 3:
        # Hypotheses: pairs (i, j) of remaining points with compatible normals.
        m = 4 * params.planes.ransac_hypotheses
        i = rng.choice(remaining, size=m)
        j = rng.choice(remaining, size=m)
        dxy = xy[j] - xy[i]
        length = np.linalg.norm(dxy, axis=1)
        ok = (length > 0.3) & (np.abs(np.sum(n2[i] * n2[j], axis=1)) > cos_n)
        line_n = np.column_stack([-dxy[:, 1], dxy[:, 0]]) / np.maximum(length, 1e-12)[:, None]
        ok &= np.abs(np.sum(line_n * n2[i], axis=1)) > np.cos(np.radians(2 * params.planes.ransac_normal_deg))
        i, line_n = i[ok][:params.planes.ransac_hypotheses], line_n[ok][:params.planes.ransac_hypotheses]
        if len(i) == 0:
            failures += 1
            continue
        c = -np.sum(line_n * xy[i], axis=1)
        sub = remaining if len(remaining) <= params.planes.ransac_eval_points else \
            rng.choice(remaining, size=params.planes.ransac_eval_points, replace=False)
        dist = np.abs(line_n @ xy[sub].T + c[:, None])
        agree = np.abs(line_n @ n2[sub].T) > cos_n
        score = np.count_nonzero((dist < thr) & agree, axis=1)
        found = False
        for h in np.argsort(-score)[:3]:
            normal, cc = line_n[h], c[h]
            for _ in range(3):  # least-squares refit on the growing inlier set
                inl = remaining[(np.abs(xy[remaining] @ normal + cc) < thr)
                                & (np.abs(n2[remaining] @ normal) > cos_n)]
                if len(inl) < 3:
                    break
                normal, cc = fit_line_2d(xy[inl])
            else:
                s = xy[inl] @ np.array([-normal[1], normal[0]])
                inl = inl[_largest_run(s, params.planes.facade_max_gap)]
                if len(inl) >= params.planes.min_facade_points:
                    plane = _make_plane(xy, inl)
                    if plane.s_max - plane.s_min >= params.planes.min_facade_length:
                        planes.append(plane)
                        remaining = np.setdiff1d(remaining, inl, assume_unique=True)
                        found = True
                        break
        failures = 0 if found else failures + 1
    return planes


def region_growing_vertical_planes(xyz: np.ndarray, normals: np.ndarray, neighbours: np.ndarray,
                                   params: "FacadeParams") -> list[VerticalPlane]:
    """Vertical planes by region growing on the k-NN graph (normal angle and point-to-plane distance)."""
    n = len(xyz)
    vertical = np.abs(normals[:, 2]) < np.sin(np.radians(params.planes.vertical_tolerance_deg))
    if n == 0 or not vertical.any():
        return []
    rows = np.repeat(np.arange(n), neighbours.shape[1])
    cols = neighbours.ravel()
    cos_a = np.cos(np.radians(params.planes.region_angle_deg))
    ok = vertical[rows] & vertical[cols] & (np.abs(np.sum(normals[rows] * normals[cols], axis=1)) > cos_a)
    ok &= np.abs(np.sum(normals[rows] * (xyz[cols] - xyz[rows]), axis=1)) < params.planes.ransac_threshold
    graph = coo_matrix((np.ones(int(ok.sum())), (rows[ok], cols[ok])), shape=(n, n))
    ncomp, labels = connected_components(graph, directed=False)
    labels = np.where(vertical, labels, -1)
    counts = np.bincount(labels[labels >= 0], minlength=ncomp)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    planes: list[VerticalPlane] = []
    xy = xyz[:, :2]
    for comp in np.flatnonzero(counts >= params.planes.min_facade_points):
        lo, hi = np.searchsorted(sorted_labels, [comp, comp + 1])
        members = order[lo:hi]
        plane = _make_plane(xy, members)
        # keep the inliers of the refitted plane only, then the largest run along it
        d = np.abs(plane.distance(xy[members]))
        members = members[d < 2 * params.planes.ransac_threshold]
        if len(members) < params.planes.min_facade_points:
            continue
        members = members[_largest_run(plane.along(xy[members]), params.planes.facade_max_gap)]
        if len(members) < params.planes.min_facade_points:
            continue
        plane = _make_plane(xy, members)
        if plane.s_max - plane.s_min >= params.planes.min_facade_length:
            planes.append(plane)
    return planes


@dataclasses.dataclass
class PlaneGroup:
    """Parallel vertical planes close in depth and along the wall: one façade with several layers."""

    plane: VerticalPlane  # the best supported member: the reference for depth
    members: list[VerticalPlane]
    s_min: float
    s_max: float
    d_min: float  # member plane offsets relative to the reference, metres along its normal
    d_max: float

    @property
    def support(self) -> int:
        return sum(m.support for m in self.members)


def _joinable(g: "PlaneGroup", plane: VerticalPlane, params: "FacadeParams",
              max_gap: float | None = None) -> tuple[bool, np.ndarray, np.ndarray]:
    """Whether ``plane`` belongs to group ``g`` (near-parallel, both ends within merge_depth, close along the wall:
    a gap of at most ``max_gap``, default ``facade_max_gap``); also its ends' depths and along-wall positions in the
    group's reference plane."""
    gap = params.planes.facade_max_gap if max_gap is None else max_gap
    ends = np.array([plane.s_min, plane.s_max])[:, None] * plane.direction - plane.c * plane.normal
    d = g.plane.distance(ends)
    s = g.plane.along(ends)
    ok = abs(float(plane.normal @ g.plane.normal)) >= np.cos(np.radians(params.planes.merge_angle_deg))
    ok = ok and np.max(np.abs(d)) <= params.planes.merge_depth
    ok = ok and not (s.min() > g.s_max + gap or s.max() < g.s_min - gap)
    return bool(ok), d, s


def _span(g: "PlaneGroup") -> VerticalPlane:
    """Group ``g`` as one plane: its reference plane over the group's whole range along the wall."""
    return VerticalPlane(g.plane.normal, g.plane.c, g.s_min, g.s_max, g.support, g.plane.members)


def _absorb(ga: "PlaneGroup", gb: "PlaneGroup", d: np.ndarray, s: np.ndarray) -> None:
    """Group ``gb`` joins ``ga``; ``d``, ``s``: the ends of ``gb``'s span in ``ga``'s reference plane."""
    ga.members += gb.members
    ga.s_min, ga.s_max = min(ga.s_min, float(s.min())), max(ga.s_max, float(s.max()))
    sign = 1.0 if float(ga.plane.normal @ gb.plane.normal) >= 0 else -1.0
    lo_b, hi_b = sorted((sign * gb.d_min, sign * gb.d_max))
    ga.d_min = min(ga.d_min, float(d.min()) + lo_b)
    ga.d_max = max(ga.d_max, float(d.max()) + hi_b)


def group_planes(planes: list[VerticalPlane], params: "FacadeParams") -> list[PlaneGroup]:
    """Merge near-parallel planes (angle < ``merge_angle_deg``) whose ends lie within ``merge_depth`` of a bigger
    plane and that overlap it along the wall (gaps < ``facade_max_gap``), transitively: pieces of one wall split
    by pilasters or a column of windows end up in one group, whatever order they were found in."""
    groups: list[PlaneGroup] = []
    for plane in sorted(planes, key=lambda p: -p.support):
        for g in groups:
            ok, d, s = _joinable(g, plane, params)
            if ok:
                g.members.append(plane)
                g.s_min, g.s_max = min(g.s_min, float(s.min())), max(g.s_max, float(s.max()))
                g.d_min, g.d_max = min(g.d_min, float(d.min())), max(g.d_max, float(d.max()))
                break
        else:
            groups.append(PlaneGroup(plane, [plane], plane.s_min, plane.s_max, 0.0, 0.0))
    merged = True
    while merged and len(groups) > 1:  # join groups that grew towards each other
        merged = False
        for a in range(len(groups)):
            for b in range(len(groups)):
                if a == b:
                    continue
                ga, gb = groups[a], groups[b]
                ok, d, s = _joinable(ga, _span(gb), params)
                if ok and ga.support >= gb.support:
                    _absorb(ga, gb, d, s)
                    del groups[b]
                    merged = True
                    break
            if merged:
                break
    return groups


def plane_frame(plane: VerticalPlane) -> FacadeFrame:
    """The façade frame of a vertical plane: origin on it at s = 0, z = 0, s along :attr:`VerticalPlane.direction`
    (so s is :meth:`VerticalPlane.along`), d along its normal."""
    return FacadeFrame(origin=np.array([*(-plane.c * plane.normal), 0.0]), u=np.array([*plane.direction, 0.0]))


def group_edge(g: PlaneGroup, polygon, params: "FacadeParams") -> int | None:
    """The footprint edge group ``g`` lies on (:func:`match_footprint_edge`), ``None`` for none."""
    return match_footprint_edge(plane_frame(g.plane), (g.s_min, g.s_max), polygon, params)[0]


def join_edge_groups(groups: list[PlaneGroup], polygon, params: "FacadeParams") -> list[PlaneGroup]:
    """Groups on one footprint edge that :func:`group_planes` left apart only for a gap along the wall (more than
    ``facade_max_gap``: a tree or a van hid the wall between them) are one façade. Kept apart, both would reach
    over the whole edge in a later campaign (the map widens a façade to its edge) and split that wall's windows
    between two planes, each proposing its own copy."""
    if polygon is None or len(groups) < 2:
        return groups
    edges = [group_edge(g, polygon, params) for g in groups]
    kept: list[int] = []  # indices into groups, the best supported first; a joining group takes its reference plane
    for i in sorted(range(len(groups)), key=lambda k: -groups[k].support):
        for a in kept:
            if edges[i] is None or edges[i] != edges[a]:
                continue
            ok, d, s = _joinable(groups[a], _span(groups[i]), params, max_gap=np.inf)
            if ok:
                _absorb(groups[a], groups[i], d, s)
                break
        else:
            kept.append(i)
    return [groups[i] for i in sorted(kept)]  # the order they were found in


# ----------------------------------------------------------------------------------------------------------------------
# Frames and footprint edges


def fit_facade_frame(points_xyz: np.ndarray, outward: np.ndarray | None = None,
                     t0: float | None = None) -> FacadeFrame:
    """A :class:`FacadeFrame` fitted to façade points by PCA of their xy (normal = smallest eigenvector, horizontal).

    ``outward`` (a horizontal direction, e.g. towards the sensor or away from the footprint) orients the normal; the
    origin is on the fitted plane at the smallest s of the points and at height ``t0`` (default: lowest point).
    """
    xyz = np.asarray(points_xyz, dtype=np.float64)
    if len(xyz) < 3:
        raise ValueError("a façade frame needs at least three points")
    normal2, c = fit_line_2d(xyz[:, :2])
    if outward is not None and float(np.asarray(outward, dtype=np.float64)[:2] @ normal2) < 0:
        normal2, c = -normal2, -c
    u = np.array([-normal2[1], normal2[0], 0.0])  # n = u x z  <=>  u = (-n_y, n_x)
    s = xyz[:, :2] @ u[:2]
    z0 = float(xyz[:, 2].min()) if t0 is None else float(t0)
    origin_xy = s.min() * u[:2] - c * normal2
    return FacadeFrame(origin=np.array([origin_xy[0], origin_xy[1], z0]), u=u)


def footprint_edges(polygon) -> np.ndarray:
    """Edges (E, 2, 2) of a footprint: polygon parts in order, exterior ring then interior rings, vertex k -> k+1."""
    parts = list(getattr(polygon, "geoms", [polygon]))
    edges = []
    for part in parts:
        for ring in [part.exterior, *part.interiors]:
            coords = np.asarray(ring.coords)[:, :2]
            edges.append(np.stack([coords[:-1], coords[1:]], axis=1))
    return np.concatenate(edges) if edges else np.zeros((0, 2, 2))


def match_footprint_edge(frame: FacadeFrame, s_range: tuple[float, float], polygon,
                         params: "FacadeParams") -> tuple[int | None, bool | None]:
    """The footprint edge a façade lies on (normal within ``edge_angle_deg``, distance <= ``max_footprint_distance``).

    Returns (edge index in :func:`footprint_edges` order or ``None``, whether the frame's normal points out of the
    footprint, ``None`` when undecided). Among candidates the edge with the longest overlap along the wall wins.
    """
    edges = footprint_edges(polygon)
    if len(edges) == 0:
        return None, None
    n2 = frame.normal[:2]
    u2 = frame.u[:2]
    vec = edges[:, 1] - edges[:, 0]
    length = np.linalg.norm(vec, axis=1)
    valid = length > 1e-9
    dirs = vec / np.maximum(length, 1e-12)[:, None]
    parallel = np.abs(dirs @ u2) > np.cos(np.radians(params.planes.edge_angle_deg))
    ends_st = (edges - frame.origin[:2]) @ np.stack([u2, n2], axis=1)  # (E, 2, 2): (s, d) of both ends
    mid = frame.origin[:2] + 0.5 * (s_range[0] + s_range[1]) * u2
    # distance of the façade's segment (its middle) to the edge line, and the overlap along the wall
    rel = mid - edges[:, 0]
    mid_d = np.abs(dirs[:, 0] * rel[:, 1] - dirs[:, 1] * rel[:, 0])
    e_lo, e_hi = ends_st[:, :, 0].min(axis=1), ends_st[:, :, 0].max(axis=1)
    overlap = np.minimum(e_hi, s_range[1]) - np.maximum(e_lo, s_range[0])
    ok = valid & parallel & (mid_d <= params.join.max_footprint_distance) & (overlap > 0)
    if not ok.any():
        return None, None
    best = int(np.argmax(np.where(ok, overlap, -np.inf)))
    # outward: the footprint lies on the -n side of the façade; probe both sides of the edge at the overlap centre
    centre = frame.origin[:2] + 0.5 * (max(e_lo[best], s_range[0]) + min(e_hi[best], s_range[1])) * u2
    on_edge = edges[best, 0] + dirs[best] * float((centre - edges[best, 0]) @ dirs[best])
    probe = min(0.05, 0.25 * float(length[best]))
    inside_front = shapely.contains_xy(polygon, *(on_edge + probe * n2))
    inside_back = shapely.contains_xy(polygon, *(on_edge - probe * n2))
    outward = None if inside_front == inside_back else bool(inside_back)
    return best, outward


def check_points(xyz: np.ndarray, source: str | None) -> None:
    """Refuse empty or non-finite clouds with a one-line error."""
    if len(xyz) == 0:
        raise InputError("the point cloud is empty", source)
    if not np.all(np.isfinite(xyz)):
        raise InputError("NaN or infinite point coordinates", source)
