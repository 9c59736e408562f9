"""Preprocessing (paper §3.1): LiDAR tiles + building footprints -> one point set per building.

Tiles are merged while streaming them chunk by chunk, so a building cut by a tile border comes out whole. Every point
within ``buffer`` of a footprint is assigned to exactly one building, the nearest footprint (distance 0 inside; ties go
to the footprint that comes first in the footprint file). Footprints whose status marks them as under construction are
dropped together with their points, and so are buildings lower than ``min_height``. Colour is quantised to 8 bits and a
:class:`~lidarmap.frame.LocalFrame` is chosen for the downstream float32 stages.

Stage API (arrays and small dataclasses, no files)::

    assign_points(xy, footprints, buffer) -> (building index, -1 = none; distance to that footprint)
    split_buildings(cloud, footprints, params) -> list[BuildingPoints]
    prep_cloud(cloud, footprints, params) -> PrepResult

Streaming driver and output (the only functions here that touch files)::

    scan_tiles(paths, crs=None) -> TileSet                  # headers only: CRS agreement, bounds, point counts
    prep_tiles(paths, footprints, params, crs=None) -> PrepResult
    write_prep(out_dir, result) -> Path                     # buildings/<id>.laz, buildings.csv, frame.json, prep.json
    read_prep_index(out_dir) -> list[dict]

Memory of :func:`prep_tiles`: one chunk of input (``chunk_points``) plus the kept points (those within ``buffer`` of a
non-excluded footprint, all attributes, about 60-80 bytes each) plus the ground points near footprints (one float per
(point, footprint) pair). It does not grow with the number of points that lie away from the footprints.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import shapely
from pyproj import CRS
from shapely.geometry.base import BaseGeometry

from lidarmap.config import check_params
from lidarmap.core import Footprints, PointCloud
from lidarmap.errors import ConfigError
from lidarmap.frame import LocalFrame
from lidarmap.io.crs import same_crs
from lidarmap.io.footprints import check_overlap

__all__ = ["PrepParams", "BuildingPoints", "PrepSummary", "PrepResult", "FootprintIndex", "DEFAULT_EXCLUDED_STATUSES",
           "assign_points", "split_buildings", "prep_cloud", "SpooledPrep", "BuildingEntry", "canonical_order",
           "chunk_columns"]

#: Status values (compared case-insensitively, whitespace collapsed) that mark a footprint as not built yet.
DEFAULT_EXCLUDED_STATUSES: tuple[str, ...] = (
    "under construction", "construction", "in construction", "planned", "proposed",
    "in aanbouw", "bouw gestart", "bouwvergunning verleend", "plan",          # Dutch BAG / BGT
    "en construction", "en cours de construction", "en projet",               # French
    "im bau", "in bau", "geplant",                                            # German
)

#: Name of the extra dimension holding each point's distance to its footprint (0 inside).
DISTANCE_DIM = "footprint_distance"


@dataclasses.dataclass(frozen=True)
class PrepParams:
    """Parameters of ``lidarmap prep`` (``[prep]`` table of a config file).

    Selection
        buffer (5.0): keep points within this horizontal distance (CRS units, metres) of a footprint (paper: 5 m).
        id_field ("id"): footprint property that holds the building id (then the GeoJSON feature ``id``, then the
            feature's index). Used when the footprints are read (the CLI's ``--id-field``).
        status_field ("status"): footprint property that holds the construction status.
        excluded_statuses (:data:`DEFAULT_EXCLUDED_STATUSES`): status values whose footprints are dropped with their
            points ("under construction", "in aanbouw", "bouw gestart", ...); compared case-insensitively with
            whitespace collapsed, whole value only.
    Height
        min_height (3.0): buildings lower than this (metres) are dropped with their points (paper: 3 m); 0 keeps all.
        height_field ("height"): footprint property with the building height in metres; used when present and
            numeric, otherwise the height is measured from the points.
        roof_percentile (95.0): measured height = this percentile of z of the points inside the footprint ...
        ground_class (2): ... minus the median z of the points of this class within ``ground_radius`` of the
            footprint's bounding box (any building's or none's: ground points are collected before assignment) ...
        ground_radius (10.0): ... (metres) ...
        ground_percentile (5.0): ... or, where no such point exists, minus this percentile of z of all points
            assigned to the building.
    Output
        rotation_deg (0.0): rotation about z of the local frame (degrees, counter-clockwise from the CRS x axis),
            e.g. to align the local axes with the streets; the offset is the kept points' minimum corner, rounded
            down to whole metres.
        quantize_rgb (True): store colour with 8-bit precision: the red/green/blue fields hold ``v8 * 257``
            (the LAS 16-bit range, so readers see the right colour) and ``PointCloud.rgb8()`` returns ``v8`` exactly.
            The 16-bit/8-bit decision is taken once over all kept points.
        distance_dim (True): add the extra dimension ``footprint_distance`` (float32, metres, 0 inside) to the
            building point clouds.
        chunk_points (1000000): points per chunk when streaming tiles (memory per chunk about 100 bytes/point).
    """

    section = "prep"
    constraints: ClassVar[dict[str, str]] = {
        "buffer": ">= 0",
        "min_height": ">= 0",
        "roof_percentile": ">= 0",
        "ground_class": ">= 0",
        "ground_radius": ">= 0",
        "ground_percentile": ">= 0",
        "rotation_deg": ">= 0",
        "chunk_points": ">= 0",
    }

    buffer: float = 5.0
    id_field: str = "id"
    status_field: str = "status"
    excluded_statuses: tuple[str, ...] = DEFAULT_EXCLUDED_STATUSES
    min_height: float = 3.0
    height_field: str = "height"
    roof_percentile: float = 95.0
    ground_class: int = 2
    ground_radius: float = 10.0
    ground_percentile: float = 5.0
    rotation_deg: float = 0.0
    quantize_rgb: bool = True
    distance_dim: bool = True
    chunk_points: int = 1_000_000

    def __post_init__(self) -> None:
        check_params(self)
        checks = [
            (math.isfinite(self.buffer) and self.buffer >= 0, "buffer must be a finite number >= 0"),
            (math.isfinite(self.min_height), "min_height must be finite"),
            (0 <= self.roof_percentile <= 100, "roof_percentile must be in [0, 100]"),
            (0 <= self.ground_percentile <= 100, "ground_percentile must be in [0, 100]"),
            (math.isfinite(self.ground_radius) and self.ground_radius >= 0, "ground_radius must be >= 0"),
            (math.isfinite(self.rotation_deg), "rotation_deg must be finite"),
            (self.chunk_points >= 1, "chunk_points must be >= 1"),
            (bool(self.id_field) and bool(self.status_field) and bool(self.height_field),
             "id_field, status_field and height_field must not be empty"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"prep parameters: {message}")

    def is_excluded(self, status: Any) -> bool:
        """True when a footprint's status value marks it as not built yet."""
        if status is None:
            return False
        return _norm_status(status) in {_norm_status(s) for s in self.excluded_statuses}


