"""A mobile campaign from any point file with its sensor positions from whatever the data has (docs/mls.md).

In this order: a trajectory file (the points need GPS time); per-point origins (``x_origin, y_origin, z_origin``);
nothing, then the sensor path estimated from the cloud (:mod:`lidarmap.facade.sensors`), placed in time by the
GPS time when the points have it. The result is what :func:`lidarmap.map.update.fuse_campaign` takes: a
:class:`~lidarmap.map.update.CampaignSource` whose chunks carry a ``gps_time`` on the clock of a
:class:`~lidarmap.core.Trajectory` (the point number for origins, a pulse count per scanner head for a path
estimated without GPS time from a file in scan order, else the arc length), so that ``trajectory.position_at(gps_time)`` is every point's sensor.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lidarmap.core import Footprints, PointCloud, Trajectory
from lidarmap.errors import InputError
from lidarmap.facade.sensors import (
    PulseClock,
    SensorParams,
    estimate_path,
    ground_points,
    knots_trajectory,
    origin_knots,
    path_times,
    path_trajectory,
    profile_slopes,
    timed_path,
    with_height,
)
from lidarmap.io.ply import ORIGIN_FIELDS
from lidarmap.io.points import (
    PointsHeader,
    iter_points,
    measure_bounds,
    read_points_header,
)
from lidarmap.io.trajectory import read_trajectory
from lidarmap.map.model import DERIVED
from lidarmap.map.update import CampaignSource

log = logging.getLogger(__name__)

#: A file whose consecutive returns (of one head) are adjacent pulses this often is in scan order: its order is
#: the pulse order when it has no GPS time (:class:`~lidarmap.facade.sensors.PulseClock`).
MIN_ADJACENT = 0.5

#: Consecutive points kept together in the sample the path is estimated from.
SAMPLE_BLOCK = 4096

#: How a campaign's sensor positions were obtained (stored in the campaign's summary as ``sensors``).
MODES = ("trajectory", "origins", "estimated from the cloud and GPS time", "estimated from the cloud")


@dataclasses.dataclass
class MobileCampaign:
    """A mobile campaign ready to fuse: its points, its trajectory (on their ``gps_time`` clock), how the sensor
    positions were found and the factor on the campaign's noise in fusion (> 1 for an estimated path)."""

    source: CampaignSource
    trajectory: Trajectory
    mode: str
    noise_factor: float
    pulse_times: bool = True  # False: gps_time is only the trajectory's clock (point number, arc length)

    @property
    def estimated(self) -> bool:
        return self.mode.startswith("estimated")


def _stream(header: PointsHeader, chunk_points: int, crs: Any, columns: str | None) -> Iterator[PointCloud]:
    return iter_points(header.path, chunk_points, crs, columns)


def _bounds(header: PointsHeader, chunk_points: int, crs: Any, columns: str | None) -> tuple:
    if header.lo is not None and header.n_points is not None:
        return header.lo, header.hi, header.n_points
    lo, hi, n = measure_bounds(header.path, chunk_points, crs, columns)
    if n == 0:
        raise InputError("the point cloud is empty", header.path)
    return lo, hi, n


def _with_clock(chunks: Iterator[PointCloud], clock) -> Iterator[PointCloud]:
    """The chunks with ``gps_time`` replaced by ``clock(first point number, chunk)``."""
    first = 0
    for chunk in chunks:
        chunk.attrs["gps_time"] = clock(first, chunk)
        first += len(chunk)
        yield chunk


def _origins_trajectory(header: PointsHeader, chunk_points: int, crs: Any, columns: str | None,
                        params: SensorParams) -> Trajectory:
    """Knots from the origins: over GPS time when the points have it (one knot per pulse time, in time order),
    else over the point number."""
    times, positions, first = [], [], 0
    for chunk in _stream(header, chunk_points, crs, columns):
        origins = np.column_stack([chunk.attrs[f] for f in ORIGIN_FIELDS]).astype(np.float64)
        if not np.all(np.isfinite(origins)):
            raise InputError("NaN or infinite sensor origins (x_origin, y_origin, z_origin)", header.path)
        if header.has_gps_time:
            gps = np.asarray(chunk.attrs["gps_time"], dtype=np.float64)
            gps, keep = np.unique(gps, return_index=True)  # sorted; the returns of one pulse share its origin
            t, xyz = origin_knots(0, origins[keep], params.origin_tolerance, gps)
            times.append(t)
            positions.append(xyz)
            continue
        t, xyz = origin_knots(first, origins, params.origin_tolerance)
        times.append(t)
        positions.append(xyz)
        first += len(chunk)
    if header.has_gps_time:  # chunks need not be in time order
        t, xyz = np.concatenate(times), np.concatenate(positions)
        order = np.argsort(t, kind="stable")
        times, positions = [t[order]], [xyz[order]]
    return knots_trajectory(times, positions, str(header.path))


