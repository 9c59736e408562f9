"""Buildings found from the points alone, for campaigns without footprints (docs/mls.md).

1. **Wall cells.** The campaign's building points (class 6, or every non-ground point under the height rule:
   :class:`~lidarmap.facade.scan.PointClasses`) are binned on an xy grid of ``cell`` metres; a cell with at least
   ``min_cell_points`` points spanning at least ``min_height`` metres in z is a wall cell (a street wall seen from
   the road stacks metres of points in every cell; cars do not, tree crowns are weeded out next).
2. **Buildings by adjacency.** Wall cells closer than ``gap`` metres form one building (connected components of the
   dilated cell mask).
3. **Vertical planes.** Per building, RANSAC on the cells' xy (``planes`` lines at most): at least ``min_plane_share``
   of its points must lie within ``plane_tolerance`` of vertical planes, one of them ``min_length`` long; tree rows
   and clutter fail.
4. **Derived footprint.** The region behind the walls as the scanner saw them: from every wall cell, ``depth``
   metres on along the ray from the nearest sensor position (its "shadow"), as a polygon of grid cells. Its
   boundary runs along the seen walls (the façade joins it like a footprint edge) and its interior lies behind
   them (the façade's outward normal points to the street).
5. **Stable ids.** ``p`` + the first 10 hex digits of SHA-1 of the longest plane's midpoint rounded to ``id_grid``
   metres; the map reuses a stored building its footprint overlaps (:func:`merge_discovered`), so the next
   campaign refines the same building whatever its id would be.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import ClassVar

import numpy as np
import shapely
from scipy import ndimage
from scipy.spatial import cKDTree

from lidarmap.config import check_params
from lidarmap.facade.layers import mask_to_polygons


@dataclasses.dataclass(frozen=True)
class DiscoverParams:
    """Buildings without footprints (TOML table ``[discover]``). Lengths in metres.

        cell (0.5): xy grid of the wall cells.
        min_cell_points (5): a wall cell holds at least this many building points ...
        min_height (2.5): ... spanning at least this much height.
        gap (2.0): wall cells closer than this belong to the same building.
        planes (4): vertical planes fitted per building (RANSAC on the cells' xy) at most.
        plane_tolerance (0.4): cells within this distance of a plane belong to it.
        min_plane_share (0.6): a building needs this share of its points on its planes ...
        min_length (4.0): ... and a plane at least this long.
        depth (8.0): the derived footprint reaches this far behind the seen walls.
        id_grid (2.0): the id hashes the longest plane's midpoint rounded to this.
        ransac_trials (200): line hypotheses per plane (drawn from ``seed``).
    """

    section = "discover"
    constraints: ClassVar[dict[str, str]] = {
        "cell": "> 0", "min_cell_points": ">= 1", "min_height": ">= 0", "gap": ">= 0", "planes": ">= 1",
        "plane_tolerance": "> 0", "min_plane_share": "[0, 1]", "min_length": ">= 0", "depth": "> 0",
        "id_grid": "> 0", "ransac_trials": ">= 1",
    }

    cell: float = 0.5
    min_cell_points: int = 5
    min_height: float = 2.5
    gap: float = 2.0
    planes: int = 4
    plane_tolerance: float = 0.4
    min_plane_share: float = 0.6
    min_length: float = 4.0
    depth: float = 8.0
    id_grid: float = 2.0
    ransac_trials: int = 200

    def __post_init__(self) -> None:
        check_params(self)


class WallCells:
    """Building points binned on the xy grid, chunk by chunk: count and z range per occupied cell."""

    def __init__(self, origin: np.ndarray, cell: float):
        self.origin, self.cell = np.asarray(origin, dtype=np.float64)[:2], float(cell)
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, xyz: np.ndarray) -> None:
        if not len(xyz):
            return
        ij = np.floor((xyz[:, :2] - self.origin) / self.cell).astype(np.int64)
        key = (ij[:, 0] << 32) + ij[:, 1]
        self.parts.append(self._reduce(key, np.ones(len(key), np.int64), xyz[:, 2], xyz[:, 2]))
        if len(self.parts) > 8:
            self.parts = [self._reduce(*map(np.concatenate, zip(*self.parts)))]

    @staticmethod
    def _reduce(key, count, zlo, zhi):
        order = np.argsort(key, kind="stable")
        key, count, zlo, zhi = key[order], count[order], zlo[order], zhi[order]
        starts = np.flatnonzero(np.concatenate([[True], np.diff(key) != 0]))
        return (key[starts], np.add.reduceat(count, starts), np.minimum.reduceat(zlo, starts),
                np.maximum.reduceat(zhi, starts))

    def finish(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cell ij (K, 2), points per cell, z span per cell)."""
        if not self.parts:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0)
        key, count, zlo, zhi = self._reduce(*map(np.concatenate, zip(*self.parts)))
        ij = np.column_stack([key >> 32, key & 0xFFFFFFFF])
        return ij, count, zhi - zlo


@dataclasses.dataclass
class DiscoveredBuilding:
    """A building found from the points: its id, derived footprint, planes (xy segments) and wall points."""

    building_id: str
    footprint: shapely.Polygon
    planes: list[np.ndarray]  # (2, 2) segment ends per vertical plane
    n_points: int