def _norm_status(value: Any) -> str:
    return " ".join(str(value).split()).casefold()


@dataclasses.dataclass
class BuildingPoints:
    """The points of one building.

    ``cloud`` is in CRS coordinates (float64) with every attribute of the input (colour quantised, see
    :class:`PrepParams`) plus ``footprint_distance`` when enabled. ``height`` is in metres; ``height_source`` is
    "footprint" (the footprint's height property), "points" (roof percentile minus ground points' median) or
    "points-no-ground" (no ground point near: roof percentile minus a low percentile of the building's points).
    """

    id: str
    cloud: PointCloud
    footprint: BaseGeometry
    properties: dict[str, Any]
    height: float
    height_source: str
    ground_z: float
    points_inside: int
    status: str | None = None

    def __len__(self) -> int:
        return len(self.cloud)

    @property
    def distance(self) -> np.ndarray | None:
        """Each point's distance to the footprint (0 inside), when ``distance_dim`` was on."""
        return self.cloud.attrs.get(DISTANCE_DIM)

    def rgb8(self) -> np.ndarray | None:
        """8-bit colour (N, 3) or ``None``."""
        return self.cloud.rgb8()

    def local_xyz(self, frame: LocalFrame) -> np.ndarray:
        """The points in a local frame (float64; safe to cast to float32)."""
        return frame.to_local(self.cloud.xyz)


@dataclasses.dataclass(kw_only=True)
class PrepSummary:
    """What prep found, whether the points are loaded (:class:`PrepResult`) or spooled (:class:`SpooledPrep`).

    ``dropped`` maps footprint ids to the reason they produced no building ("under construction (status ...)",
    "lower than 3 m (...)", "no points within 5 m", "no points inside the footprint"), and the footprints file's
    features that gave no polygon ("null geometry", "zero area", ...; :func:`lidarmap.io.footprints.read_footprints`).
    """

    dropped: dict[str, str]
    frame: LocalFrame
    crs: CRS | None
    params: PrepParams
    repaired: list[str] = dataclasses.field(default_factory=list)  # ids of invalid footprints repaired (make_valid)
    points_read: int = 0
    points_kept: int = 0
    footprints: int = 0
    sources: list[str] = dataclasses.field(default_factory=list)
    footprint_source: str | None = None
    seconds: float = 0.0

    @property
    def points_per_second(self) -> float:
        return self.points_read / self.seconds if self.seconds > 0 else float("nan")