def _sample(header: PointsHeader, n_points: int, chunk_points: int, crs: Any, columns: str | None,
            params: SensorParams) -> dict[str, np.ndarray | None]:
    """A sample (at most about ``sample_points``) of xyz, classification and GPS time: every k-th block of
    ``SAMPLE_BLOCK`` consecutive points, so that the scan lines in it keep every return (their stripes on the
    ground give the profile's yaw: :func:`~lidarmap.facade.sensors.profile_slopes`)."""
    stride = max(1, -(-n_points // params.sample_points))
    parts: dict[str, list] = {"xyz": [], "classification": [], "gps_time": []}
    first = 0
    for chunk in _stream(header, chunk_points, crs, columns):
        pick = np.flatnonzero(((first + np.arange(len(chunk))) // SAMPLE_BLOCK) % stride == 0)
        parts["xyz"].append(chunk.xyz[pick])
        for name in ("classification", "gps_time"):
            if name in chunk.attrs:
                parts[name].append(chunk.attrs[name][pick])
        first += len(chunk)
    return {name: (np.concatenate(values) if values and len(values) == len(parts["xyz"]) else None)
            for name, values in parts.items()}


def mobile_campaign(points: Path, trajectory: Path | None, crs: Any, columns: str | None, chunk_points: int,
                    params: SensorParams | None = None, trajectory_gaps: tuple[float, float] | None = None
                    ) -> MobileCampaign:
    """The campaign in ``points`` with its sensor positions (module doc); errors name the file.
    ``trajectory_gaps``: (warn, refuse) seconds of a hole in the trajectory file (:func:`read_trajectory`)."""
    params = params or SensorParams()
    header = read_points_header(points, crs, columns)
    if header.n_points == 0:
        raise InputError("the point cloud is empty", points)
    lo, hi, n = _bounds(header, chunk_points, crs, columns)

    def source(clock=None) -> CampaignSource:
        def chunks() -> Iterator[PointCloud]:
            stream = _stream(header, chunk_points, crs, columns)
            return stream if clock is None else _with_clock(stream, clock)
        return CampaignSource(chunks, lo, hi, n, header.crs, str(points))

    if trajectory is not None:
        if not header.has_gps_time:
            raise InputError("the points have no GPS time: a trajectory file gives sensor positions only by GPS "
                             "time (leave --trajectory out to use the points' origins or an estimated path)", points)
        return MobileCampaign(source(), read_trajectory(trajectory, *(trajectory_gaps or ())), MODES[0], 1.0)
    if header.has_origins:
        track = _origins_trajectory(header, chunk_points, crs, columns, params)
        if header.has_gps_time:
            return MobileCampaign(source(), track, MODES[1], 1.0)
        return MobileCampaign(source(lambda first, chunk: first + np.arange(len(chunk), dtype=np.float64)),
                              track, MODES[1], 1.0, pulse_times=False)
    sample = _sample(header, n, chunk_points, crs, columns, params)
    path = estimate_path(sample["xyz"], sample["classification"], params, str(points))
    ground = ground_points(sample["xyz"], sample["classification"], params.cell)
    slopes = profile_slopes(path, ground, params)
    path = with_height(path, ground, slopes, params)
    log.info("%s: sensor path estimated from the cloud (%.0f m)", points, path.s[-1])
    if sample["gps_time"] is not None:
        track = timed_path(path, sample["gps_time"], sample["xyz"][:, :2], params, str(points))
        return MobileCampaign(source(), track, MODES[2], params.noise_factor)
    clock = PulseClock(path, slopes)
    track = clock.trajectory(_stream(header, chunk_points, crs, columns), str(points))
    if clock.adjacent_share >= MIN_ADJACENT:
        log.info("%s: no GPS time: pulses counted in file order, %d head(s) yawed %s deg, %.2f deg per pulse",
                 points, len(clock.slopes), np.round(np.degrees(np.arctan(clock.slopes)), 1),
                 np.degrees(clock.step))
        return MobileCampaign(source(clock), track, MODES[3], params.noise_factor)
    log.warning("%s: no trajectory, origins or GPS time, and the file is not in scan order: every point's sensor "
                "is taken across the track from it (a yawed or crossed profiler breaks this; docs/mls.md)", points)
    return MobileCampaign(source(lambda first, chunk: path_times(path, chunk.xyz[:, :2])),
                          path_trajectory(path, str(points)), MODES[3], params.noise_factor, pulse_times=False)


# ----------------------------------------------------------------------------------------------------------------------
# Without footprints: buildings found from the points, kept by the map


def _track_positions(trajectory: Trajectory, most: int = 200_000) -> np.ndarray:
    step = max(1, len(trajectory.xyz) // most)
    return trajectory.xyz[::step]


def discover_campaign(mobile: MobileCampaign, fparams: Any, params: Any = None, seed: int = 0) -> list:
    """The buildings of a campaign found from its points alone (:func:`lidarmap.facade.discover.discover_buildings`):
    one pass for the campaign's classes (the façade steps' rule), one for the wall cells."""
    from lidarmap.facade.discover import DiscoverParams, WallCells, discover_buildings
    from lidarmap.facade.scan import CampaignScan

    params = params or DiscoverParams()
    source = mobile.source
    scan = CampaignScan(source.lo, fparams, source.source)
    for chunk in source.chunks():
        scan.add(chunk)
    classes = scan.classes()
    cells = WallCells(source.lo, params.cell)
    for chunk in source.chunks():
        _, building = classes.masks(chunk.xyz, chunk.attrs.get("classification"))
        cells.add(chunk.xyz[building])
    return discover_buildings(cells, _track_positions(mobile.trajectory), params, seed)


def merge_discovered(stored: Footprints | None, found: list, crs: Any,
                     source: str | None) -> tuple[Footprints, dict[str, Any]]:
    """The footprints a campaign without footprint file runs with: the map's buildings (a derived footprint grown by
    the campaign's view of it) and the buildings found that overlap none of them (new, with their own ids).
    Returns them and {building id: grown derived footprint} for the map to store."""
    from shapely import STRtree

    ids = list(stored.ids) if stored is not None else []
    polygons = list(stored.polygons) if stored is not None else []
    props = [dict(p) for p in stored.properties] if stored is not None else []
    tree = STRtree(np.array(polygons, dtype=object)) if polygons else None
    grown: dict[str, Any] = {}
    for b in found:
        hits = [] if tree is None else [int(k) for k in tree.query(b.footprint, predicate="intersects")]
        overlap = [(polygons[k].intersection(b.footprint).area, k) for k in hits]
        overlap = [(a, k) for a, k in overlap if a > 0]
        if not overlap:
            ids.append(b.building_id)
            polygons.append(b.footprint)
            props.append({DERIVED: True})
            continue
        _, k = max(overlap)
        if props[k].get(DERIVED):  # the campaign saw more of a building found before: its footprint grows
            polygons[k] = grown[ids[k]] = polygons[k].union(b.footprint).buffer(0)
    array = np.empty(len(polygons), dtype=object)
    array[:] = polygons
    return Footprints(ids=ids, polygons=array, properties=props, crs=crs, source=source), grown


def join_given_footprints(given: Footprints, stored: Footprints | None) -> tuple[Footprints, dict[str, tuple]]:
    """Footprints given for a map that holds buildings found from the points: each such building takes the given
    footprint overlapping it most (its id kept; the footprint's own id stored as ``footprint_id``). Returns the
    footprints to run with and {building id: (footprint polygon, properties)} for the map to store."""
    if stored is None:
        return given, {}
    derived = [k for k, p in enumerate(stored.properties) if p.get(DERIVED)]
    ids = list(given.ids)
    props = [dict(p) for p in given.properties]
    joined: dict[str, tuple] = {}
    taken: set[int] = set()
    for k in derived:
        overlap = [(stored.polygons[k].intersection(poly).area, j) for j, poly in enumerate(given.polygons)
                   if j not in taken]
        overlap = [(a, j) for a, j in overlap if a > 0]
        if not overlap:
            continue
        _, j = max(overlap)
        taken.add(j)
        props[j] = {**props[j], "footprint_id": ids[j]}
        ids[j] = stored.ids[k]
        joined[ids[j]] = (given.polygons[j], props[j])
    return Footprints(ids=ids, polygons=given.polygons, properties=props, crs=given.crs, source=given.source), joined