def _components(ij: np.ndarray, gap_cells: int) -> np.ndarray:
    """Label of every cell: cells closer than the gap share one."""
    lo = ij.min(axis=0)
    shape = ij.max(axis=0) - lo + 1
    mask = np.zeros(shape, dtype=bool)
    mask[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = True
    grown = ndimage.binary_dilation(mask, iterations=max(gap_cells, 0)) if gap_cells > 0 else mask
    labels, _ = ndimage.label(grown, structure=np.ones((3, 3)))
    return labels[ij[:, 0] - lo[0], ij[:, 1] - lo[1]]


def _ransac_lines(xy: np.ndarray, weight: np.ndarray, params: DiscoverParams,
                  rng: np.random.Generator) -> tuple[list[np.ndarray], float]:
    """Up to ``planes`` lines (segments over their inliers) and the share of the weight on them."""
    left = np.ones(len(xy), dtype=bool)
    segments = []
    for _ in range(params.planes):
        idx = np.flatnonzero(left)
        if len(idx) < 2:
            break
        pairs = rng.integers(0, len(idx), (params.ransac_trials, 2))
        a, b = xy[idx[pairs[:, 0]]], xy[idx[pairs[:, 1]]]
        d = b - a
        length = np.linalg.norm(d, axis=1)
        ok = length > 1e-6
        if not ok.any():
            break
        n = np.column_stack([-d[ok, 1], d[ok, 0]]) / length[ok, None]
        p = xy[idx]
        dist = np.abs((p[None, :, 0] - a[ok][:, None, 0]) * n[:, None, 0]
                      + (p[None, :, 1] - a[ok][:, None, 1]) * n[:, None, 1])
        score = (dist <= params.plane_tolerance) @ weight[idx]
        best = int(np.argmax(score))
        inl = idx[dist[best] <= params.plane_tolerance]
        if weight[inl].sum() < 0.05 * weight.sum():
            break
        direction = d[ok][best] / length[ok][best]
        along = (xy[inl] - a[ok][best]) @ direction
        segments.append(a[ok][best] + np.outer([along.min(), along.max()], direction))
        left[inl] = False
    share = 1.0 - weight[left].sum() / max(weight.sum(), 1)
    return segments, float(share)


def _shadow(xy: np.ndarray, track: np.ndarray, params: DiscoverParams) -> shapely.Polygon | None:
    """The region behind the wall cells seen from the track, ``depth`` deep, as one polygon (the largest part)."""
    _, k = cKDTree(track[:, :2]).query(xy)
    away = xy - track[k, :2]
    away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9)
    steps = np.arange(0.0, params.depth + 1e-9, params.cell / 2)
    pts = (xy[:, None, :] + steps[None, :, None] * away[:, None, :]).reshape(-1, 2)
    lo = pts.min(axis=0) - params.cell
    ij = np.floor((pts - lo) / params.cell).astype(np.int64)
    mask = np.zeros(ij.max(axis=0) + 2, dtype=bool)
    mask[ij[:, 0], ij[:, 1]] = True
    mask = ndimage.binary_fill_holes(ndimage.binary_closing(mask, iterations=2))
    # mask_to_polygons takes rows as t and columns as s: our (i, j) = (x, y) grid transposed
    parts = mask_to_polygons(mask.T, lo[0], lo[1], params.cell)
    return max(parts, key=lambda p: p.area) if parts else None


def building_id(segment: np.ndarray, grid: float) -> str:
    """A stable id from the longest plane's midpoint rounded to ``grid`` metres."""
    mid = np.round(segment.mean(axis=0) / grid).astype(np.int64)
    return "p" + hashlib.sha1(f"{mid[0]},{mid[1]}".encode()).hexdigest()[:10]


def discover_buildings(cells: WallCells, track: np.ndarray, params: DiscoverParams,
                       seed: int = 0) -> list[DiscoveredBuilding]:
    """Buildings from a campaign's wall cells (module doc), ordered by id; ``track``: sensor positions (M, 3)."""
    ij, count, span = cells.finish()
    wall = (count >= params.min_cell_points) & (span >= params.min_height)
    ij, count = ij[wall], count[wall]
    if not len(ij) or not len(track):
        return []
    labels = _components(ij, int(np.ceil(params.gap / params.cell / 2)))
    xy = cells.origin + (ij + 0.5) * cells.cell
    rng = np.random.default_rng(seed)
    found: dict[str, DiscoveredBuilding] = {}
    for label in np.unique(labels):
        members = np.flatnonzero(labels == label)
        segments, share = _ransac_lines(xy[members], count[members].astype(np.float64), params, rng)
        lengths = [float(np.linalg.norm(s[1] - s[0])) for s in segments]
        if not segments or share < params.min_plane_share or max(lengths) < params.min_length:
            continue
        footprint = _shadow(xy[members], track, params)
        if footprint is None:
            continue
        bid = building_id(segments[int(np.argmax(lengths))], params.id_grid)
        while bid in found:  # two buildings rounding to one id: the later gets a suffix, deterministically
            bid += "b"
        found[bid] = DiscoveredBuilding(bid, footprint, segments, int(count[members].sum()))
    return [found[k] for k in sorted(found)]
