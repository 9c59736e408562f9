"""One campaign's points as the façade steps need them: file order, sensor positions from the trajectory (GPS
time), ground/building flags, the footprint join and a coarse xy index."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from lidarmap.core import Footprints, PointCloud, Trajectory
from lidarmap.errors import CRSError, InputError
from lidarmap.facade.params import FacadeParams
from lidarmap.facade.planes import check_points, join_footprints


@dataclasses.dataclass
class CampaignData:
    """One campaign prepared for façade work (:func:`prepare_campaign`): shared by all its façades.

    ``sensors`` holds the sensor position of every non-ground point's pulse (NaN for ground points); the indices
    fetch points around a façade fast; ``limits`` are the scanner's max range and elevation limits measured on the
    campaign; ``track`` samples the trajectory over the campaign's time span every ``reach_step`` metres.
    """

    xyz: np.ndarray
    sensors: np.ndarray
    ground: np.ndarray
    building: np.ndarray
    nonground_index: _XYIndex
    nonground_ids: np.ndarray
    limits: tuple[float, float, float]
    track: np.ndarray
    ground_index: _XYIndex | None = None
    ground_ids: np.ndarray | None = None
    source: str | None = None
    gps: np.ndarray | None = None  # GPS time of every point: orders the returns of one scan line (ray evidence)
    noise_factor: float = 1.0  # > 1: the campaign's Gaussians are widened in fusion (an estimated sensor path)


def campaign_track(trajectory: Trajectory, t_min: float, t_max: float, step: float) -> np.ndarray:
    """The trajectory over the campaign's time span, sampled every ``step`` metres (the reach test's positions)."""
    inside = (trajectory.time > t_min) & (trajectory.time < t_max)
    times = np.concatenate([[t_min], trajectory.time[inside], [t_max]])
    pos = trajectory.position_at(np.clip(times, trajectory.time[0], trajectory.time[-1]))
    seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return pos[:1]
    samples = np.interp(np.arange(0.0, cum[-1] + step, step), cum, times)
    track = trajectory.position_at(np.clip(samples, trajectory.time[0], trajectory.time[-1]))
    # a place passed twice (a clock counting two scanner heads one after the other) is tested once
    _, first = np.unique(np.round(track / (0.5 * step)).astype(np.int64), axis=0, return_index=True)
    return track[np.sort(first)]


def campaign_data(xyz: np.ndarray, gps: np.ndarray, ground: np.ndarray, building: np.ndarray,
                  trajectory: Trajectory, limits: tuple[float, float, float], track: np.ndarray, origin: np.ndarray,
                  params: FacadeParams, source: str | None = None) -> CampaignData:
    """:class:`CampaignData` over some of a campaign's points (all of them, or one building's context) with the
    campaign-wide ``limits``, ``track`` and index ``origin`` (:mod:`lidarmap.facade.observe.scan`)."""
    nonground = np.flatnonzero(~ground)
    sensors = np.full((len(xyz), 3), np.nan)
    sensors[nonground] = trajectory.position_at(gps[nonground])  # InputError when the trajectory misses them
    camp = CampaignData(xyz=xyz, sensors=sensors, ground=ground, building=building,
                        nonground_index=_XYIndex(xyz[nonground, :2], params.occlusion.index_bin, origin),
                        nonground_ids=nonground, limits=limits, track=track, source=source,
                        gps=np.asarray(gps, dtype=np.float64))
    ground_ids = np.flatnonzero(ground)
    if len(ground_ids):
        camp.ground_index, camp.ground_ids = _XYIndex(xyz[ground_ids, :2], params.occlusion.index_bin, origin), ground_ids
    return camp


def prepare_campaign(points: PointCloud, trajectory: Trajectory, params: FacadeParams, seed: int = 0,
                     timings: dict | None = None) -> CampaignData:
    """Ground/building masks, the sensor position of every non-ground point, spatial indices, scanner limits, for
    a whole campaign held in memory (the same rules as the streamed update, :mod:`lidarmap.facade.observe.scan`; ``seed``
    is unused: the reach limits come from a stride sample).

    Raises :class:`~lidarmap.errors.InputError` for an empty cloud, missing ``gps_time`` or GPS times the
    trajectory does not cover (``Trajectory.position_at``).
    """
    from lidarmap.facade.scan import CampaignScan, StatsPass

    clock = time.perf_counter()
    tm = timings if timings is not None else {}
    check_points(points.xyz, points.source)
    origin = points.xyz[:, :2].min(axis=0)
    scan = CampaignScan(origin, params, points.source)
    index = scan.add(points)
    classes = scan.classes()
    stats_pass = StatsPass(classes, scan, trajectory)
    classification = points.attrs.get("classification")
    gps = np.asarray(points.attrs["gps_time"], dtype=np.float64)
    stats_pass.add(points.xyz, gps, classification, index)
    stats = stats_pass.finish(params.occlusion.reach_quantile)
    ground, building = classes.masks(points.xyz, classification)
    camp = campaign_data(points.xyz, gps, ground, building, trajectory, stats.limits,
                         campaign_track(trajectory, *stats.t_span, params.occlusion.reach_step), origin, params, points.source)
    tm["prepare"] = tm.get("prepare", 0.0) + time.perf_counter() - clock
    return camp


def check_same_crs(points: PointCloud, footprints: Footprints) -> None:
    """Refuse footprints in another CRS than the points (CRSError naming the footprint file)."""
    if points.crs is not None and footprints.crs is not None:
        from lidarmap.io.crs import same_crs
        if not same_crs(points.crs, footprints.crs):
            raise CRSError(f"footprints are in {footprints.crs.name!r} but the points in {points.crs.name!r}; "
                           "reproject the footprints (Footprints.to_crs) first", footprints.source)


def join_campaign(camp: CampaignData, footprints: Footprints, params: FacadeParams) -> dict[int, np.ndarray]:
    """The campaign's building points joined to their nearest footprint (§2.2): {footprint index: point ids
    (indices into the campaign)} in footprint order, points farther than ``max_footprint_distance`` left out.

    Raises :class:`~lidarmap.errors.InputError` (naming the footprint file) when no building point lies within
    ``max_footprint_distance`` of any footprint.
    """
    xyz = camp.xyz
    cand = np.flatnonzero(camp.building)
    bidx, _ = join_footprints(xyz[cand, :2], footprints, params.join.max_footprint_distance, params.join.join_quantum)
    if not np.any(bidx >= 0):
        lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        raise no_join_error(len(cand), (lo[0], lo[1], hi[0], hi[1]), footprints, params)
    order = np.argsort(bidx, kind="stable")
    sorted_b = bidx[order]
    joined: dict[int, np.ndarray] = {}
    for b in np.unique(bidx[bidx >= 0]):
        lo, hi = np.searchsorted(sorted_b, [b, b + 1])
        joined[int(b)] = cand[order[lo:hi]]
    return joined


def no_join_error(n_building: int, points_bounds: tuple[float, float, float, float], footprints: Footprints,
                  params: FacadeParams) -> InputError:
    """The error for a campaign none of whose building points lies near a footprint (naming the footprint file)."""
    px0, py0, px1, py1 = points_bounds
    fx0, fy0, fx1, fy1 = footprints.bounds
    return InputError(
        f"none of the {n_building} building points lies within {params.join.max_footprint_distance:g} m of a "
        f"footprint (points bbox [{px0:.1f}, {py0:.1f}, {px1:.1f}, {py1:.1f}], footprints bbox "
        f"[{fx0:.1f}, {fy0:.1f}, {fx1:.1f}, {fy1:.1f}]): wrong footprints file or CRS?", footprints.source)


class _XYIndex:
    """Points binned on an xy grid (sorted by bin) for fast box queries.

    With a fixed ``origin`` (the campaign's) the bins, and so which points a box query returns and in what order,
    are the same for any part of the campaign that holds the queried bins: a building's context answers like the
    whole campaign.
    """

    def __init__(self, xy: np.ndarray, bin_size: float, origin: np.ndarray | None = None):
        self.bin = float(bin_size)
        if origin is not None:
            self.lo = np.asarray(origin, dtype=np.float64)[:2]
        else:
            self.lo = xy.min(axis=0) if len(xy) else np.zeros(2)
        ij = np.floor((xy - self.lo) / self.bin).astype(np.int64)
        self.shape = (ij.max(axis=0) + 1) if len(xy) else np.array([1, 1])
        keys = ij[:, 0] * self.shape[1] + ij[:, 1]
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]

    def query_box(self, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
        i0, j0 = np.floor((np.array([x0, y0]) - self.lo) / self.bin).astype(np.int64)
        i1, j1 = np.floor((np.array([x1, y1]) - self.lo) / self.bin).astype(np.int64)
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, self.shape[0] - 1), min(j1, self.shape[1] - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, dtype=np.int64)
        rows = np.arange(i0, i1 + 1)
        lo = np.searchsorted(self.keys, rows * self.shape[1] + j0, side="left")
        hi = np.searchsorted(self.keys, rows * self.shape[1] + j1, side="right")
        parts = [self.order[a:b] for a, b in zip(lo, hi) if b > a]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