@dataclasses.dataclass(kw_only=True)
class PrepResult(PrepSummary):
    """Output of :func:`prep_tiles` / :func:`prep_cloud`: every building with its points."""

    buildings: list[BuildingPoints]


# ----------------------------------------------------------------------------------------------------------------
# Point -> footprint assignment
# ----------------------------------------------------------------------------------------------------------------


class FootprintIndex:
    """A grid index of footprints for vectorised distance queries of many points.

    Built once per footprint set and ``reach`` (the largest distance asked for). The grid's cells list the
    footprints that lie within ``reach`` of them (exact cell-to-polygon distance), and flag the cells that lie wholly
    inside a footprint. A query expands each point to its cell's (point, footprint) candidates, culls them by the
    footprints' bounding boxes grown by ``reach``, then resolves them exactly: inside (distance 0) from the cell flag
    or ``shapely.contains_xy``, the rest by a numpy point-to-segment distance over the footprint's edges (all rings,
    holes included). Everything is array code; Python loops run over batches only.
    """

    #: Upper bounds on the work arrays (elements), which keeps memory per batch at a few tens of MB.
    POINT_BATCH = 262_144
    EDGE_BATCH = 2_000_000
    MAX_CELLS = 4_000_000
    MAX_ENTRIES = 8_000_000

    def __init__(self, polygons: Sequence[BaseGeometry] | np.ndarray, reach: float):
        polys = np.asarray(list(polygons) if not isinstance(polygons, np.ndarray) else polygons, dtype=object)
        if polys.ndim != 1 or not len(polys):
            raise ValueError("FootprintIndex needs at least one footprint")
        if not math.isfinite(reach) or reach < 0:
            raise ValueError(f"reach must be a finite number >= 0, got {reach}")
        self.polygons = polys
        self.reach = float(reach)
        shapely.prepare(polys)
        bounds = shapely.bounds(polys)
        self.lo = bounds[:, :2] - self.reach
        self.hi = bounds[:, 2:] + self.reach
        self.origin = self.lo.min(axis=0)
        self.lo -= self.origin
        self.hi -= self.origin
        # Edges of every ring of every part, relative to the origin, grouped by footprint.
        parts, part_of = shapely.get_parts(polys, return_index=True)
        rings, ring_of = shapely.get_rings(parts, return_index=True)
        coords, coord_ring = shapely.get_coordinates(rings, return_index=True)
        coords = coords - self.origin
        same = coord_ring[:-1] == coord_ring[1:]
        a, b = coords[:-1][same], coords[1:][same]
        edge_fp = part_of[ring_of[coord_ring[:-1][same]]]
        order = np.argsort(edge_fp, kind="stable")
        self.ax, self.ay = a[order, 0], a[order, 1]
        self.dx, self.dy = b[order, 0] - self.ax, b[order, 1] - self.ay
        self.len2 = self.dx * self.dx + self.dy * self.dy
        self.edge_count = np.bincount(edge_fp, minlength=len(polys))
        self.edge_start = np.concatenate([[0], np.cumsum(self.edge_count)[:-1]])
        self._build_grid()

    def __len__(self) -> int:
        return len(self.polygons)

    def _build_grid(self) -> None:
        size = self.hi - self.lo
        extent = np.maximum(self.hi.max(axis=0), 1e-9)
        # cells about half the reach (a tight cull) but not much smaller than the footprints, bounded in number
        cell = max(self.reach / 2, 0.25 * float(np.median(size.max(axis=1))) - self.reach / 2, 0.5,
                   math.sqrt(extent[0] * extent[1] / self.MAX_CELLS))
        while True:
            ix0, iy0 = (self.lo // cell).astype(np.int64).T
            ix1, iy1 = (self.hi // cell).astype(np.int64).T
            wx, wy = ix1 - ix0 + 1, iy1 - iy0 + 1
            counts = wx * wy
            if counts.sum() <= self.MAX_ENTRIES:
                break
            cell *= 1.5
        self.cell = cell
        self.nx, self.ny = int(extent[0] // cell) + 1, int(extent[1] // cell) + 1
        fp = np.repeat(np.arange(len(counts)), counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        cx = ix0[fp] + k % wx[fp]
        cy = iy0[fp] + k // wx[fp]
        # exact cull: keep a (cell, footprint) entry only when the footprint is within reach of the cell
        x0, y0 = cx * cell + self.origin[0], cy * cell + self.origin[1]
        boxes = shapely.box(x0, y0, x0 + cell, y0 + cell)
        near = shapely.dwithin(self.polygons[fp], boxes, self.reach)
        full = shapely.contains(self.polygons[fp[near]], boxes[near])
        fp, cell_id = fp[near], (cy * self.nx + cx)[near]
        order = np.lexsort((fp, cell_id))
        self.cell_fp = fp[order]
        self.cell_full = full[order]
        self.cell_count = np.bincount(cell_id, minlength=self.nx * self.ny)
        self.cell_start = np.concatenate([[0], np.cumsum(self.cell_count)[:-1]])

    def _candidates(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point, footprint, cell wholly inside) for the points in cells within reach of the footprint."""
        cx = np.floor(x / self.cell)
        cy = np.floor(y / self.cell)
        ok = (cx >= 0) & (cx < self.nx) & (cy >= 0) & (cy < self.ny)
        pts = np.flatnonzero(ok)
        cell = cy[ok].astype(np.int64) * self.nx + cx[ok].astype(np.int64)
        cnt = self.cell_count[cell]
        pt = np.repeat(pts, cnt)
        entry = np.repeat(self.cell_start[cell] - (np.cumsum(cnt) - cnt), cnt) + np.arange(len(pt))
        fp = self.cell_fp[entry]
        px, py = x[pt], y[pt]
        keep = (px >= self.lo[fp, 0]) & (px <= self.hi[fp, 0]) & (py >= self.lo[fp, 1]) & (py <= self.hi[fp, 1])
        return pt[keep], fp[keep], self.cell_full[entry[keep]]

    def _inside(self, x: np.ndarray, y: np.ndarray, pt: np.ndarray, fp: np.ndarray, full: np.ndarray) -> np.ndarray:
        inside = full.copy()
        test = np.flatnonzero(~full)
        if len(test):
            inside[test] = shapely.contains_xy(self.polygons[fp[test]], x[pt[test]] + self.origin[0],
                                               y[pt[test]] + self.origin[1])
        return inside

    def _edge_distance(self, px: np.ndarray, py: np.ndarray, fp: np.ndarray) -> np.ndarray:
        """Distance from each point to the boundary of its paired footprint (arrays of equal length)."""
        out = np.empty(len(fp))
        ne = self.edge_count[fp]
        ends = np.cumsum(ne)
        start = 0
        while start < len(fp):
            # the largest batch whose expansion stays under EDGE_BATCH (at least one pair)
            base = ends[start - 1] if start else 0
            stop = max(int(np.searchsorted(ends, base + self.EDGE_BATCH, side="right")), start + 1)
            sl = slice(start, stop)
            n = ne[sl]
            first = np.cumsum(n) - n
            rep = np.repeat(np.arange(stop - start), n)
            e = np.repeat(self.edge_start[fp[sl]] - first, n) + np.arange(int(n.sum()))
            wx = px[sl][rep] - self.ax[e]
            wy = py[sl][rep] - self.ay[e]
            dx, dy, len2 = self.dx[e], self.dy[e], self.len2[e]
            with np.errstate(invalid="ignore", divide="ignore"):
                t = np.where(len2 > 0, (wx * dx + wy * dy) / len2, 0.0)
            np.clip(t, 0.0, 1.0, out=t)
            wx -= t * dx
            wy -= t * dy
            d2 = wx * wx + wy * wy
            out[sl] = np.sqrt(np.minimum.reduceat(d2, first))
            start = stop
        return out

    def _batches(self, xy: np.ndarray) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        for start in range(0, len(xy), self.POINT_BATCH):
            yield (start, xy[start:start + self.POINT_BATCH, 0] - self.origin[0],
                   xy[start:start + self.POINT_BATCH, 1] - self.origin[1])

    def _check(self, max_distance: float | None) -> float:
        max_distance = self.reach if max_distance is None else float(max_distance)
        if max_distance > self.reach:
            raise ValueError(f"max_distance {max_distance} exceeds the index reach {self.reach}")
        return max_distance

    def pairs(self, xy: np.ndarray, max_distance: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All (point, footprint, distance) with distance <= ``max_distance`` (default ``reach``; 0 inside)."""
        max_distance = self._check(max_distance)
        out_pt, out_fp, out_d = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
        for start, x, y in self._batches(xy):
            pt, fp, full = self._candidates(x, y)
            inside = self._inside(x, y, pt, fp, full)
            dist = np.zeros(len(pt))
            out = np.flatnonzero(~inside)
            if len(out):
                dist[out] = self._edge_distance(x[pt[out]], y[pt[out]], fp[out])
            keep = dist <= max_distance
            out_pt.append(pt[keep] + start)
            out_fp.append(fp[keep])
            out_d.append(dist[keep])
        return np.concatenate(out_pt), np.concatenate(out_fp), np.concatenate(out_d)

    def near_pairs(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point, footprint) for points in the footprint's grown bounding box and in a grid cell within ``reach``
        of it: a cheap superset of the pairs within ``reach`` (at most a cell diagonal farther)."""
        out_pt, out_fp = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for start, x, y in self._batches(xy):
            pt, fp, _ = self._candidates(x, y)
            out_pt.append(pt + start)
            out_fp.append(fp)
        return np.concatenate(out_pt), np.concatenate(out_fp)

    def assign(self, xy: np.ndarray, max_distance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Nearest footprint of each point within ``max_distance``: (index, -1 = none; distance, inf = none).

        A point inside one or more footprints goes to the first of them (lowest index) with distance 0; any other
        point within ``max_distance`` to the nearest footprint (ties: lowest index; a point on a boundary has
        distance 0).
        """
        max_distance = self._check(max_distance)
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        index = np.full(len(xy), -1, dtype=np.int64)
        distance = np.full(len(xy), np.inf)
        for start, x, y in self._batches(xy):
            pt, fp, full = self._candidates(x, y)
            if not len(pt):
                continue
            inside = self._inside(x, y, pt, fp, full)
            # inside: the lowest footprint index among those containing the point
            owner = np.full(len(x), np.iinfo(np.int64).max)
            np.minimum.at(owner, pt[inside], fp[inside])
            has = owner != np.iinfo(np.int64).max
            index[start + np.flatnonzero(has)] = owner[has]
            distance[start + np.flatnonzero(has)] = 0.0
            # outside every footprint: exact distances, then the nearest (ties: lowest index)
            rest = np.flatnonzero(~has[pt])
            if not len(rest):
                continue
            pt, fp = pt[rest], fp[rest]
            dist = self._edge_distance(x[pt], y[pt], fp)
            keep = dist <= max_distance
            pt, fp, dist = pt[keep], fp[keep], dist[keep]
            order = np.lexsort((fp, dist, pt))
            pt, fp, dist = pt[order], fp[order], dist[order]
            first = np.ones(len(pt), dtype=bool)
            first[1:] = pt[1:] != pt[:-1]
            index[start + pt[first]] = fp[first]
            distance[start + pt[first]] = dist[first]
        return index, distance


def _polygons_of(footprints: Footprints | Sequence[BaseGeometry] | np.ndarray) -> np.ndarray:
    if isinstance(footprints, Footprints):
        return footprints.polygons
    return np.asarray(list(footprints), dtype=object)


def assign_points(xy: np.ndarray, footprints: Footprints | Sequence[BaseGeometry] | np.ndarray,
                  buffer: float) -> tuple[np.ndarray, np.ndarray]:
    """Assign each point (N, 2+; only x and y are used) to its nearest footprint within ``buffer``.

    Returns ``(index, distance)``: ``index`` int64 (N,) into the footprints, -1 when no footprint is within
    ``buffer``; ``distance`` float64 (N,), 0 inside (or on the boundary of) the footprint, ``inf`` when unassigned.
    Ties go to the footprint with the lower index. Footprints must be in the points' CRS.
    """
    xy = np.asarray(xy, dtype=np.float64)
    xy = xy[:, :2] if xy.ndim == 2 else xy.reshape(-1, 2)
    polys = _polygons_of(footprints)
    if not len(polys) or not len(xy):
        return np.full(len(xy), -1, dtype=np.int64), np.full(len(xy), np.inf)
    return FootprintIndex(polys, buffer).assign(xy)


# ----------------------------------------------------------------------------------------------------------------
# Accumulation and per-building results
# ----------------------------------------------------------------------------------------------------------------


def _property_height(properties: dict[str, Any], field: str) -> float | None:
    value = properties.get(field)
    if value is None or isinstance(value, bool):
        return None
    try:
        height = float(str(value).strip().replace(",", ".")) if isinstance(value, str) else float(value)
    except (TypeError, ValueError):
        return None
    return height if math.isfinite(height) else None


#: Spool column of each kept point's distance to its footprint (float64 while streaming).
_DISTANCE = "__distance"


def chunk_columns(chunk: PointCloud) -> dict[str, np.ndarray]:
    """A chunk as spool columns: ``xyz`` and every attribute."""
    return {"xyz": chunk.xyz, **chunk.attrs}


class _Accumulator:
    """Collects, chunk after chunk, the points kept for each footprint and the ground points near them, in two
    :class:`~lidarmap.io.spool.ColumnSpool` keyed by footprint (on disk under ``work_dir`` when given, so memory holds
    one chunk and one spool buffer whatever the input size)."""

    def __init__(self, footprints: Footprints, params: PrepParams, work_dir: Path | None = None):
        from lidarmap.io.spool import ColumnSpool

        self.footprints = footprints
        self.params = params
        self.excluded = np.array([params.is_excluded(p.get(params.status_field)) for p in footprints.properties],
                                 dtype=bool)
        self.index = FootprintIndex(footprints.polygons, params.buffer)
        self.ground_index = FootprintIndex(footprints.polygons, params.ground_radius)
        buffer_rows = max(params.chunk_points, 100_000)
        self.points = ColumnSpool(len(footprints), None if work_dir is None else work_dir / "points", buffer_rows)
        self.ground = ColumnSpool(len(footprints), None if work_dir is None else work_dir / "ground", buffer_rows)
        self.extra_dims: list[str] | None = None
        self.missing: set[str] = set()  # attributes some tile lacks: dropped from the output (as in concatenate)
        self.points_read = 0

    def _columns(self, chunk: PointCloud, rows: np.ndarray, distance: np.ndarray) -> dict[str, np.ndarray]:
        columns = chunk_columns(chunk.subset(rows))
        columns[_DISTANCE] = distance
        if self.points.dtypes:  # tiles of other point formats: fill what they lack, drop what the first lacked
            for name in set(self.points.dtypes) - set(columns):
                self.missing.add(name)
                columns[name] = np.zeros((len(rows), *self.points.shapes[name]), self.points.dtypes[name])
            columns = {k: v for k, v in columns.items() if k in self.points.dtypes}
        return columns

    def add(self, chunk: PointCloud) -> None:
        self.points_read += len(chunk)
        if not len(chunk):
            return
        if self.extra_dims is None:
            self.extra_dims = list(chunk.extra_dims)
        xy = chunk.xyz[:, :2]
        index, distance = self.index.assign(xy)
        hit = index >= 0
        excluded = np.zeros(len(index), dtype=bool)
        excluded[hit] = self.excluded[index[hit]]
        keep = np.flatnonzero(hit & ~excluded)
        if len(keep):
            self.points.add(index[keep], self._columns(chunk, keep, distance[keep]))
        classes = chunk.attrs.get("classification")
        if classes is not None:
            ground = np.flatnonzero(classes == self.params.ground_class)
            if len(ground):
                pt, fp = self.ground_index.near_pairs(xy[ground])
                self.ground.add(fp, {"z": chunk.xyz[ground[pt], 2]})

    def finish(self, crs: CRS | None, sources: list[str], seconds: float) -> "SpooledPrep":
        return _finish(self, crs, sources, seconds)


def _percentile(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


@dataclasses.dataclass
class BuildingEntry:
    """One building of a :class:`SpooledPrep` before its points are loaded."""

    id: str
    key: int  # footprint index (spool key)
    footprint: BaseGeometry
    properties: dict[str, Any]
    height: float
    height_source: str
    ground_z: float
    points: int
    points_inside: int
    bounds: tuple[float, float, float, float]  # of its points (x0, y0, x1, y1)
    status: str | None = None


def _building_entry(acc: _Accumulator, i: int, dropped: dict[str, str]) -> BuildingEntry | None:
    """The entry of footprint ``i`` from its spooled points, or ``None`` (reason in ``dropped``)."""
    params, fps = acc.params, acc.footprints
    fid, props = fps.ids[i], fps.properties[i]
    status = props.get(params.status_field)
    if acc.excluded[i]:
        dropped[fid] = f"under construction ({params.status_field}={status!r})"
        return None
    if acc.points.counts[i] == 0:
        dropped[fid] = f"no points within {params.buffer:g} m"
        return None
    cols = acc.points.get(i, ["xyz", _DISTANCE])
    z, inside = cols["xyz"][:, 2], cols[_DISTANCE] == 0
    ground = _percentile(acc.ground.get(i)["z"], 50.0) if acc.ground.counts[i] else float("nan")
    low = _percentile(z, params.ground_percentile)
    given = _property_height(props, params.height_field)
    if given is not None:
        height, source, ground_z = given, "footprint", ground if math.isfinite(ground) else low
    elif not inside.any():
        dropped[fid] = "no points inside the footprint (height unknown)"
        return None
    elif math.isfinite(ground):
        height, source, ground_z = _percentile(z[inside], params.roof_percentile) - ground, "points", ground
    else:
        height, source, ground_z = _percentile(z[inside], params.roof_percentile) - low, "points-no-ground", low
    if height < params.min_height:
        dropped[fid] = f"lower than {params.min_height:g} m ({height:.2f} m, {source})"
        return None
    lo, hi = cols["xyz"][:, :2].min(axis=0), cols["xyz"][:, :2].max(axis=0)
    return BuildingEntry(id=fid, key=i, footprint=fps.polygons[i], properties=dict(props), height=float(height),
                         height_source=source, ground_z=float(ground_z), points=int(acc.points.counts[i]),
                         points_inside=int(inside.sum()), bounds=(float(lo[0]), float(lo[1]), float(hi[0]),
                                                                  float(hi[1])),
                         status=None if status is None else str(status))


def _finish(acc: _Accumulator, crs: CRS | None, sources: list[str], seconds: float) -> "SpooledPrep":
    dropped: dict[str, str] = dict(acc.footprints.rejected)
    entries = [e for e in (_building_entry(acc, i, dropped) for i in range(len(acc.footprints))) if e is not None]
    if entries:
        zmin = min(float(acc.points.get(e.key, ["xyz"])["xyz"][:, 2].min()) for e in entries)
        corner = np.array([[min(e.bounds[0] for e in entries), min(e.bounds[1] for e in entries), zmin]])
        frame = LocalFrame.around(corner, rotation_deg=acc.params.rotation_deg)
    else:
        x0, y0, _, _ = acc.footprints.bounds
        frame = LocalFrame(offset=(math.floor(x0), math.floor(y0), 0.0), rotation_deg=acc.params.rotation_deg)
    names = [n for n in acc.points.names if n not in acc.missing]
    rgb16 = False
    if acc.params.quantize_rgb and {"red", "green", "blue"} <= set(names):
        rgb16 = any(int(acc.points.get(e.key, [c])[c].max(initial=0)) > 255 for e in entries
                    for c in ("red", "green", "blue"))
    return SpooledPrep(entries=entries, dropped=dropped, repaired=list(acc.footprints.repaired), frame=frame, crs=crs, params=acc.params,
                       spool=acc.points, names=names, extra_dims=[d for d in (acc.extra_dims or []) if d in names],
                       rgb16=rgb16, points_read=acc.points_read, points_kept=int(sum(e.points for e in entries)),
                       footprints=len(acc.footprints), sources=sources, footprint_source=acc.footprints.source,
                       seconds=seconds, ground=acc.ground)


def canonical_order(columns: dict[str, np.ndarray]) -> np.ndarray:
    """The order that sorts points by x, y, z, then every attribute: a building's points come out in the same
    order however the input was tiled, chunked or read (results must not change with tile edges)."""
    keys = [columns[name] for name in sorted(columns) if name != "xyz" and columns[name].ndim == 1]
    xyz = columns["xyz"]
    return np.lexsort([*keys[::-1], xyz[:, 2], xyz[:, 1], xyz[:, 0]])


@dataclasses.dataclass(kw_only=True)
class SpooledPrep(PrepSummary):
    """Prep's result with the points still in the spool: per building an entry; :meth:`load` reads one building
    (memory: that building), :meth:`context` the other kept points around it. :meth:`close` removes the spool."""

    entries: list[BuildingEntry]
    spool: Any
    names: list[str]
    extra_dims: list[str]
    rgb16: bool
    ground: Any = None

    def _cloud(self, keys: Sequence[int]) -> PointCloud:
        cols = self.spool.get_many(list(keys), [*self.names])
        order = canonical_order({k: v for k, v in cols.items() if k != _DISTANCE})
        cols = {k: v[order] for k, v in cols.items()}
        distance = cols.pop(_DISTANCE)
        xyz = cols.pop("xyz")
        extra = list(self.extra_dims)
        if self.params.quantize_rgb and self.rgb16:
            for name in ("red", "green", "blue"):
                cols[name] = (cols[name] // 257).astype(np.uint16) * np.uint16(257)  # as PointCloud.rgb8
        elif self.params.quantize_rgb and "red" in cols:
            for name in ("red", "green", "blue"):
                cols[name] = cols[name].astype(np.uint8).astype(np.uint16) * np.uint16(257)
        if self.params.distance_dim:
            cols[DISTANCE_DIM] = distance.astype(np.float32)
            extra.append(DISTANCE_DIM)
        return PointCloud(xyz=xyz, attrs=cols, crs=self.crs, extra_dims=extra,
                          source=self.sources[0] if self.sources else None)

    def load(self, k: int) -> BuildingPoints:
        """Building ``k`` (index into ``entries``) with its points in :func:`canonical_order`."""
        e = self.entries[k]
        return BuildingPoints(id=e.id, cloud=self._cloud([e.key]), footprint=e.footprint,
                              properties=dict(e.properties), height=e.height, height_source=e.height_source,
                              ground_z=e.ground_z, points_inside=e.points_inside, status=e.status)

    def bounds_of(self, members: Sequence[int]) -> tuple[float, float, float, float]:
        """The union of the bounds of some entries' points."""
        b = np.array([self.entries[k].bounds for k in members])
        return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())

    def neighbours(self, members: Sequence[int], halo: float) -> list[int]:
        """Entries (other than ``members``) whose points' bounds come within ``halo`` of the members' bounds."""
        x0, y0, x1, y1 = self.bounds_of(members)
        taken = set(members)
        return [j for j, e in enumerate(self.entries) if j not in taken and e.bounds[0] <= x1 + halo
                and e.bounds[2] >= x0 - halo and e.bounds[1] <= y1 + halo and e.bounds[3] >= y0 - halo]

    def context(self, members: Sequence[int], halo: float) -> PointCloud | None:
        """The kept points of the other buildings within ``halo`` of the bounds of ``members`` (entry indices):
        segmentation context, or ``None`` when there are none."""
        near = self.neighbours(members, halo)
        if not near:
            return None
        cloud = self._cloud([self.entries[j].key for j in near])
        x0, y0, x1, y1 = self.bounds_of(members)
        xy = cloud.xyz[:, :2]
        inside = (xy[:, 0] >= x0 - halo) & (xy[:, 0] <= x1 + halo) & (xy[:, 1] >= y0 - halo) & (xy[:, 1] <= y1 + halo)
        return cloud.subset(np.flatnonzero(inside)) if inside.any() else None

    def materialise(self) -> PrepResult:
        """Every building loaded into a :class:`PrepResult` (memory: all kept points)."""
        return PrepResult(buildings=[self.load(k) for k in range(len(self.entries))], dropped=dict(self.dropped),
                          repaired=list(self.repaired), frame=self.frame, crs=self.crs, params=self.params, points_read=self.points_read,
                          points_kept=self.points_kept, footprints=self.footprints, sources=list(self.sources),
                          footprint_source=self.footprint_source, seconds=self.seconds)

    def close(self) -> None:
        self.spool.close()
        if self.ground is not None:
            self.ground.close()


def _footprints_in(footprints: Footprints, crs: CRS | None) -> Footprints:
    """The footprints in the points' CRS (reprojected when they differ)."""
    if crs is None or same_crs(footprints.crs, crs):
        return footprints
    return footprints.to_crs(crs)


def prep_cloud(cloud: PointCloud, footprints: Footprints, params: PrepParams | None = None) -> PrepResult:
    """Prep one in-memory cloud (all tiles already merged). Footprints in another CRS are reprojected."""
    params = params or PrepParams()
    clock = time.perf_counter()
    footprints = _footprints_in(footprints, cloud.crs)
    if len(cloud):
        lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
        check_overlap(footprints, (lo[0], lo[1], hi[0], hi[1]), cloud.source or "the point cloud")
    acc = _Accumulator(footprints, params)
    for start in range(0, len(cloud), params.chunk_points):
        acc.add(cloud.subset(slice(start, start + params.chunk_points)) if len(cloud) > params.chunk_points
                else cloud)
    return acc.finish(cloud.crs, [cloud.source] if cloud.source else [], time.perf_counter() - clock).materialise()


def split_buildings(cloud: PointCloud, footprints: Footprints, params: PrepParams | None = None) -> list[BuildingPoints]:
    """The per-building point sets of one cloud (see :func:`prep_cloud` for the frame and the dropped footprints)."""
    return prep_cloud(cloud, footprints, params).buildings


# ----------------------------------------------------------------------------------------------------------------
# Tiles (streaming)
# ----------------------------------------------------------------------------------------------------------------


def spool_chunks(chunks: Iterable[PointCloud], footprints: Footprints, crs: CRS | None,
                 bounds: tuple[float, float, float, float], name: str, sources: Sequence[str],
                 params: PrepParams | None = None, progress: Callable[[int], None] | None = None,
                 work_dir: str | Path | None = None) -> SpooledPrep:
    """Spool streamed point chunks (any number, any tiling) into the points kept per footprint.

    ``crs``/``bounds``/``name`` describe the whole input (the tiles' headers: :func:`lidarmap.io.tiles.scan_tiles`);
    footprints in another CRS are reprojected to ``crs`` and refused when they miss ``bounds``. With ``work_dir`` the
    spool lives on disk there (memory: a chunk and a spool buffer, whatever the input size); without, in memory.
    ``progress`` is called with the number of points of every chunk.
    """
    params = params or PrepParams()
    clock = time.perf_counter()
    footprints = _footprints_in(footprints, crs)
    check_overlap(footprints, bounds, name)
    acc = _Accumulator(footprints, params, None if work_dir is None else Path(work_dir))
    try:
        for chunk in chunks:
            acc.add(chunk)
            if progress is not None:
                progress(len(chunk))
        return acc.finish(crs, list(sources), time.perf_counter() - clock)
    except BaseException:
        acc.points.close()
        acc.ground.close()
        raise


# ----------------------------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------------------------


