"""One mobile campaign fused into the façade map building by building, streamed with bounded memory (docs/map.md).

``lidarmap map update --points`` and the in-memory entry points (:func:`lidarmap.map.refine.refine_map`,
:func:`lidarmap.map.update.extract_buildings`) all run :func:`fuse_campaign`:

1. **Pass 1** reads the campaign in chunks (:func:`lidarmap.io.las.iter_las`, file order) and spools every point
   (xyz, GPS time, class, its number in the file) into a :class:`~lidarmap.io.spool.ColumnSpool` keyed by the
   ``cell`` x ``cell`` xy cell it falls in (on disk, in a temporary folder the caller gives); it gathers the classes
   present and the height rule's lowest cells (:class:`~lidarmap.facade.observe.observe.scan.CampaignScan`).
2. **Pass 2** reads the spool once, cell by cell: the non-ground GPS time span (checked against the trajectory),
   counts, and a stride sample for the scanner's reach limits (:class:`~lidarmap.facade.observe.observe.scan.StatsPass`).
3. **Per building** (every footprint with spooled points near it): its *context* is the points of the box around
   its footprint and stored façades grown by everything façade work may look at (:func:`context_box`). With the
   footprints that could be nearer to some of its points and its reach track box it makes a :class:`BuildingJob`.
   Neighbouring buildings (footprint centres in one ``group_size`` cell) share one picklable :class:`GroupJob`: the
   union of their contexts, the reach limits and track. :func:`group_task` prepares the shared context once, then
   :func:`building_task` turns each member into the new :class:`~lidarmap.map.model.Building`: façade extraction for a
   building the map does not hold, refinement (:func:`lidarmap.map.refine.refine_building`) for one it holds.
4. Jobs run through :func:`lidarmap.executor.map_tasks` (this process, a LocalCluster or a remote scheduler);
   this process collects the buildings, and the caller commits them (one transaction).

**The same map whatever the chunking, workers or scheduler.** A building's result is a function of its job, and its
job of the campaign, the footprints and the stored building only: every lattice (index bins, ground cells, join
snapping) is anchored at the campaign's origin; the context's points are put back in file order; a point joins its
nearest footprint among all footprints (ties: the first in the file); every building draws its random numbers from
(seed, building id) (:func:`building_rng`); the reach limits come from a stride sample. A context holds every point
any of the building's queries can return, so it answers them exactly as the whole campaign would — and so does a
group's larger context: the grouping does not change the map.

**Memory.** Pass 1 holds a chunk and the spool's buffer (``chunk_points`` rows); the height rule's table one number
per occupied ``ground_cell`` cell (only for campaigns without a ground class); each task one group's context, with
at most ``max_in_flight`` (2 x workers) jobs built and not yet collected. Memory follows the largest group's
surroundings, not the campaign's size.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import shapely
from shapely.geometry import box as shapely_box

from lidarmap.config import check_params
from lidarmap.core import Footprints, PointCloud, Trajectory
from lidarmap.errors import ConfigError, InputError
from lidarmap.executor import (
    TaskFailure,
    building_seed_sequence,
    check_cluster_params,
    group_by_cell,
    map_tasks,
    run_task,
)
from lidarmap.facade.campaign import (
    CampaignData,
    campaign_data,
    campaign_track,
    check_same_crs,
    no_join_error,
)
from lidarmap.facade.observe import building_facades
from lidarmap.facade.sensors import widen_layers
from lidarmap.facade.params import FacadeParams
from lidarmap.facade.planes import check_points, join_footprints
from lidarmap.facade.scan import CampaignScan, CampaignStats, PointClasses, StatsPass
from lidarmap.io.spool import ColumnSpool
from lidarmap.map.model import DERIVED, Building, BuildingMap
from lidarmap.map.refine import RefineParams, _campaign_applied, refine_building

log = logging.getLogger(__name__)

__all__ = ["UpdateParams", "CampaignSource", "cloud_source", "las_source", "CellGrid", "BuildingJob", "GroupJob",
           "BuildingOutcome", "GroupOutcome", "FusedCampaign", "fuse_campaign", "group_task", "building_task",
           "building_groups", "building_rng", "context_box", "ContextBoxes"]

#: Rows per batch of pass 2 (memory of that pass: ~50 bytes per row).
STATS_BATCH_ROWS = 2_000_000
#: At most this many spool cells (every run of the spool stores one offset per cell): a campaign spread wider than
#: 25 km x 25 km gets larger cells.
MAX_SPOOL_CELLS = 1_000_000


@dataclasses.dataclass(frozen=True)
class UpdateParams:
    """How ``lidarmap map update`` runs a mobile campaign (TOML table ``[update]``). None of them changes the map.

        workers (1): worker processes on this machine (a dask LocalCluster, one thread each); 1 = this process.
        scheduler (""): address of a running dask scheduler (e.g. "tcp://10.0.0.5:8786") for multi-machine updates;
            overrides ``workers``. Workers compute buildings; this process alone writes the map.
        chunk_points (2000000): points read from the LAS/LAZ file at a time, also the rows the spool buffers before
            writing them to disk (pass 1 holds about 150 bytes per point of this).
        cell (25.0): xy size (m) of the spool's cells: a building's context is read as the cells its box overlaps,
            then cut to the box.
        group_size (60.0): buildings whose footprint centre falls in the same ``group_size`` x ``group_size`` m
            cell run as one task sharing one context (the union of their boxes): neighbours' contexts overlap
            almost entirely (each reaches the scanner's range), so a group reads and indexes its points once and
            ships them once. 0 = one building per task. Memory per task: one group's context.
        trajectory_warn_gap (1.0): a hole (s) between trajectory rows longer than this is interpolated with a
            warning.
        trajectory_max_gap (30.0): a trajectory with a longer hole (s) is refused (positions would be guesses).
    """

    section = "update"
    constraints: ClassVar[dict[str, str]] = {
        "workers": ">= 0",
        "chunk_points": ">= 0",
        "cell": ">= 0",
        "group_size": ">= 0",
        "trajectory_warn_gap": "> 0",
        "trajectory_max_gap": "> 0",
    }

    workers: int = 1
    scheduler: str = ""
    chunk_points: int = 2_000_000
    cell: float = 25.0
    group_size: float = 60.0
    trajectory_warn_gap: float = 1.0
    trajectory_max_gap: float = 30.0

    def __post_init__(self) -> None:
        check_params(self)
        try:
            check_cluster_params(self.workers, self.scheduler)
        except ConfigError as exc:
            raise ValueError(exc.problem) from None
        if self.chunk_points < 1:
            raise ValueError("chunk_points must be at least 1")
        if not self.cell > 0:
            raise ValueError("cell must be > 0")
        if not (math.isfinite(self.group_size) and self.group_size >= 0):
            raise ValueError("group_size must be >= 0")


# ----------------------------------------------------------------------------------------------------------------------
# The campaign's points


@dataclasses.dataclass
class CampaignSource:
    """A campaign's points as chunks in file order, and what is known before reading them: the xy box they lie in,
    their number and CRS."""

    chunks: Callable[[], Iterator[PointCloud]]
    lo: np.ndarray  # no point lies below or left of it: the campaign's origin
    hi: np.ndarray
    n_points: int
    crs: Any = None
    source: str | None = None


def cloud_source(cloud: PointCloud) -> CampaignSource:
    """A campaign held in memory (one chunk)."""
    check_points(cloud.xyz, cloud.source)
    return CampaignSource(lambda: iter([cloud]), cloud.xyz[:, :2].min(axis=0), cloud.xyz[:, :2].max(axis=0),
                          len(cloud), cloud.crs, cloud.source)


def las_source(path: str | Path, crs: Any = None, chunk_points: int = 2_000_000) -> CampaignSource:
    """A campaign streamed from a LAS/LAZ file: the header's bounds widened by the slack the reader accepts
    (:func:`lidarmap.io.las.iter_las` refuses points further out); a header without bounds costs a first pass.
    ``crs`` is used when the file has none (a conflicting one is an error)."""
    from lidarmap.io.las import iter_las, read_header_crs

    header, points_crs = read_header_crs(path, crs)
    if header.point_count == 0:
        raise InputError("the point cloud is empty", path)
    if "gps_time" not in header.point_format.dimension_names:
        raise InputError("the points have no gps_time: façade occlusion needs each point's sensor position", path)
    lo, hi = np.asarray(header.mins, dtype=np.float64)[:2], np.asarray(header.maxs, dtype=np.float64)[:2]
    if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.any(lo != hi):
        slack = (hi - lo) * 0.01 + np.asarray(header.scales, dtype=np.float64)[:2] * 2
        lo, hi = lo - slack, hi + slack
    else:  # bounds unset by the writer: measure them
        lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
        for chunk in iter_las(path, chunk_points, crs):
            if len(chunk):
                lo, hi = np.minimum(lo, chunk.xyz[:, :2].min(axis=0)), np.maximum(hi, chunk.xyz[:, :2].max(axis=0))
        if not np.all(np.isfinite(lo)):
            lo = hi = np.zeros(2)
    return CampaignSource(lambda: iter_las(path, chunk_points, crs), lo, hi, int(header.point_count), points_crs,
                          str(path))


@dataclasses.dataclass(frozen=True)
class CellGrid:
    """The spool's xy cells: ``cell`` metres from ``origin``, ``shape`` cells (points beyond fall in the edge
    cells, which a context reads whenever its box reaches them)."""

    origin: np.ndarray
    cell: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, lo: np.ndarray, hi: np.ndarray, cell: float) -> "CellGrid":
        """Cells of at least ``cell`` metres over [lo, hi], at most ``MAX_SPOOL_CELLS`` of them."""
        size = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
        cell = max(float(cell), math.sqrt(float(size[0] + cell) * float(size[1] + cell) / MAX_SPOOL_CELLS))
        n = np.floor(size / cell).astype(np.int64) + 1
        return cls(np.asarray(lo, dtype=np.float64), cell, (int(n[0]), int(n[1])))

    @property
    def n_keys(self) -> int:
        return self.shape[0] * self.shape[1]

    def _ij(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((np.asarray(xy, dtype=np.float64) - self.origin) / self.cell).astype(np.int64)
        return np.clip(ij, 0, np.array(self.shape) - 1)

    def keys(self, xy: np.ndarray) -> np.ndarray:
        ij = self._ij(xy)
        return ij[:, 0] * self.shape[1] + ij[:, 1]

    def keys_in(self, box: tuple[float, float, float, float]) -> np.ndarray:
        """Every cell an xy box overlaps."""
        (i0, j0), (i1, j1) = self._ij(np.array([box[:2], box[2:]]))
        return (np.arange(i0, i1 + 1)[:, None] * self.shape[1] + np.arange(j0, j1 + 1)[None, :]).ravel()


def _spool_campaign(source: CampaignSource, grid: CellGrid, spool: ColumnSpool, params: FacadeParams) -> CampaignScan:
    """Pass 1: every point into the spool under its cell, with its number in the file."""
    scan = CampaignScan(grid.origin, params, source.source)
    for chunk in source.chunks():
        index = scan.add(chunk)
        columns = {"xyz": chunk.xyz, "gps_time": np.asarray(chunk.attrs["gps_time"], dtype=np.float64),
                   "index": index}
        if "classification" in chunk.attrs:
            columns["classification"] = chunk.attrs["classification"]
        spool.add(grid.keys(chunk.xyz[:, :2]), columns)
    if scan.n_points == 0:
        raise InputError("the point cloud is empty", source.source)
    return scan


def _key_batches(counts: np.ndarray, rows: int) -> list[np.ndarray]:
    """The non-empty keys in order, grouped into batches of about ``rows`` rows (at least one key each)."""
    keys = np.flatnonzero(counts)
    group = (np.cumsum(counts[keys]) - 1) // rows
    return np.split(keys, np.flatnonzero(np.diff(group)) + 1) if len(keys) else []


def _campaign_stats(spool: ColumnSpool, scan: CampaignScan, classes: PointClasses, trajectory: Trajectory,
                    params: FacadeParams) -> tuple[CampaignStats, np.ndarray]:
    """Pass 2 over the spool (see :class:`~lidarmap.facade.observe.observe.scan.StatsPass`); also the building points per cell."""
    stats = StatsPass(classes, scan, trajectory)
    building_cells = np.zeros(spool.n_keys, dtype=np.int64)
    for keys in _key_batches(spool.counts, STATS_BATCH_ROWS):
        cols = spool.get_many(keys)  # key after key, each key's rows together
        building = stats.add(cols["xyz"], cols["gps_time"], cols.get("classification"), cols["index"])
        starts = np.concatenate([[0], np.cumsum(spool.counts[keys])[:-1]])
        building_cells[keys] = np.add.reduceat(building.astype(np.int64), starts)
    return stats.finish(params.occlusion.reach_quantile), building_cells


# ----------------------------------------------------------------------------------------------------------------------
# One building


def building_rng(seed: int, building_id: str) -> tuple[int, np.random.Generator]:
    """A building's seed and generator: the same whatever else is in the run and on every machine (from
    (seed, building id), from :func:`lidarmap.executor.building_seed_sequence`)."""
    sequence = building_seed_sequence(seed, building_id)
    return int(sequence.generate_state(1)[0]), np.random.default_rng(sequence)


def _grow(box: tuple[float, float, float, float], by: float) -> tuple[float, float, float, float]:
    return box[0] - by, box[1] - by, box[2] + by, box[3] + by


def _inside(xy: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    return (xy[:, 0] >= box[0]) & (xy[:, 0] <= box[2]) & (xy[:, 1] >= box[1]) & (xy[:, 1] <= box[3])


@dataclasses.dataclass(frozen=True)
class ContextBoxes:
    """Where a building's façade work looks (xy boxes): ``facades`` where its façades can lie, ``points`` the
    non-ground points it can query, ``ground`` the ground points, ``track`` the reach track positions."""

    facades: tuple[float, float, float, float]
    points: tuple[float, float, float, float]
    ground: tuple[float, float, float, float]
    track: tuple[float, float, float, float]


def context_box(footprint: Any, stored: Building | None, limits: tuple[float, float, float],
                fparams: FacadeParams, rparams: RefineParams) -> ContextBoxes:
    """The boxes holding every point and track position the building's façade work can look at.

    Its façades lie near the footprint (the join distance, the façade margin, the layers' depth range) and, for a
    stored building, near its stored façades, which a campaign can grow (whole cells, ``extend_margin``) and turn
    (at most ``normal_max_angle_deg`` about their middle). From a façade :func:`lidarmap.facade.observe.observe.observe_facade`
    looks at non-ground points up to the scanner's reach in front (``limits[0] * reach_margin + 1``) and
    ``through_max_depth`` behind, at ground points ``ground_band`` in front, 1 m beyond both, in whole ``index_bin``
    bins; the reach test at track positions within the scanner's reach.
    """
    x0, y0, x1, y1 = footprint.bounds
    near = (fparams.join.max_footprint_distance + fparams.join.join_quantum + fparams.planes.facade_margin + fparams.layers.layer_front
            + fparams.layers.layer_back + 2 * fparams.layers.cell)
    if stored is not None and stored.facades:
        for f in stored.facades:
            ends = f.frame.to_crs(np.array([[f.extent[0], 0.0, 0.0], [f.extent[1], 0.0, 0.0]]))
            x0, y0 = min(x0, *ends[:, 0]), min(y0, *ends[:, 1])
            x1, y1 = max(x1, *ends[:, 0]), max(y1, *ends[:, 1])
        near += rparams.extend_margin + 1.0 + math.sin(math.radians(rparams.normal_max_angle_deg)) * math.hypot(
            x1 - x0, y1 - y0)
    facades = _grow((x0, y0, x1, y1), near)
    reach = limits[0] * fparams.occlusion.reach_margin + 1.0
    return ContextBoxes(facades=facades,
                        points=_grow(facades, max(reach, fparams.occlusion.through_max_depth) + 1.0 + fparams.occlusion.index_bin),
                        ground=_grow(facades, fparams.openings.ground_band + 1.0 + fparams.occlusion.index_bin),
                        track=_grow(facades, reach))


def _join_box(footprint: Any, params: FacadeParams) -> tuple[float, float, float, float]:
    """Where the building's joined points can lie: within the join distance (+ the snapping) of its footprint."""
    return _grow(footprint.bounds, params.join.max_footprint_distance + params.join.join_quantum)


@dataclasses.dataclass
class BuildingJob:
    """One building of a :class:`GroupJob`: what its update needs beyond the group's points (picklable)."""

    building_id: str
    footprint: Any  # shapely polygon from the footprint file
    properties: dict
    stored: Building | None
    neighbours: np.ndarray  # footprints that may be nearer to some of its points, in file order (itself included)
    own: int  # its position among them
    track_box: tuple[float, float, float, float]  # where the reach track positions that can see its façades lie
    origin: np.ndarray  # the campaign's lattices' anchor
    campaign_id: int
    seed: int


@dataclasses.dataclass
class GroupJob:
    """One task: neighbouring buildings and the context they share (picklable; travels to a worker)."""

    members: list[BuildingJob]
    points: dict[str, np.ndarray]  # the union of the members' contexts: xyz, gps_time, index, ground, building
    limits: tuple[float, float, float]
    track: np.ndarray  # the reach track positions that can see some member's façades
    origin: np.ndarray


@dataclasses.dataclass
class BuildingOutcome:
    """A building after the campaign (``None``: nothing new for the map) and how many points joined it."""

    building: Building | None
    n_joined: int
    timings: dict


@dataclasses.dataclass
class GroupOutcome:
    """Each member's outcome (or :class:`TaskFailure`), in member order, and the group's own timings."""

    outcomes: list[BuildingOutcome | TaskFailure]
    timings: dict


def _joined_ids(camp: CampaignData, job: BuildingJob, params: FacadeParams) -> np.ndarray:
    """The context's building points whose nearest footprint (among all footprints) is this building's (§2.2)."""
    xy = camp.xyz[:, :2]
    cand = np.flatnonzero(camp.building & _inside(xy, _join_box(job.footprint, params)))
    nearest, _ = join_footprints(xy[cand], job.neighbours, params.join.max_footprint_distance, params.join.join_quantum,
                                 origin=job.origin)
    return cand[nearest == job.own]


def group_task(job: GroupJob, trajectory: Trajectory, fparams: FacadeParams, rparams: RefineParams,
               noise_factor: float = 1.0, pulse_times: bool = True, strict: bool = False) -> GroupOutcome:
    """The group's context prepared once (file order, sensor positions, indices), then :func:`building_task` for
    each member; a member that fails becomes a :class:`TaskFailure` (``strict``: the error is raised).
    ``noise_factor``: the campaign's Gaussians are that much wider in fusion (an estimated sensor path);
    ``pulse_times`` False: the points' ``gps_time`` is only the trajectory's clock (point number, arc length), not
    the pulses' times, so the ray evidence does not order pulses by it."""
    clock = time.perf_counter()
    order = np.argsort(job.points["index"], kind="stable")  # file order, as the whole campaign would have them
    points = {name: values[order] for name, values in job.points.items()}
    camp = campaign_data(points["xyz"], points["gps_time"], points["ground"], points["building"], trajectory,
                         job.limits, job.track, job.origin, fparams)
    camp.noise_factor = noise_factor
    if not pulse_times:
        camp.gps = None
    timings = {"prepare": time.perf_counter() - clock}
    outcomes: list[BuildingOutcome | TaskFailure] = []
    for member in job.members:
        # a context holding more points answers every query as the member's own would (docs/map.md); the track
        # is cut to the member's own box all the same, as a one-building task has it
        member_camp = dataclasses.replace(camp, track=job.track[_inside(job.track, member.track_box)])
        args = (member, member_camp, fparams, rparams)
        outcomes.append(building_task(*args) if strict else run_task(building_task, *args))
    return GroupOutcome(outcomes, timings)


def building_task(job: BuildingJob, camp: CampaignData, fparams: FacadeParams,
                  rparams: RefineParams) -> BuildingOutcome:
    """One building after the campaign: new façades (a building the map does not hold) or its refinement."""
    tm: dict = {}
    clock = time.perf_counter()
    ids = _joined_ids(camp, job, fparams)
    tm["join"] = time.perf_counter() - clock
    if not len(ids):
        return BuildingOutcome(None, 0, tm)
    seed, rng = building_rng(job.seed, job.building_id)
    if job.properties.get(DERIVED) or (job.stored is not None and job.stored.attributes.get(DERIVED)):
        fparams = fparams.updated(openings_need_edge=False)  # a derived footprint's edges do not follow the walls
    if job.stored is not None:
        result = refine_building(job.stored, camp, ids, fparams, rparams, job.campaign_id, seed, rng, tm)
        return BuildingOutcome(result, len(ids), tm)
    facades = widen_layers(building_facades(camp, ids, job.footprint, fparams, job.campaign_id, seed, rng, tm),
                           camp.noise_factor)
    result = Building(building_id=job.building_id, footprint=job.footprint, attributes=dict(job.properties),
                      facades=facades) if facades else None
    return BuildingOutcome(result, len(ids), tm)


# ----------------------------------------------------------------------------------------------------------------------
# The campaign


@dataclasses.dataclass
class _Campaign:
    """What the jobs share: the spool, its grid, the campaign's rule, stats and reach track."""

    spool: ColumnSpool
    grid: CellGrid
    classes: PointClasses
    stats: CampaignStats
    building_cells: np.ndarray  # building points per spool cell
    track: np.ndarray


def _buildings_near_points(footprints: Footprints, campaign: _Campaign, params: FacadeParams) -> list[int]:
    """Footprints (indices, file order) with building points in the cells of their join box: only they can get
    any (a footprint file may cover a whole city, the campaign a few streets)."""
    return [b for b, polygon in enumerate(footprints.polygons)
            if campaign.building_cells[campaign.grid.keys_in(_join_box(polygon, params))].any()]


def _context_points(campaign: _Campaign, boxes: ContextBoxes) -> dict[str, np.ndarray]:
    """The spooled points a building's façade work can query (cell by cell; :func:`building_task` restores file
    order), with their ground and building masks: non-ground points in ``boxes.points``, ground points (most of a
    street scan, looked at only right in front of a façade) in ``boxes.ground``."""
    cols = campaign.spool.get_many(campaign.grid.keys_in(boxes.points))
    xy = cols["xyz"][:, :2]
    ground, building = campaign.classes.masks(cols["xyz"], cols.pop("classification", None))
    keep = _inside(xy, boxes.points)
    far = np.flatnonzero(keep & ground)
    keep[far] = _inside(xy[far], boxes.ground)
    take = np.flatnonzero(keep)
    return {**{name: values[take] for name, values in cols.items()}, "ground": ground[take],
            "building": building[take]}


def _building_job(b: int, stored: BuildingMap, footprints: Footprints, tree: shapely.STRtree, campaign: _Campaign,
                  fparams: FacadeParams, rparams: RefineParams, campaign_id: int,
                  seed: int) -> tuple[BuildingJob, ContextBoxes]:
    """Footprint ``b``'s job and the boxes of its context."""
    bid = str(footprints.ids[b])
    polygon = footprints.polygons[b]
    building = stored.buildings.get(bid)
    # a point joined to this footprint lies within the join box; any footprint nearer to it than this one
    # intersects the join box grown by the join distance again
    reach = fparams.join.max_footprint_distance + fparams.join.join_quantum
    neighbours = np.sort(tree.query(shapely_box(*_grow(_join_box(polygon, fparams), reach))))
    boxes = context_box(polygon, building, campaign.stats.limits, fparams, rparams)
    job = BuildingJob(building_id=bid, footprint=polygon, properties=dict(footprints.properties[b]),
                      stored=building, neighbours=footprints.polygons[neighbours],
                      own=int(np.searchsorted(neighbours, b)), track_box=boxes.track, origin=campaign.grid.origin,
                      campaign_id=campaign_id, seed=seed)
    return job, boxes


def _union(boxes: Iterable[tuple[float, float, float, float]]) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = np.array(list(boxes)).T
    return float(x0.min()), float(y0.min()), float(x1.max()), float(y1.max())


def _group_job(group: list[int], stored: BuildingMap, footprints: Footprints, tree: shapely.STRtree,
               campaign: _Campaign, fparams: FacadeParams, rparams: RefineParams, campaign_id: int,
               seed: int) -> GroupJob:
    """The job of neighbouring footprints: their context is read once, as the union of their boxes."""
    members, boxes = zip(*(_building_job(b, stored, footprints, tree, campaign, fparams, rparams, campaign_id, seed)
                           for b in group))
    union = ContextBoxes(*(_union(getattr(box, name) for box in boxes) for name in
                           ("facades", "points", "ground", "track")))
    return GroupJob(members=list(members), points=_context_points(campaign, union), limits=campaign.stats.limits,
                    track=campaign.track[_inside(campaign.track, union.track)], origin=campaign.grid.origin)


def building_groups(footprints: Footprints, todo: list[int], size: float) -> list[list[int]]:
    """``todo`` (footprint indices) grouped by the ``size`` m cell of their footprint
    (:func:`lidarmap.executor.group_by_cell`)."""
    boxes = shapely.bounds(footprints.polygons[np.asarray(todo, dtype=np.int64)]) if todo else np.empty((0, 4))
    return [[todo[k] for k in group] for group in group_by_cell(boxes, size)]


def _run_jobs(jobs: Iterable[GroupJob], shared: tuple, update: UpdateParams,
              strict: bool) -> Iterator[tuple[int, GroupOutcome | TaskFailure]]:
    """(number, outcome or TaskFailure) per group; ``strict`` runs them here and lets errors through (in-memory
    callers want the exception, the command a report per building)."""
    if strict:
        for number, job in enumerate(jobs):
            yield number, group_task(job, *shared, strict=True)
        return
    yield from map_tasks(group_task, jobs, update.workers, update.scheduler, shared=shared)


@dataclasses.dataclass
class FusedCampaign:
    """The map after the campaign, the buildings whose task failed ({id: reason}; their stored version kept),
    and the campaign's numbers."""

    map: BuildingMap
    failed: dict[str, str]
    stats: CampaignStats


def _add_timings(total: dict, part: dict) -> None:
    for key, seconds in part.items():
        total[key] = total.get(key, 0.0) + seconds


def fuse_campaign(stored: BuildingMap, source: CampaignSource, trajectory: Trajectory, footprints: Footprints,
                  fparams: FacadeParams, rparams: RefineParams, campaign_id: int, seed: int = 0,
                  update: UpdateParams | None = None, spool_dir: str | Path | None = None, strict: bool = False,
                  timings: dict | None = None,
                  progress: Callable[[int, int], None] | None = None, noise_factor: float = 1.0,
                  pulse_times: bool = True) -> FusedCampaign:
    """The map after one mobile campaign (see the module doc); ``stored`` is not modified.

    ``spool_dir``: a folder for the spool (created, removed at the end), ``None`` keeps it in memory. ``strict``
    runs every building here and raises the first error; otherwise a failing building is reported in
    ``failed``. ``progress(done, total)`` after every group of buildings. ``noise_factor`` widens the campaign's
    Gaussians in fusion (a campaign whose sensor path was estimated, :mod:`lidarmap.map.mls`). Raises
    :class:`~lidarmap.errors.InputError` for an empty campaign, missing GPS times, times the trajectory does not
    cover, and a campaign none of whose building points lies near a footprint when the footprints lie away from its
    points (within their box it saw none of the mapped buildings: a warning, no building changes).
    """
    update = update or UpdateParams()
    tm = timings if timings is not None else {}
    clock = time.perf_counter()
    grid = CellGrid.covering(source.lo, source.hi, update.cell)
    with ColumnSpool(grid.n_keys, spool_dir, buffer_rows=update.chunk_points) as spool:
        scan = _spool_campaign(source, grid, spool, fparams)
        classes = scan.classes()
        stats, building_cells = _campaign_stats(spool, scan, classes, trajectory, fparams)
        campaign = _Campaign(spool, grid, classes, stats, building_cells,
                             campaign_track(trajectory, *stats.t_span, fparams.occlusion.reach_step))
        todo = _buildings_near_points(footprints, campaign, fparams)
        groups = building_groups(footprints, todo, update.group_size)
        tm["prepare"] = tm.get("prepare", 0.0) + time.perf_counter() - clock
        tree = shapely.STRtree(footprints.polygons)
        jobs = (_group_job(group, stored, footprints, tree, campaign, fparams, rparams, campaign_id, seed)
                for group in groups)
        outcomes: dict[int, Any] = {}
        for number, result in _run_jobs(jobs, (trajectory, fparams, rparams, noise_factor, pulse_times), update,
                                        strict):
            if isinstance(result, TaskFailure):  # the group's context could not be prepared: all its buildings
                outcomes.update((b, result) for b in groups[number])
            else:
                _add_timings(tm, result.timings)
                outcomes.update(zip(groups[number], result.outcomes))
            if progress is not None:
                progress(len(outcomes), len(todo))
    return _assemble(stored, footprints, outcomes, stats, fparams, tm)


def _assemble(stored: BuildingMap, footprints: Footprints, outcomes: dict[int, Any], stats: CampaignStats,
              fparams: FacadeParams, tm: dict) -> FusedCampaign:
    """The new map in footprint order (stored buildings keep their place); failures keep the stored building."""
    new_map = copy.deepcopy(stored)
    failed: dict[str, str] = {}
    joined = 0
    for b in sorted(outcomes):
        bid, outcome = str(footprints.ids[b]), outcomes[b]
        if isinstance(outcome, TaskFailure):
            failed[bid] = outcome.reason
            log.warning("building %s failed: %s", bid, outcome.reason)
            continue
        joined += outcome.n_joined
        _add_timings(tm, outcome.timings)
        if outcome.building is not None:
            new_map.buildings[bid] = outcome.building
    if not joined and not failed:
        if not footprints.meets(stats.bounds, fparams.join.max_footprint_distance):
            raise no_join_error(stats.n_building, stats.bounds, footprints, fparams)
        # the footprints lie where the campaign went, but it saw none of their buildings (a drive along a street
        # of unmapped houses, a scanner facing away): the map has nothing to learn from it, which is no input error
        # (issue 18 round 37: reserved independent scene 9049's third campaign stopped the whole run)
        log.warning("%s: none of its %d building points lies within %g m of a footprint: it saw none of the mapped "
                    "buildings; no building changes", stats.source or "the campaign", stats.n_building,
                    fparams.join.max_footprint_distance)
    if failed and len(failed) == len(outcomes):  # committing would mark the campaign applied with nothing from it
        bid, reason = next(iter(failed.items()))
        raise InputError(f"the task of every building failed ({len(failed)}; {bid}: {reason}); nothing changed",
                         stats.source)
    return FusedCampaign(new_map, failed, stats)


def extract_buildings(points: PointCloud, trajectory: Trajectory, footprints: Footprints, params: FacadeParams,
                      campaign_id: int, seed: int = 0, timings: dict | None = None) -> list[Building]:
    """Buildings with façades, layers, elements and evidence from one mobile-mapping campaign.

    ``points`` need ``gps_time`` (for the sensor positions of the occlusion ray tracing) and are in the same CRS as
    ``footprints``. Returns the buildings (footprint order) that received at least one façade; ``timings`` (a dict)
    receives seconds per step. Runs building by building exactly like ``lidarmap map update``
    (:func:`lidarmap.map.update.fuse_campaign`): each building draws its random numbers from (seed, its id).
    """
    from lidarmap.map.model import BuildingMap
    from lidarmap.map.refine import RefineParams
    from lidarmap.map.update import cloud_source, fuse_campaign

    check_same_crs(points, footprints)
    fused = fuse_campaign(BuildingMap(crs_wkt=""), cloud_source(points), trajectory, footprints, params,
                          RefineParams(), campaign_id, seed, strict=True, timings=timings)
    return list(fused.map.buildings.values())


def refine_map(stored: BuildingMap, points: PointCloud, trajectory: Trajectory, footprints: Footprints,
               facade_params: FacadeParams, params: RefineParams, campaign_id: int, seed: int = 0,
               timings: dict | None = None) -> BuildingMap:
    """The map after one more mobile campaign (see the module doc); ``stored`` is not modified.

    Buildings are matched to footprints by id; a building the map does not hold yet is extracted from the campaign
    (§2.2-2.4). Re-applying a campaign id the map already lists (or a façade already holds) changes nothing.
    ``timings`` (a dict) receives seconds per step. Runs building by building exactly like ``lidarmap map update``
    (:func:`lidarmap.map.update.fuse_campaign`, in this process, the first error raised).
    """
    from lidarmap.map.update import cloud_source, fuse_campaign

    if _campaign_applied(stored, campaign_id):
        return copy.deepcopy(stored)
    check_same_crs(points, footprints)
    return fuse_campaign(stored, cloud_source(points), trajectory, footprints, facade_params, params, campaign_id,
                         seed, strict=True, timings=timings).map
