"""Update a map file with one campaign: the use case behind ``lidarmap map update`` (and the demo, and Python users).

Under the map's writer lock: refuse a campaign whose files were applied before (same bytes:
:func:`lidarmap.map.store.campaign_fingerprint`) before reading them, read the points (a mobile campaign is streamed),
fuse them into the stored map (:func:`lidarmap.map.update.fuse_campaign` or :func:`lidarmap.map.refine.add_aerial`)
and commit the new state in one transaction; a map that does not exist yet is created (in the points' CRS) only when
the first campaign commits, so a failed first update leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import glob
import logging
import shutil
import sqlite3
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from lidarmap.core import Footprints, PointCloud
from lidarmap.errors import ConfigError, CRSError, InputError
from lidarmap.export.summary import count_map
from lidarmap.io.crs import horizontal_crs, same_crs
from lidarmap.io.footprints import check_overlap, read_footprints
from lidarmap.io.points import read_points
from lidarmap.map import refine
from lidarmap.map.mls import (
    DERIVED,
    discover_campaign,
    join_given_footprints,
    merge_discovered,
    mobile_campaign,
)
from lidarmap.map.model import BuildingMap, Campaign
from lidarmap.map.store import (
    MapStore,
    campaign_fingerprint,
    damaged_map_error,
    writer_lock,
)
from lidarmap.map.update import UpdateParams, fuse_campaign

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class CampaignInputs:
    """What one ``map update`` reads: a mobile campaign (points + trajectory) or an aerial scan."""

    kind: str  # "mobile" | "aerial"
    points: Path
    trajectory: Path | None
    footprints: Path | None
    id_field: str
    crs: str | None
    columns: str | None = None  # a text point file's column spec (lidarmap.io.xyz)

    @property
    def source(self) -> str:
        """Campaign source as history shows it: the file name(s)."""
        return self.points.name + (f" + {self.trajectory.name}" if self.trajectory else "")


def campaign_inputs(points: Path | None, trajectory: Path | None, aerial: Path | None, footprints: Path | None,
                    id_field: str | None, crs: str | None, columns: str | None = None) -> CampaignInputs:
    """Check the option combination of ``map update`` (one line per mistake). Without ``trajectory`` a mobile
    campaign's sensor positions come from the points (origins, or a path estimated from the cloud: docs/mls.md)."""
    if points is None and aerial is None:
        raise ConfigError("map update needs --points (a mobile campaign) or --aerial (an aerial scan)")
    if points is not None and aerial is not None:
        raise ConfigError("--points and --aerial cannot be combined: one campaign per update")
    if aerial is not None and trajectory is not None:
        raise ConfigError("--trajectory belongs to a mobile campaign (--points), not to --aerial")
    kind = "mobile" if points is not None else "aerial"
    return CampaignInputs(kind=kind, points=Path(points if points is not None else aerial), trajectory=trajectory,
                          footprints=footprints, id_field=id_field or "id", crs=crs, columns=columns)


def _refuse_applied(store: MapStore, fingerprint: str, inputs: CampaignInputs) -> None:
    applied = store.campaign_for_fingerprint(fingerprint)
    if applied is not None:
        raise InputError(f"campaign already applied: {inputs.source} is campaign {applied.campaign_id} "
                         f"(applied {applied.created[:19]}); nothing changed", store.path)


def _map_crs(points_crs: CRS | None, store: MapStore | None, points: Path) -> CRS:
    """The map's CRS: the stored one (the points must match it) or, for a new map, the points' CRS."""
    if points_crs is None:
        raise CRSError("the points have no CRS; give it with --crs (e.g. --crs EPSG:32632)", points)
    if store is None or not store.crs_wkt:
        return points_crs
    stored = CRS.from_user_input(store.crs_wkt)
    if not same_crs(stored, points_crs):
        raise CRSError(f"the points are in {points_crs.name!r} but the map is in {stored.name!r}", points)
    return stored


def map_footprints(building_map: BuildingMap, source: Path) -> Footprints:
    """The map's own building footprints (ids, polygons, attributes) as :class:`Footprints` in the map's CRS."""
    buildings = list(building_map.buildings.values())
    if not buildings:
        raise ConfigError("the map has no buildings yet: give --footprints")
    polygons = np.empty(len(buildings), dtype=object)
    polygons[:] = [b.footprint for b in buildings]
    return Footprints(ids=[b.building_id for b in buildings], polygons=polygons,
                      properties=[dict(b.attributes) for b in buildings],
                      crs=horizontal_crs(CRS.from_user_input(building_map.crs_wkt)), source=str(source))


