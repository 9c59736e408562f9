"""Sensor positions of a mobile campaign from whatever the data has (docs/mls.md).

The façade steps need the origin of every point's pulse (occlusion ray tracing, the reach test). They get it as
``Trajectory.position_at(gps_time)``; a campaign without a trajectory file is brought to that form here:

* **per-point origins** (``x_origin, y_origin, z_origin``): a trajectory over the *point number* (file order) whose
  knots are the origins themselves, thinned only where linear interpolation between kept knots reproduces every
  dropped origin within ``origin_tolerance`` (1 cm): the origins are the ray origins.
* **nothing** (no trajectory, no origins): the sensor path is estimated from the cloud (:func:`estimate_path`):
  the ground under a profile scanner is densest right below it (points per metre across the track fall as
  h² / (h² + c²)), so the ridge of the smoothed ground-point density on a 1 m grid is the path; its skeleton's
  longest branch gives the order; the cross-track position is refined per 2 m of track as the median offset of the
  ground points within ``refine_window`` of it (the density is symmetric about the nadir), and the height is the
  ground height there plus ``sensor_height``. Every point's sensor is then the path point its position projects to
  (the profile plane is across the track): its "time" is that arc length (:func:`path_times`). With GPS time the
  path is parameterised by time instead (:func:`timed_path`): per ``time_bin`` the median arc length of the points
  scanned then.

A campaign with an estimated path is marked so in the map and its Gaussians are widened by ``noise_factor`` in
fusion (:class:`SensorParams`).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, shortest_path
from scipy.spatial import cKDTree

from lidarmap.config import check_params
from lidarmap.core import Trajectory
from lidarmap.errors import InputError

#: ASPRS ground class.
GROUND = 2


@dataclasses.dataclass(frozen=True)
class SensorParams:
    """Sensor positions without a trajectory file (TOML table ``[sensors]``). Lengths in metres.

        sensor_height (2.5): height of the scanner above the road when the path is estimated (typical MLS vans:
            2-3 m; the simulator's default is 2.5).
        cell (1.0): grid cell of the ground-point density whose ridge is the path.
        smooth (1.5): standard deviation (m) of the Gaussian smoothing of that density.
        ridge_fraction (0.5): cells whose smoothed density reaches this fraction of the 99th percentile form the
            strip under the path (its skeleton's longest branch is the path).
        refine_window (3.0): the cross-track refinement takes the median offset of the ground points within this
            distance of the current path (twice).
        path_smooth (6.0): length (m) of the moving average along the estimated path.
        time_bin (0.2): seconds per knot of a path parameterised by GPS time.
        origin_tolerance (0.01): per-point origins dropped from the knots are reproduced within this distance.
        noise_factor (2.0): the Gaussians a campaign with an estimated path contributes to fusion are this many
            times wider (its sensor positions, hence its occlusion and point weights, are less certain).
        sample_points (2000000): points (a stride sample) the path estimation looks at.
    """

    section = "sensors"
    constraints: ClassVar[dict[str, str]] = {
        "sensor_height": ">= 0", "cell": "> 0", "smooth": "> 0", "ridge_fraction": "(0, 1]",
        "refine_window": "> 0", "path_smooth": ">= 0", "time_bin": "> 0", "origin_tolerance": ">= 0",
        "noise_factor": ">= 1", "sample_points": ">= 1000",
    }

    sensor_height: float = 2.5
    cell: float = 1.0
    smooth: float = 1.5
    ridge_fraction: float = 0.5
    refine_window: float = 3.0
    path_smooth: float = 6.0
    time_bin: float = 0.2
    origin_tolerance: float = 0.01
    noise_factor: float = 2.0
    sample_points: int = 2_000_000

    def __post_init__(self) -> None:
        check_params(self)


# ----------------------------------------------------------------------------------------------------------------------
# Per-point origins


def origin_knots(first: int, origins: np.ndarray, tolerance: float,
                 times: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Knots (clock, origins) of one chunk of points: the largest stride whose linear interpolation over the clock
    reproduces every origin within ``tolerance`` (the chunk's first and last points always kept). The clock is
    ``times`` (increasing) when given, else the point number counted from ``first``."""
    n = len(origins)
    index = np.arange(n)
    clock = first + index.astype(np.float64) if times is None else np.asarray(times, dtype=np.float64)
    for stride in (1024, 256, 64, 16, 4):
        keep = np.unique(np.concatenate([index[::stride], [n - 1]]))
        if len(keep) < 2:
            continue
        approx = np.column_stack([np.interp(clock, clock[keep], origins[keep, k]) for k in range(3)])
        if np.max(np.abs(approx - origins)) <= tolerance:
            return clock[keep], origins[keep]
    return clock, origins


def knots_trajectory(times: list[np.ndarray], positions: list[np.ndarray], source: str | None) -> Trajectory:
    """One trajectory from chunks of knots (strictly increasing times)."""
    t = np.concatenate(times)
    xyz = np.concatenate(positions)
    keep = np.concatenate([[True], np.diff(t) > 0])
    if keep.sum() < 2:  # a single point: a second knot a little later so that the trajectory is valid
        t, xyz = np.concatenate([t[:1], t[:1] + 1.0]), np.concatenate([xyz[:1], xyz[:1]])
        keep = np.ones(2, dtype=bool)
    return Trajectory(time=t[keep], xyz=xyz[keep], source=source)


# ----------------------------------------------------------------------------------------------------------------------
# The estimated path


def ground_points(xyz: np.ndarray, classification: np.ndarray | None, cell: float) -> np.ndarray:
    """The ground among ``xyz``: class 2 when the classification marks at least 5 % so, else the points within
    0.2 m of their ``cell``'s lowest point."""
    if classification is not None:
        ground = classification == GROUND
        if ground.mean() >= 0.05:
            return xyz[ground]
    ij = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / cell).astype(np.int64)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    _, inverse = np.unique(key, return_inverse=True)
    lowest = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(lowest, inverse, xyz[:, 2])
    return xyz[xyz[:, 2] <= lowest[inverse] + 0.2]


def _longest_branch(mask: np.ndarray) -> np.ndarray:
    """Grid cells (i, j) of the longest shortest path through the skeleton of ``mask`` (its largest component)."""
    from skimage.morphology import skeletonize

    skel = skeletonize(mask)
    cells = np.argwhere(skel)
    if len(cells) < 2:
        raise ValueError("no path strip")
    ids = -np.ones(skel.shape, dtype=np.int64)
    ids[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    rows, cols, weights = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        nb = cells + (di, dj)
        ok = (nb[:, 0] < skel.shape[0]) & (nb[:, 1] >= 0) & (nb[:, 1] < skel.shape[1])
        other = np.full(len(cells), -1)
        other[ok] = ids[nb[ok, 0], nb[ok, 1]]
        link = other >= 0
        rows.append(np.flatnonzero(link))
        cols.append(other[link])
        weights.append(np.full(link.sum(), np.hypot(di, dj)))
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(len(cells), len(cells))).tocsr()
    _, labels = connected_components(graph, directed=False)
    largest = np.flatnonzero(labels == np.bincount(labels).argmax())
    dist = shortest_path(graph, directed=False, indices=largest[0])
    a = largest[np.argmax(dist[largest])]
    dist, pred = shortest_path(graph, directed=False, indices=a, return_predecessors=True)
    b = largest[np.argmax(dist[largest])]
    chain = [b]
    while chain[-1] != a:
        chain.append(pred[chain[-1]])
    return cells[np.array(chain[::-1])]


def _resample(xy: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    fine = np.linspace(0.0, s[-1], max(int(s[-1] / step) + 2, 2))
    return np.column_stack([np.interp(fine, s, xy[:, 0]), np.interp(fine, s, xy[:, 1])])


def _smooth_line(xy: np.ndarray, window: int) -> np.ndarray:
    if window < 2 or len(xy) < 3:
        return xy
    pad = np.concatenate([np.repeat(xy[:1], window, 0), xy, np.repeat(xy[-1:], window, 0)])
    kernel = np.ones(2 * window + 1) / (2 * window + 1)
    out = np.column_stack([np.convolve(pad[:, k], kernel, mode="same")[window:-window] for k in range(2)])
    out[0], out[-1] = xy[0], xy[-1]
    return out


@dataclasses.dataclass
class SensorLine:
    """An estimated sensor path: positions (CRS, every ``step`` m along it) and their arc lengths."""

    xyz: np.ndarray
    s: np.ndarray

    def at(self, s: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(s, self.s, self.xyz[:, k]) for k in range(3)])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length of each point's foot on the path and its signed offset (left positive)."""
        tree = cKDTree(self.xyz[:, :2])
        _, k = tree.query(xy, workers=1)
        # the direction over +-TANGENT_SPAN m: a far point's foot must not follow the path's small wiggles
        tangent = np.gradient(_smooth_line(self.xyz[:, :2], int(TANGENT_SPAN / STEP)), axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        d = xy - self.xyz[k, :2]
        along = np.einsum("ij,ij->i", d, tangent[k])
        across = tangent[k, 0] * d[:, 1] - tangent[k, 1] * d[:, 0]
        return np.clip(self.s[k] + along, self.s[0], self.s[-1]), across


STEP = 0.5  # m between the estimated path's samples
TANGENT_SPAN = 10.0  # m either side over which the path's direction is measured when projecting points
EXTEND = 30.0  # m the strip's skeleton is continued at both ends before the refinement and the trim


def estimate_path(xyz: np.ndarray, classification: np.ndarray | None, params: SensorParams,
                  source: str | None = None) -> SensorLine:
    """The sensor path under which the cloud was scanned (module doc); ``xyz``: a sample of the campaign."""
    ground = ground_points(xyz, classification, params.cell)
    if len(ground) < 100:
        raise InputError("too few ground points to estimate the sensor path: give --trajectory", source)
    lo = ground[:, :2].min(axis=0)
    ij = np.floor((ground[:, :2] - lo) / params.cell).astype(np.int64)
    density = np.zeros(ij.max(axis=0) + 1)
    np.add.at(density, (ij[:, 0], ij[:, 1]), 1.0)
    density = ndimage.gaussian_filter(density, params.smooth / params.cell)
    mask = density >= params.ridge_fraction * np.percentile(density[density > 0], 99)
    try:
        cells = _longest_branch(mask)
    except ValueError:
        raise InputError("no sensor path found in the cloud (no dense ground strip): give --trajectory",
                         source) from None
    xy = lo + (cells + 0.5) * params.cell
    xy = _resample(_smooth_line(_resample(xy, STEP), int(params.path_smooth / STEP / 2)), STEP)
    xy = _extend(xy, EXTEND)
    path = SensorLine(np.column_stack([xy, np.zeros(len(xy))]), np.arange(len(xy)) * STEP)
    for _ in range(2):
        path = _refine(path, ground, params)
    return _trim(path, ground, params)


def _extend(xy: np.ndarray, length: float) -> np.ndarray:
    """The line continued straight for ``length`` metres at both ends (the density strip stops short of them)."""
    n = max(int(length / STEP), 1)
    k = min(len(xy) - 1, 10)
    head = (xy[0] - xy[k]) / max(np.linalg.norm(xy[0] - xy[k]), 1e-12)
    tail = (xy[-1] - xy[-1 - k]) / max(np.linalg.norm(xy[-1] - xy[-1 - k]), 1e-12)
    steps = (np.arange(n, 0, -1) * STEP)[:, None]
    return np.concatenate([xy[0] + steps * head, xy, xy[-1] + steps[::-1] * tail])


def _trim(path: SensorLine, ground: np.ndarray, params: SensorParams) -> SensorLine:
    """The path cut to the stretch the ground near it covers (the extension beyond the scan's ends removed)."""
    s, c = path.project(ground[:, :2])
    near = s[np.abs(c) <= params.refine_window]
    if len(near) < 2:
        return path
    a, b = np.searchsorted(path.s, [np.percentile(near, 0.05), np.percentile(near, 99.95)])
    a, b = max(a - 1, 0), min(b + 1, len(path.s))
    return SensorLine(path.xyz[a:b], path.s[a:b] - path.s[a])


def _binned_median(s: np.ndarray, values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Median of ``values`` per bin of ``s`` (NaN for an empty bin)."""
    b = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, len(edges) - 2)
    order = np.lexsort((values, b))
    b, v = b[order], values[order]
    starts = np.searchsorted(b, np.arange(len(edges) - 1))
    ends = np.searchsorted(b, np.arange(len(edges) - 1), side="right")
    out = np.full(len(edges) - 1, np.nan)
    has = ends > starts
    mid = (starts[has] + ends[has] - 1) / 2.0
    out[has] = 0.5 * (v[np.floor(mid).astype(np.int64)] + v[np.ceil(mid).astype(np.int64)])
    return out


def _fill(values: np.ndarray) -> np.ndarray:
    ok = np.isfinite(values)
    if not ok.any():
        return np.zeros_like(values)
    return np.interp(np.arange(len(values)), np.flatnonzero(ok), values[ok])


def _refine(path: SensorLine, ground: np.ndarray, params: SensorParams) -> SensorLine:
    """The path moved across to the median offset of the nearby ground, every 2 m of track; z on the ground."""
    s, c = path.project(ground[:, :2])
    near = np.abs(c) <= params.refine_window
    edges = np.arange(path.s[0], path.s[-1] + 2.0, 2.0)
    shift = _fill(_binned_median(s[near], c[near], edges))
    centre = np.abs(c) <= 1.0
    height = _fill(_binned_median(s[centre], ground[centre, 2], edges))
    mids = 0.5 * (edges[:-1] + edges[1:])
    tangent = np.gradient(path.xyz[:, :2], axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    left = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    xy = path.xyz[:, :2] + left * np.interp(path.s, mids, shift)[:, None]
    xy = _resample(_smooth_line(xy, int(params.path_smooth / STEP / 2)), STEP)
    s_new = np.arange(len(xy)) * STEP
    z = np.interp(s_new * (path.s[-1] / max(s_new[-1], 1e-9)), mids, height) + params.sensor_height
    return SensorLine(np.column_stack([xy, z]), s_new)


def path_times(path: SensorLine, xy: np.ndarray) -> np.ndarray:
    """Each point's "time" on an estimated path without GPS time: the arc length its position projects to."""
    return path.project(xy)[0]


def path_trajectory(path: SensorLine, source: str | None = None) -> Trajectory:
    """The estimated path as a trajectory over arc length (:func:`path_times`)."""
    return Trajectory(time=path.s.copy(), xyz=path.xyz.copy(), source=source)


def timed_path(path: SensorLine, gps: np.ndarray, xy: np.ndarray, params: SensorParams,
               source: str | None = None) -> Trajectory:
    """The estimated path over GPS time: per ``time_bin`` the median arc length of the points scanned then."""
    s = path_times(path, xy)
    edges = np.arange(gps.min(), gps.max() + params.time_bin, params.time_bin)
    if len(edges) < 3:
        return path_trajectory(path, source)
    along = _binned_median(gps, s, edges)
    mids = 0.5 * (edges[:-1] + edges[1:])
    ok = np.isfinite(along)
    if ok.sum() < 2:
        raise InputError("too few points per GPS time bin to place the estimated path in time", source)
    t = np.concatenate([[edges[0] - 1.0], mids[ok], [edges[-1] + 1.0]])  # a second's margin: the sample's ends
    a = np.concatenate([[along[ok][0]], along[ok], [along[ok][-1]]])
    return Trajectory(time=t, xyz=path.at(a), source=source)


def widen_layers(facades: list, factor: float) -> list:
    """Façades (new from a campaign) with their layers' σ multiplied by ``factor`` (1: unchanged)."""
    if factor != 1.0:
        for f in facades:
            for layer in f.layers:
                layer.sigma *= factor
    return facades
