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
  ground height there plus ``sensor_height``. With GPS time the path is parameterised by time
  (:func:`timed_path`): per ``time_bin`` the median arc length of the points scanned then. Without it, a file in
  scan order gets a pulse clock (:class:`PulseClock`): the profile plane's yaw from the scan-line stripes on the
  ground (:func:`profile_slopes`), two crossed heads told apart (:func:`scan_heads`), each return's sensor where
  its yawed scan line meets the path, and pulses counted per head from the angles between consecutive returns.
  A file out of scan order falls back to each point's sensor straight across the track (:func:`path_times`).

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

        sensor_height (2.5): height of the scanner above the road when the path is estimated and its height is not
            measured (typical MLS vans: 2-3 m; the simulator's default is 2.5).
        measure_height (True): measure the scanner's height from the width of the ground strip under it
            (:func:`strip_height`); sensor_height where that fails.
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
        stripe_reach (6.0): without GPS time, the scan lines' direction on the ground (the profile plane's yaw) is
            measured on the ground points within this distance across the path (farther, profiles lie farther
            apart than the pulses of one profile).
        second_head (0.3): a second stripe direction at least this share of the first's peak means two crossed
            scanner heads.
    """

    section = "sensors"
    constraints: ClassVar[dict[str, str]] = {
        "sensor_height": ">= 0", "cell": "> 0", "smooth": "> 0", "ridge_fraction": "(0, 1]",
        "refine_window": "> 0", "path_smooth": ">= 0", "time_bin": "> 0", "origin_tolerance": ">= 0",
        "noise_factor": ">= 1", "sample_points": ">= 1000", "stripe_reach": "> 0.5", "second_head": "(0, 1]",
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
    stripe_reach: float = 6.0
    second_head: float = 0.3
    measure_height: bool = True

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


# ----------------------------------------------------------------------------------------------------------------------
# Yawed and crossed profilers without GPS time: the scan-line stripes on the ground, a pulse clock from file order

#: Pseudo-seconds per pulse of the clock of a path estimated without GPS time (a 100 kHz profiler's pulse period):
#: the clock only orders the pulses and counts the missed ones; its scale sets the ray evidence's travel window.
PULSE_SECONDS = 1e-5
END_MARGIN = 8.0  # m at either end of a path where its direction is not trusted for the stripes' yaw
MAX_YAW = 60.0  # degrees: steeper stripes are the spacing between profiles, not a profile
NADIR = 1.5  # m across the path within which the two heads' ground lines meet: links there are not trusted
NADIR_REF = 1.0  # m across the path: a return this close to the nadir has its sensor nearly straight across
FILE_BLOCK = 512  # consecutive returns of the file over which the sensor's place is taken as one (about a profile)
LAGS = 40  # a return's predecessor on its own head's scan line is among the previous LAGS returns of the file


def profile_slopes(path: SensorLine, ground: np.ndarray, params: SensorParams) -> np.ndarray:
    """tan(yaw) of each scanner head's profile plane in the path's frame (along = tan(yaw) x across on a scan
    line): the ground points' nearest neighbours lie on their own scan line (pulses a few cm apart, profiles
    ``speed / rate`` apart), so the directions to them, folded to (-90°, 90°], peak at each head's yaw. One slope,
    or two when a second peak at least ``second_head`` x the first lies more than 15° from it (crossed heads)."""
    s, c = path.project(ground[:, :2])
    near = (np.abs(c) > 0.5) & (np.abs(c) < params.stripe_reach)
    if path.s[-1] > 4 * END_MARGIN:  # the path's ends are continued straight, their frame bent: not measured there
        near &= (s > path.s[0] + END_MARGIN) & (s < path.s[-1] - END_MARGIN)
    pts = np.column_stack([s[near], c[near]])
    if len(pts) < 100:
        return np.zeros(1)
    _, k = cKDTree(pts).query(pts, k=[2, 3], workers=1)
    d = pts[k.ravel()] - np.repeat(pts, 2, axis=0)
    angle = (np.degrees(np.arctan2(d[:, 0], d[:, 1])) + 90.0) % 180.0 - 90.0
    angle = angle[np.abs(angle) < MAX_YAW]
    if len(angle) < 50:
        return np.zeros(1)
    hist = np.histogram(angle, bins=int(2 * MAX_YAW), range=(-MAX_YAW, MAX_YAW))[0].astype(np.float64)
    hist = np.convolve(hist, [1.0, 2.0, 1.0], mode="same")
    centres = np.arange(-MAX_YAW, MAX_YAW) + 0.5
    first = int(np.argmax(hist))
    far = np.abs(centres - centres[first]) > 15.0
    peaks = [first]
    if far.any():
        second = int(np.flatnonzero(far)[np.argmax(hist[far])])
        if hist[second] >= params.second_head * hist[first]:
            peaks.append(second)
    yaws = [float(np.mean(angle[np.abs(angle - centres[p]) <= 3.0])) for p in sorted(peaks)]
    return np.tan(np.radians(yaws))


def scan_heads(xyz: np.ndarray, s: np.ndarray, c: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """Which head (index into ``slopes``) scanned each return of a file that interleaves two crossed profilers.

    Every return is linked to the nearest of the previous ``LAGS`` returns of the file when it lies within 0.1 rad
    of it (seen from the path): the next pulse of the same head's scan line. A link that runs over the ground
    (more horizontal than vertical) votes for the head whose stripe direction it follows (within 8°); each chain of
    links takes its majority. Chains without a vote (a wall seen without its foot) stay -1."""
    n = len(xyz)
    heads = np.full(n, -1, dtype=np.int64)
    if len(slopes) < 2 or n < 2:
        return np.zeros(n, dtype=np.int64) if len(slopes) < 2 else heads
    best = np.full(n, np.inf)
    pred = np.full(n, -1, dtype=np.int64)
    r = np.maximum(np.hypot(c, xyz[:, 2] - np.median(xyz[:, 2])), 1.0)
    active = np.arange(n)
    for lag in range(1, LAGS + 1):
        if lag == 5:  # most returns have found the next pulse of their line by now: only the others look farther
            active = active[best[active] > 0.05]
        ids = active[active >= lag]
        dist = np.linalg.norm(xyz[ids] - xyz[ids - lag], axis=1) / r[ids]
        better = dist < best[ids]
        best[ids[better]], pred[ids[better]] = dist[better], ids[better] - lag
    linked = np.flatnonzero(best < 0.2)
    a, b = linked, pred[linked]
    ds, dc, dz = s[a] - s[b], c[a] - c[b], xyz[a, 2] - xyz[b, 2]
    flat = np.hypot(ds, dc) > 2.0 * np.abs(dz)
    angle = (np.degrees(np.arctan2(ds, dc)) + 90.0) % 180.0 - 90.0
    yaws = np.degrees(np.arctan(slopes))
    diff = np.abs((angle[:, None] - yaws[None, :] + 90.0) % 180.0 - 90.0)
    vote = np.where(flat & (diff.min(axis=1) <= 8.0), np.argmin(diff, axis=1), -1)
    # a flat link along neither stripe, or one near the nadir (where both heads' lines meet), may join two heads
    keep = (~flat | (vote >= 0)) & (np.minimum(np.abs(c[a]), np.abs(c[b])) > NADIR)
    graph = coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n))
    _, chain = connected_components(graph, directed=False)
    voted = vote >= 0
    tally = np.zeros((chain.max() + 1, len(slopes)))
    np.add.at(tally, (chain[a[voted]], vote[voted]), 1.0)
    has = tally.sum(axis=1) > 0
    label = np.where(has, np.argmax(tally, axis=1), -1)
    heads = label[chain]
    # a chain without a vote (a wall whose foot the scan line did not reach): the two heads fire together, so the
    # file's returns next to its returns that belong to another, labelled chain are the other head's
    for other in (np.arange(n - 1), np.arange(1, n)):
        mine = other + 1 if other[0] == 0 else other - 1
        ok = (heads[mine] < 0) & (heads[other] >= 0) & (chain[mine] != chain[other])
        np.add.at(tally, (chain[mine[ok]], 1 - heads[other[ok]]), 1.0)
    label = np.where((tally.sum(axis=1) > 0) & (tally.max(axis=1) > tally.min(axis=1)), np.argmax(tally, axis=1), -1)
    return _by_file_time(s, c, slopes, label[chain])


def _by_file_time(s: np.ndarray, c: np.ndarray, slopes: np.ndarray, heads: np.ndarray) -> np.ndarray:
    """Heads checked against the sensor's place at each return's moment: the file is in scan order, so the returns
    near the nadir (within ``NADIR_REF`` across, where both heads' lines meet) of each block of ``FILE_BLOCK``
    returns give the sensor's arc length then (their median); a return whose two head hypotheses put its sensor
    more than 1 m apart takes the head whose sensor lies nearer to it (decisive for walls: 2 c tan(yaw) apart),
    the others keep their chain's head, or without one take the nearer too (near the nadir either is right)."""
    n = len(s)
    nadir = np.flatnonzero(np.abs(c) < NADIR_REF)
    if len(nadir) < 10:
        return heads
    block = nadir // FILE_BLOCK
    order = np.lexsort((s[nadir], block))
    blocks, start, count = np.unique(block[order], return_index=True, return_counts=True)
    sorted_s = s[nadir][order]
    median = 0.5 * (sorted_s[start + (count - 1) // 2] + sorted_s[start + count // 2])
    reference = np.interp(np.arange(n), (blocks + 0.5) * FILE_BLOCK, median)
    miss = np.abs(s[:, None] - slopes[None, :] * c[:, None] - reference[:, None])
    nearest = np.argmin(miss, axis=1)
    decisive = np.abs(miss[:, 0] - miss[:, 1]) > 1.0
    return np.where(decisive | (heads < 0), nearest, heads)


MAX_STEP_DEG = 2.0  # a median angle between consecutive returns above this is no profiler's step
HEAD_OFFSET = 1e4  # pseudo-seconds between the clocks of two heads (each head's pulses counted on its own)


@dataclasses.dataclass
class PulseClock:
    """The clock of a campaign whose file holds its returns in scan order but no GPS time (docs/mls.md).

    Each return's head is found (:func:`scan_heads`; -1: not found, clock ``len(slopes)``, taken as unyawed); its
    sensor is the path point ``s - slope x c`` (its scan line meets the path there: the profile plane is yawed by
    the head's slope); consecutive returns of one head, ``angle`` apart as seen from that sensor, are
    ``round(angle / step)`` pulses apart. Each head counts its own pulses, ``PULSE_SECONDS`` per pulse, from
    ``HEAD_OFFSET`` x its number: the ray evidence orders each head's pulses and counts the missed ones as with GPS
    times. ``step`` is the profiler's angular step, the median angle between consecutive returns of the first
    chunk (adjacent pulses); ``adjacent_share`` the share of them 0.5-1.5 steps apart (0 when the step exceeds
    ``MAX_STEP_DEG``: the file is not in scan order). Call it on the chunks in file order (``first`` 0 starts over)."""

    path: SensorLine
    slopes: np.ndarray
    step: float | None = None
    adjacent_share: float = 1.0
    _carry: dict = dataclasses.field(default_factory=dict)
    _heads: dict = dataclasses.field(default_factory=dict)

    @property
    def heads(self) -> int:
        return len(self.slopes) + 1  # the heads, and the returns whose head was not found

    def __call__(self, first: int, chunk) -> np.ndarray:
        return self.times(first, chunk.xyz)[0]

    def times(self, first: int, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(clock, head, sensor arc length) of a chunk of returns in file order."""
        if first == 0:
            self._carry = {}
        s, c = self.path.project(xyz[:, :2])
        key = (first, len(xyz))
        if key not in self._heads:  # every pass over the file finds the same heads: found once (1 byte a return)
            self._heads[key] = scan_heads(xyz, s, c, self.slopes).astype(np.int8)
        head = self._heads[key].astype(np.int64)
        slope = np.append(self.slopes, 0.0)[head]
        s_sensor = np.clip(s - slope * c, self.path.s[0], self.path.s[-1])
        origin = self.path.at(s_sensor)
        if self.step is None:
            self._measure_step(xyz, origin, head)
        clock = np.empty(len(xyz))
        for h in range(self.heads):
            ids = np.flatnonzero(np.where(head < 0, self.heads - 1, head) == h)
            if len(ids):
                clock[ids] = self._count(h, xyz[ids], origin[ids])
        return clock, head, s_sensor

    def _count(self, h: int, xyz: np.ndarray, origin: np.ndarray) -> np.ndarray:
        last_xyz, last_clock = self._carry.get(h, (xyz[0], h * HEAD_OFFSET - PULSE_SECONDS))
        prev = np.concatenate([last_xyz[None], xyz[:-1]])
        pulses = np.maximum(np.rint(_angles(xyz, prev, origin) / self.step), 1.0)
        clock = last_clock + np.cumsum(pulses) * PULSE_SECONDS
        self._carry[h] = (xyz[-1], clock[-1])
        return clock

    def _measure_step(self, xyz: np.ndarray, origin: np.ndarray, head: np.ndarray) -> None:
        angles = []
        for h in range(len(self.slopes)):
            ids = np.flatnonzero(head == h)
            if len(ids) > 1:
                angles.append(_angles(xyz[ids[1:]], xyz[ids[:-1]], origin[ids[1:]]))
        a = np.concatenate(angles) if angles else np.zeros(0)
        a = a[a > 0]
        self.step = float(np.median(a)) if len(a) else np.radians(0.5)
        self.adjacent_share = float(np.mean((a > 0.5 * self.step) & (a < 1.5 * self.step))) if len(a) else 0.0
        if self.step > np.radians(MAX_STEP_DEG):  # no profiler steps that far: the file is not in scan order
            self.adjacent_share = 0.0

    def trajectory(self, chunks, source: str | None = None) -> Trajectory:
        """The sensor path over this clock: per head, per 0.01 pseudo-s of its clock (about a profile), the median
        sensor arc length of its returns; between two heads' clocks the path is run back to its start (the
        reach test samples the trajectory in between)."""
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        first = 0
        for chunk in chunks:
            parts.append(self.times(first, chunk.xyz))
            first += len(chunk)
        clock, head, s = (np.concatenate([p[k] for p in parts]) for k in range(3))
        head = np.where(head < 0, self.heads - 1, head)
        times, arcs = [], []
        for h in range(self.heads):
            ids = np.flatnonzero(head == h)
            if len(ids) < 2:
                continue
            t = clock[ids]
            edges = np.arange(t.min(), t.max() + 0.01, 0.01)
            if len(edges) < 2:
                edges = np.array([t.min(), t.max() + PULSE_SECONDS])
            along = _binned_median(t, s[ids], edges)
            ok = np.isfinite(along)
            mids = 0.5 * (edges[:-1] + edges[1:])[ok]
            knots_t = np.concatenate([[t.min() - 1.0], mids, [t.max() + 1.0]])
            knots_s = np.concatenate([[along[ok][0]], along[ok], [along[ok][-1]]])
            if times:  # back along the path from the previous head's end to this head's start
                t0, t1 = times[-1][-1], knots_t[0]
                back = np.linspace(arcs[-1][-1], knots_s[0], 50)[1:-1]
                times.append(np.linspace(t0, t1, 50)[1:-1])
                arcs.append(back)
            times.append(knots_t)
            arcs.append(knots_s)
        if not times:  # too few returns to count (adjacent_share is then 0: the caller does not use this clock)
            return path_trajectory(self.path, source)
        t, a = np.concatenate(times), np.concatenate(arcs)
        keep = np.concatenate([[True], np.diff(t) > 0])
        return Trajectory(time=t[keep], xyz=self.path.at(a[keep]), source=source)


def _angles(xyz: np.ndarray, prev: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Angle (radians) between the rays from ``origin`` to ``xyz`` and to ``prev``."""
    u, v = xyz - origin, prev - origin
    cos = np.einsum("ij,ij->i", u, v) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))


HEIGHT_RANGE = (1.0, 6.0)  # m: a measured scanner height outside this is not trusted (sensor_height instead)
HEIGHT_WINDOW = 10.0  # m of path per measurement of the ground strip's width
HEIGHT_REACH = 8.0  # m across the path over which the strip is profiled


def strip_height(path: SensorLine, ground: np.ndarray, slopes: np.ndarray) -> float | None:
    """The scanner's height above the ground from the ground strip under it: a profiler at height h puts
    h cos(yaw) / (h² cos²(yaw) + c²) ground points per metre at cross-track distance c (pulses evenly spaced in
    angle; yawed, its line on the ground is 1 / cos(yaw) longer), so the strip's density falls to half its peak at
    c = ±h cos(yaw). Per ``HEIGHT_WINDOW`` of path the density across (0.1 m bins, smoothed over 0.15 m) gives the
    larger of the two half widths at half maximum (a parked car shadows one side early, never widens it); their
    median / cos(yaw) is h. ``None`` when no window has a clear peak or h falls outside ``HEIGHT_RANGE``."""
    s, c = path.project(ground[:, :2])
    keep = np.abs(c) < HEIGHT_REACH
    if path.s[-1] > 4 * END_MARGIN:
        keep &= (s > path.s[0] + END_MARGIN) & (s < path.s[-1] - END_MARGIN)
    if keep.sum() < 1000:
        return None
    s, c = s[keep], c[keep]
    bin_ = 0.1
    bins = int(2 * HEIGHT_REACH / bin_)
    window = np.floor((s - s.min()) / HEIGHT_WINDOW).astype(np.int64)
    density = np.zeros((window.max() + 1, bins))
    np.add.at(density, (window, np.clip(((c + HEIGHT_REACH) / bin_).astype(np.int64), 0, bins - 1)), 1.0)
    density = ndimage.gaussian_filter1d(density, 1.5, axis=1)
    halves = [w for w in (_half_width(row, bin_) for row in density) if w is not None]
    if not halves:
        return None
    height = float(np.median(halves)) / float(np.mean(np.cos(np.arctan(slopes))))
    return height if HEIGHT_RANGE[0] <= height <= HEIGHT_RANGE[1] else None


def _half_width(row: np.ndarray, bin_: float) -> float | None:
    """The larger distance from the peak of ``row`` to where it falls to half the peak (linear between bins)."""
    k = int(np.argmax(row))
    if row[k] < 20:
        return None
    half = 0.5 * row[k]
    left, right = np.flatnonzero(row[:k] < half), np.flatnonzero(row[k:] < half)
    if not len(left) or not len(right):
        return None
    a, b = left[-1], k + right[0]
    left_width = (k - a) - (half - row[a]) / max(row[a + 1] - row[a], 1e-9)
    right_width = (b - 1 - k) + (row[b - 1] - half) / max(row[b - 1] - row[b], 1e-9)
    return max(left_width, right_width) * bin_


def with_height(path: SensorLine, ground: np.ndarray, slopes: np.ndarray, params: SensorParams) -> SensorLine:
    """The path raised to the measured scanner height (:func:`strip_height`) when ``measure_height``."""
    height = strip_height(path, ground, slopes) if params.measure_height else None
    if height is None:
        return path
    xyz = path.xyz.copy()
    xyz[:, 2] += height - params.sensor_height
    return SensorLine(xyz, path.s)