def _campaign_footprints(inputs: CampaignInputs, points: _Points, stored: BuildingMap, map_path: Path,
                         fparams: Any, seed: int, discover: Any = None) -> tuple[Footprints, dict[str, tuple]]:
    """The footprints the campaign runs with, and the footprint changes the map takes after it ({building id:
    (polygon, attributes or None to keep them)}): the footprint file (joined to buildings the map found from the
    points), else the map's buildings (aerial), else for a mobile campaign the map's buildings and those found in
    its points (:mod:`lidarmap.map.mls`, docs/mls.md)."""
    known = map_footprints(stored, map_path) if stored.buildings else None
    if inputs.footprints is not None:
        footprints = read_footprints(inputs.footprints, id_field=inputs.id_field, crs=points.crs)
        check_overlap(footprints, points.bounds, inputs.points.name)
        return join_given_footprints(footprints, known) if inputs.kind == "mobile" else (footprints, {})
    if inputs.kind == "aerial":
        footprints = map_footprints(stored, map_path)
        check_overlap(footprints, points.bounds, inputs.points.name)
        return footprints, {}
    found = discover_campaign(points.mobile, fparams, discover, seed)
    log.info("%s: %d building(s) found from the points", inputs.points, len(found))
    if not found and known is None:
        raise InputError("no building found in the points (no vertical walls seen): give --footprints", inputs.points)
    footprints, grown = merge_discovered(known, found, horizontal_crs(points.crs), str(inputs.points))
    return footprints, {bid: (polygon, None) for bid, polygon in grown.items()}


def _store_footprints(new_map: BuildingMap, changes: dict[str, tuple]) -> None:
    """Footprints grown by a campaign or given for buildings found from the points, into the new map."""
    for bid, (polygon, attributes) in changes.items():
        building = new_map.buildings.get(bid)
        if building is None:
            continue
        building.footprint = polygon
        if attributes is not None:
            building.attributes = {k: v for k, v in attributes.items() if k != DERIVED}


@dataclasses.dataclass
class _Points:
    """The campaign's points as far as the update needs them before fusing: CRS, count, xy bounds, and either the
    whole cloud (aerial) or a stream (mobile)."""

    crs: CRS | None
    n_points: int
    bounds: tuple[float, float, float, float]
    cloud: PointCloud | None = None
    stream: Any = None  # lidarmap.map.update.CampaignSource
    mobile: Any = None  # lidarmap.map.mls.MobileCampaign: the stream with its trajectory and sensor mode


def _read_points(inputs: CampaignInputs, update: Any, sensors: Any = None) -> _Points:
    """Aerial scans are read whole; of a mobile campaign only the header here (the update streams it)."""
    if inputs.kind == "mobile":
        mobile = mobile_campaign(inputs.points, inputs.trajectory, inputs.crs, inputs.columns, update.chunk_points,
                                 sensors, (update.trajectory_warn_gap, update.trajectory_max_gap))
        stream = mobile.source
        return _Points(stream.crs, stream.n_points, (*stream.lo, *stream.hi), stream=stream, mobile=mobile)
    cloud = read_points(inputs.points, crs=inputs.crs, columns=inputs.columns)
    if len(cloud) == 0:
        raise InputError("the point cloud is empty", inputs.points)
    lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
    return _Points(cloud.crs, len(cloud), (lo[0], lo[1], hi[0], hi[1]), cloud=cloud)


@dataclasses.dataclass
class _Fused:
    """The refinement stage's answer: the new map and the buildings whose task failed ({id: reason})."""

    map: BuildingMap
    failed: dict[str, str]


def _new_map(stored: BuildingMap, points: _Points, footprints: Footprints, inputs: CampaignInputs,
             params: tuple[Any, Any], update: Any, campaign_id: int, seed: int, map_path: Path,
             progress: Callable[[int, int], None]) -> _Fused:
    """The refinement stage: a new map (``stored`` untouched). Aerial: ``refine.add_aerial`` in memory. Mobile:
    :func:`lidarmap.map.update.fuse_campaign` streaming the points through a spool in a temporary folder beside
    the map (removed at the end, also on error), buildings on the workers ``update`` names."""
    facade_params, refine_params = params
    if inputs.kind == "aerial":
        return _Fused(refine.add_aerial(stored, points.cloud, footprints, refine_params, campaign_id, seed), {})
    with tempfile.TemporaryDirectory(dir=map_path.resolve().parent, prefix=_spool_prefix(map_path)) as spool:
        fused = fuse_campaign(stored, points.stream, points.mobile.trajectory, footprints, facade_params,
                              refine_params, campaign_id, seed, update=update, spool_dir=Path(spool) / "points",
                              progress=progress, noise_factor=points.mobile.noise_factor,
                              pulse_times=points.mobile.pulse_times)
    return _Fused(fused.map, fused.failed)


def _spool_prefix(map_path: Path) -> str:
    """The spool folder beside the map during a mobile update: ``.<map name>.spool-XXXX``."""
    return f".{map_path.name}.spool-"


def _remove_stale_spools(map_path: Path) -> None:
    """Spools of earlier updates that were killed (``kill -9`` skips the cleanup): the caller holds the map's writer
    lock, so no other update of this map is running and every spool of it is stale."""
    for stale in map_path.resolve().parent.glob(f"{glob.escape(_spool_prefix(map_path))}*"):
        shutil.rmtree(stale, ignore_errors=True)


@dataclasses.dataclass
class UpdateResult:
    """What ``map update`` committed; ``failed``: buildings whose task failed ({id: reason}), left as stored."""

    campaign: Campaign
    changes: dict[str, dict[str, int]]
    counts: dict[str, int]
    seconds: float
    failed: dict[str, str] = dataclasses.field(default_factory=dict)


def _campaign_record(inputs: CampaignInputs, campaign_id: int, fingerprint: str, points: _Points,
                     counts: dict[str, int], seconds: float, seed: int, failed: dict[str, str]) -> Campaign:
    """The campaign row: what was applied, its fingerprint, the map's counts after it (``map history``), the
    buildings it could not update (``failed``: {id: reason}) and, for a mobile campaign, where its sensor positions
    came from (``sensors``; an estimated path also ``noise_factor``)."""
    files = {name: str(path.resolve()) for name, path in (("points", inputs.points), ("trajectory", inputs.trajectory),
                                                           ("footprints", inputs.footprints)) if path is not None}
    sensors = {} if points.mobile is None else {"sensors": points.mobile.mode,
                                                "noise_factor": points.mobile.noise_factor}
    source = inputs.source + (f" [{points.mobile.mode}]" if points.mobile is not None and
                              points.mobile.mode != "trajectory" else "")
    return Campaign(campaign_id=campaign_id, kind=inputs.kind, source=source, fingerprint=fingerprint,
                    n_points=points.n_points, created=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    summary={**counts, "seconds": round(seconds, 3), "seed": seed, "files": files,
                             "failed": dict(failed), **sensors})


def apply_campaign(map_path: Path, inputs: CampaignInputs, params: tuple[Any, Any], seed: int,
                   step: Callable[[str], None] = lambda name: None, update: Any = None,
                   progress: Callable[[int, int], None] = lambda done, total: None, sensors: Any = None,
                   discover: Any = None) -> UpdateResult:
    """Fuse one campaign into the map (created when missing) in one transaction, under the writer lock.

    ``update``: :class:`lidarmap.map.update.UpdateParams` (workers, scheduler, chunking of a mobile campaign;
    default: this process). ``progress(done, total)`` after every building of a mobile campaign. ``sensors``
    (:class:`lidarmap.facade.sensors.SensorParams`) and ``discover`` (:class:`lidarmap.facade.discover.DiscoverParams`):
    a mobile campaign without trajectory file or footprints (default parameters when ``None``).
    """
    update = update or UpdateParams()
    started = time.perf_counter()
    with writer_lock(map_path):
        _remove_stale_spools(map_path)
        store = MapStore.open(map_path) if map_path.exists() else None
        try:
            step("fingerprint")
            fingerprint = campaign_fingerprint(inputs.points, inputs.trajectory)
            if store is not None:
                _refuse_applied(store, fingerprint, inputs)
            step("reading points")
            points = _read_points(inputs, update, sensors)
            crs = _map_crs(points.crs, store, inputs.points)
            stored = store.load() if store is not None else BuildingMap(crs_wkt=crs.to_wkt())
            step("reading footprints")
            footprints, footprint_changes = _campaign_footprints(inputs, points, stored, map_path, params[0], seed,
                                                                 discover)
            campaign_id = store.next_campaign_id() if store is not None else 1
            step("refining the map")
            fused = _new_map(stored, points, footprints, inputs, params, update, campaign_id, seed, map_path,
                             progress)
            new_map = fused.map
            _store_footprints(new_map, footprint_changes)
            counts = count_map(new_map)
            campaign = _campaign_record(inputs, campaign_id, fingerprint, points, counts,
                                        time.perf_counter() - started, seed, fused.failed)
            new_map.campaigns = [*stored.campaigns, campaign]
            step("committing")
            if store is None:
                store = MapStore.create(map_path, crs.to_wkt())
            changes = store.commit(new_map, campaign)
            log.info("%s: campaign %d (%s) committed: %s", map_path, campaign_id, inputs.source, counts)
        except sqlite3.DatabaseError as exc:
            damaged = damaged_map_error(exc, map_path)
            if damaged is None:
                raise
            raise damaged from None
        finally:
            if store is not None:
                store.close()
    return UpdateResult(campaign, changes, counts, time.perf_counter() - started, fused.failed)
