"""``lidarmap map ...``: the persistent façade map, refined campaign by campaign (docs/map.md).

::

    lidarmap map update MAP --points MLS.laz --trajectory T.csv --footprints F.geojson   # a mobile campaign
    lidarmap map update MAP --aerial ALS.laz [--footprints F.geojson]                    # roof planes
    lidarmap map show MAP [--building ID] [--as-of N]
    lidarmap map history MAP
    lidarmap map export MAP -o city.city.json [--as-of N]
    lidarmap map render MAP -o renders/ [--as-of N] [--building ID]

``update`` holds the map's writer lock from start to end, refuses a campaign whose files were applied before (same
bytes: :func:`lidarmap.store.campaign_fingerprint`) before reading them, and writes the new state in one
transaction; a map that does not exist yet is created (in the points' CRS) only when the first campaign commits.
Heavy modules are imported inside the commands so that ``lidarmap --help`` stays fast.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import typer
from rich.markup import escape
from rich.table import Table

from lidarmap.cli.common import (ConfigOption, CrsOption, IdFieldOption, SeedOption, handle_errors, params_from,
                                 progress, table_console)
from lidarmap.errors import ConfigError, CRSError, InputError

if TYPE_CHECKING:
    from pyproj import CRS

    from lidarmap.io.footprints import Footprints
    from lidarmap.io.pointcloud import PointCloud
    from lidarmap.model import BuildingMap, Campaign
    from lidarmap.store import MapStore

map_app = typer.Typer(name="map", no_args_is_help=True, add_completion=False,
                      help="The façade map: update it with a campaign, show, export (CityJSON), render, history.")

MapArgument = typer.Argument(..., metavar="MAP", help="The map file (SQLite, e.g. city.lmap).", dir_okay=False)
AsOfOption = typer.Option(None, "--as-of", help="The map as it was right after campaign N (see 'map history').")
BuildingOption = typer.Option(None, "--building", "-b", help="Only this building (its id in the footprints).")

#: Element rows ``map show`` prints without ``--building`` before it stops (a city has thousands).
SHOW_ELEMENTS = 200
def register(app: typer.Typer) -> None:
    """Add the ``map`` command group to the app."""
    app.add_typer(map_app, name="map")


# ----------------------------------------------------------------------------------------------------------------------
# map update


@dataclasses.dataclass(frozen=True)
class CampaignInputs:
    """What one ``map update`` reads: a mobile campaign (points + trajectory) or an aerial scan."""

    kind: str  # "mobile" | "aerial"
    points: Path
    trajectory: Path | None
    footprints: Path | None
    id_field: str
    crs: str | None

    @property
    def source(self) -> str:
        """Campaign source as history shows it: the file name(s)."""
        return self.points.name + (f" + {self.trajectory.name}" if self.trajectory else "")


def campaign_inputs(points: Path | None, trajectory: Path | None, aerial: Path | None, footprints: Path | None,
                    id_field: str | None, crs: str | None) -> CampaignInputs:
    """Check the option combination of ``map update`` (one line per mistake)."""
    if points is None and aerial is None:
        raise ConfigError("map update needs --points (a mobile campaign) or --aerial (an aerial scan)")
    if points is not None and aerial is not None:
        raise ConfigError("--points and --aerial cannot be combined: one campaign per update")
    if points is not None and trajectory is None:
        raise ConfigError("--points needs --trajectory (the vehicle trajectory CSV of the campaign)")
    if points is not None and footprints is None:
        raise ConfigError("--points needs --footprints (building footprints, GeoJSON)")
    if aerial is not None and trajectory is not None:
        raise ConfigError("--trajectory belongs to a mobile campaign (--points), not to --aerial")
    kind = "mobile" if points is not None else "aerial"
    return CampaignInputs(kind=kind, points=Path(points if points is not None else aerial), trajectory=trajectory,
                          footprints=footprints, id_field=id_field or "id", crs=crs)


def stage_params(config: Path | None) -> tuple[Any, Any]:
    """FacadeParams (``[facade]``) and RefineParams (``[refine]``) from the config file; errors name the file."""
    from lidarmap.facade import FacadeParams
    from lidarmap.refine import RefineParams

    try:
        return params_from(FacadeParams, config), params_from(RefineParams, config)
    except ConfigError as exc:
        if exc.path is None and config is not None:
            raise ConfigError(exc.problem, config) from None
        raise


def _refuse_applied(store: MapStore, fingerprint: str, inputs: CampaignInputs) -> None:
    applied = store.campaign_for_fingerprint(fingerprint)
    if applied is not None:
        raise InputError(f"campaign already applied: {inputs.source} is campaign {applied.campaign_id} "
                         f"(applied {applied.created[:19]}); nothing changed", store.path)


def update_params(config: Path | None, workers: int | None = None, scheduler: str | None = None) -> Any:
    """UpdateParams (``[update]``) from the config file, ``--workers`` / ``--scheduler`` overriding it."""
    from lidarmap.map_update import UpdateParams

    return params_from(UpdateParams, config, workers=workers, scheduler=scheduler)


def _map_crs(points_crs: CRS | None, store: MapStore | None, points: Path) -> CRS:
    """The map's CRS: the stored one (the points must match it) or, for a new map, the points' CRS."""
    from pyproj import CRS

    from lidarmap.io.crs import same_crs

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
    import numpy as np
    from pyproj import CRS

    from lidarmap.io.crs import horizontal_crs
    from lidarmap.io.footprints import Footprints

    buildings = list(building_map.buildings.values())
    if not buildings:
        raise ConfigError("the map has no buildings yet: give --footprints")
    polygons = np.empty(len(buildings), dtype=object)
    polygons[:] = [b.footprint for b in buildings]
    return Footprints(ids=[b.building_id for b in buildings], polygons=polygons,
                      properties=[dict(b.attributes) for b in buildings],
                      crs=horizontal_crs(CRS.from_user_input(building_map.crs_wkt)), source=str(source))


def _campaign_footprints(inputs: CampaignInputs, crs: CRS, bounds: tuple[float, float, float, float],
                         stored: BuildingMap, map_path: Path) -> Footprints:
    from lidarmap.io.footprints import check_overlap, read_footprints

    if inputs.footprints is not None:
        footprints = read_footprints(inputs.footprints, id_field=inputs.id_field, crs=crs)
    else:
        footprints = map_footprints(stored, map_path)
    check_overlap(footprints, bounds, inputs.points.name)
    return footprints


@dataclasses.dataclass
class _Points:
    """The campaign's points as far as the update needs them before fusing: CRS, count, xy bounds, and either the
    whole cloud (aerial) or a stream (mobile)."""

    crs: CRS | None
    n_points: int
    bounds: tuple[float, float, float, float]
    cloud: PointCloud | None = None
    stream: Any = None  # lidarmap.map_update.CampaignSource


def _read_points(inputs: CampaignInputs, update: Any) -> _Points:
    """Aerial scans are read whole; of a mobile campaign only the header here (the update streams it)."""
    from lidarmap.io.las import read_las
    from lidarmap.map_update import las_source

    if inputs.kind == "mobile":
        stream = las_source(inputs.points, inputs.crs, update.chunk_points)
        return _Points(stream.crs, stream.n_points, (*stream.lo, *stream.hi), stream=stream)
    cloud = read_las(inputs.points, crs=inputs.crs)
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
    :func:`lidarmap.map_update.fuse_campaign` streaming the points through a spool in a temporary folder beside
    the map (removed at the end, also on error), buildings on the workers ``update`` names."""
    import tempfile

    from lidarmap import refine
    from lidarmap.io.trajectory import read_trajectory
    from lidarmap.map_update import fuse_campaign

    facade_params, refine_params = params
    if inputs.kind == "aerial":
        return _Fused(refine.add_aerial(stored, points.cloud, footprints, refine_params, campaign_id, seed), {})
    trajectory = read_trajectory(inputs.trajectory)
    with tempfile.TemporaryDirectory(dir=map_path.resolve().parent, prefix=f".{map_path.name}.spool-") as spool:
        fused = fuse_campaign(stored, points.stream, trajectory, footprints, facade_params, refine_params,
                              campaign_id, seed, update=update, spool_dir=Path(spool) / "points", progress=progress)
    return _Fused(fused.map, fused.failed)


@dataclasses.dataclass
class UpdateResult:
    """What ``map update`` committed; ``failed``: buildings whose task failed ({id: reason}), left as stored."""

    campaign: Campaign
    changes: dict[str, dict[str, int]]
    counts: dict[str, int]
    seconds: float
    failed: dict[str, str] = dataclasses.field(default_factory=dict)


def _campaign_record(inputs: CampaignInputs, campaign_id: int, fingerprint: str, n_points: int,
                     counts: dict[str, int], seconds: float, seed: int, failed: dict[str, str]) -> Campaign:
    """The campaign row: what was applied, its fingerprint, the map's counts after it (``map history``) and the
    buildings it could not update (``failed``: {id: reason})."""
    from lidarmap.model import Campaign

    files = {name: str(path.resolve()) for name, path in (("points", inputs.points), ("trajectory", inputs.trajectory),
                                                           ("footprints", inputs.footprints)) if path is not None}
    return Campaign(campaign_id=campaign_id, kind=inputs.kind, source=inputs.source, fingerprint=fingerprint,
                    n_points=n_points, created=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    summary={**counts, "seconds": round(seconds, 3), "seed": seed, "files": files,
                             "failed": dict(failed)})


def apply_campaign(map_path: Path, inputs: CampaignInputs, params: tuple[Any, Any], seed: int,
                   step: Callable[[str], None] = lambda name: None, update: Any = None,
                   progress: Callable[[int, int], None] = lambda done, total: None) -> UpdateResult:
    """Fuse one campaign into the map (created when missing) in one transaction, under the writer lock.

    ``update``: :class:`lidarmap.map_update.UpdateParams` (workers, scheduler, chunking of a mobile campaign;
    default: this process). ``progress(done, total)`` after every building of a mobile campaign.
    """
    from lidarmap.export.summary import count_map
    from lidarmap.map_update import UpdateParams
    from lidarmap.model import BuildingMap
    from lidarmap.store import MapStore, campaign_fingerprint, writer_lock

    update = update or UpdateParams()
    started = time.perf_counter()
    with writer_lock(map_path):
        store = MapStore.open(map_path) if map_path.exists() else None
        try:
            step("fingerprint")
            fingerprint = campaign_fingerprint(inputs.points, inputs.trajectory)
            if store is not None:
                _refuse_applied(store, fingerprint, inputs)
            step("reading points")
            points = _read_points(inputs, update)
            crs = _map_crs(points.crs, store, inputs.points)
            stored = store.load() if store is not None else BuildingMap(crs_wkt=crs.to_wkt())
            step("reading footprints")
            footprints = _campaign_footprints(inputs, points.crs, points.bounds, stored, map_path)
            campaign_id = store.next_campaign_id() if store is not None else 1
            step("refining the map")
            fused = _new_map(stored, points, footprints, inputs, params, update, campaign_id, seed, map_path,
                             progress)
            new_map = fused.map
            counts = count_map(new_map)
            campaign = _campaign_record(inputs, campaign_id, fingerprint, points.n_points, counts,
                                        time.perf_counter() - started, seed, fused.failed)
            new_map.campaigns = [*stored.campaigns, campaign]
            step("committing")
            if store is None:
                store = MapStore.create(map_path, crs.to_wkt())
            changes = store.commit(new_map, campaign)
        finally:
            if store is not None:
                store.close()
    return UpdateResult(campaign, changes, counts, time.perf_counter() - started, fused.failed)


_UPDATE_STEPS = ("fingerprint", "reading points", "reading footprints", "refining the map", "committing")


@handle_errors
def update_command(
    map_path: Path = MapArgument,
    points: Optional[Path] = typer.Option(None, "--points", help="Mobile campaign points (LAS/LAZ with GPS time).",
                                          dir_okay=False),
    trajectory: Optional[Path] = typer.Option(None, "--trajectory", help="Trajectory CSV of the mobile campaign.",
                                              dir_okay=False),
    aerial: Optional[Path] = typer.Option(None, "--aerial", help="Aerial scan (LAS/LAZ): adds roof planes.",
                                          dir_okay=False),
    footprints: Optional[Path] = typer.Option(None, "--footprints", "-f", help="Building footprints (GeoJSON); "
                                              "optional with --aerial (default: the map's buildings).",
                                              dir_okay=False),
    id_field: Optional[str] = IdFieldOption,
    crs: Optional[str] = CrsOption,
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes for the buildings of a mobile "
                                          "campaign (dask LocalCluster; default 1: this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address for multi-machine "
                                            "updates, e.g. tcp://10.0.0.5:8786."),
    seed: Optional[int] = SeedOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Fuse one campaign into the map (created if missing): façades, layers, windows, doors, occlusions or roofs."""
    inputs = campaign_inputs(points, trajectory, aerial, footprints, id_field, crs)
    params = stage_params(config)
    update = update_params(config, workers, scheduler)
    with progress(transient=True) as bar:
        task = bar.add_task("map update", total=len(_UPDATE_STEPS))

        def step(name: str) -> None:
            bar.update(task, description=name, completed=_UPDATE_STEPS.index(name))

        def buildings(done: int, total: int) -> None:
            bar.update(task, description=f"refining the map ({done}/{total} buildings)")

        result = apply_campaign(map_path, inputs, params, 0 if seed is None else seed, step, update, buildings)
    _print_update(map_path, result)


def _change_text(change: dict[str, int]) -> tuple[str, str, str]:
    return tuple(str(change.get(k, 0)) for k in ("added", "updated", "removed"))  # type: ignore[return-value]


def _print_update(map_path: Path, result: UpdateResult) -> None:
    from lidarmap.store import ENTITIES

    c = result.campaign
    table = Table(title=f"campaign {c.campaign_id} ({c.kind}, {c.source}, {c.n_points:,} points) -> {map_path.name}",
                  title_justify="left")
    for column in ("entity", "in the map", "added", "updated", "removed"):
        table.add_column(column, justify="left" if column == "entity" else "right")
    in_map = {"buildings": result.counts["buildings"], "facades": result.counts["facades"],
              "layers": result.counts["layers"], "roofs": result.counts["roofs"],
              "elements": sum(result.counts[k] for k in ("windows", "doors", "structures", "unknown"))}
    for entity in ENTITIES:
        table.add_row(entity, str(in_map.get(entity, "–")), *_change_text(result.changes.get(entity, {})))
    out = table_console()
    out.print(table)
    for bid, reason in result.failed.items():
        out.print(f"[yellow]failed[/] {escape(bid)}: {escape(reason)} (kept as stored)", highlight=False)
    k = result.counts
    failed = f", {len(result.failed)} building(s) failed" if result.failed else ""
    out.print(f"{k['buildings']} buildings, {k['facades']} façades, {k['windows']} windows, {k['doors']} doors, "
              f"{k['structures']} structures, {k['unknown']} unknown regions, {k['roofs']} roof planes{failed}; "
              f"done in {result.seconds:.1f} s", highlight=False)


# ----------------------------------------------------------------------------------------------------------------------
# Reading commands


def load_map(map_path: Path, as_of: int | None, building: str | None = None) -> BuildingMap:
    """The stored map (as of a campaign), optionally reduced to one building (unknown id: one-line error)."""
    from lidarmap.store import MapStore

    with MapStore.open(map_path) as store:
        building_map = store.load(as_of=as_of)
    if building is not None:
        if building not in building_map.buildings:
            known = ", ".join(list(building_map.buildings)[:10]) or "none"
            raise InputError(f"no building {building!r} in this map (buildings: {known})", map_path)
        building_map.buildings = {building: building_map.buildings[building]}
    return building_map


def _state(building_map: BuildingMap, as_of: int | None) -> str:
    if not building_map.campaigns:
        return "no campaigns yet"
    return f"as of campaign {as_of if as_of is not None else building_map.campaigns[-1].campaign_id}"


def _ids(values: list[int]) -> str:
    return ",".join(str(v) for v in values) or "–"


def _epsilon(value: float) -> str:
    return "∞" if value == float("inf") else f"{value:.3f}"


def _buildings_table(building_map: BuildingMap, title: str) -> Table:
    from lidarmap.export.summary import count_buildings

    table = Table(title=title, title_justify="left")
    for column in ("building", "footprint m²", "façades", "roofs", "windows", "doors", "structures", "unknown"):
        table.add_column(column, justify="left" if column == "building" else "right")
    for bid, b in building_map.buildings.items():
        k = count_buildings([b])
        table.add_row(bid, f"{b.footprint.area:.1f}", *(str(k[c]) for c in
                                                          ("facades", "roofs", "windows", "doors", "structures",
                                                           "unknown")))
    return table


def _facades_table(building_map: BuildingMap) -> Table:
    table = Table(title="façades (normal n, plane n·x + offset = 0, σ of the main layer)", title_justify="left")
    for column in ("building", "façade", "normal (x, y)", "offset m", "σ cm", "extent m", "layers (μ cm, σ cm, w)",
                   "points", "campaigns"):
        table.add_column(column, justify="left" if column in ("building", "layers (μ cm, σ cm, w)") else "right")
    for bid, b in building_map.buildings.items():
        for f in b.facades:
            n = f.frame.normal
            s0, s1, t0, t1 = f.extent
            layers = "\n".join(f"{'*' if la.layer_id == f.main_layer else ' '}{la.layer_id}: {la.mu * 100:+.1f}, "
                               f"{la.sigma * 100:.1f}, {la.weight:.2f}" for la in f.layers) or "–"
            table.add_row(bid, str(f.facade_id), f"{n[0]:+.3f}, {n[1]:+.3f}", f"{f.frame.offset:.3f}",
                          f"{f.sigma * 100:.2f}", f"{s1 - s0:.2f} × {t1 - t0:.2f}", layers, f"{f.n_points:,}",
                          _ids(f.campaigns))
    return table


def _elements_table(building_map: BuildingMap, limit: int | None) -> tuple[Table, int]:
    from lidarmap.export.summary import element_class

    table = Table(title="elements (ε: uncertainty, eq. 1-3; ∞ = unknown)", title_justify="left")
    for column in ("building", "façade", "element", "kind", "layer", "ε", "area m²", "s m", "t m", "points",
                   "campaigns"):
        table.add_column(column, justify="left" if column in ("building", "kind") else "right")
    rows = [(bid, f, e) for bid, b in building_map.buildings.items() for f in b.facades for e in f.elements]
    for bid, f, e in rows[:limit]:
        x0, y0, x1, y1 = e.polygon.bounds
        table.add_row(bid, str(f.facade_id), str(e.element_id), element_class(e).rstrip("s"),
                      "–" if e.layer_id is None else str(e.layer_id), _epsilon(e.uncertainty), f"{e.polygon.area:.2f}",
                      f"{x0:.2f}–{x1:.2f}", f"{y0:.2f}–{y1:.2f}", f"{e.n_points:,}", _ids(e.campaigns))
    return table, len(rows)


@handle_errors
def show_command(map_path: Path = MapArgument, building: Optional[str] = BuildingOption,
                 as_of: Optional[int] = AsOfOption) -> None:
    """Tables of the map: buildings, façades (plane, σ, extent, layers), elements (kind, layer, ε, area)."""
    from pyproj import CRS

    building_map = load_map(map_path, as_of, building)
    crs = CRS.from_user_input(building_map.crs_wkt).name if building_map.crs_wkt else "unknown CRS"
    title = f"{map_path.name}: {_state(building_map, as_of)}, {crs}"
    out = table_console()
    out.print(_buildings_table(building_map, title))
    out.print(_facades_table(building_map))
    table, total = _elements_table(building_map, None if building else SHOW_ELEMENTS)
    out.print(table)
    if total > SHOW_ELEMENTS and building is None:
        out.print(f"… {total - SHOW_ELEMENTS} more elements (use --building ID)")


@handle_errors
def history_command(map_path: Path = MapArgument) -> None:
    """One row per campaign: what it was and what it changed (added ~updated -removed per entity)."""
    from lidarmap.store import ENTITIES, MapStore

    with MapStore.open(map_path) as store:
        history = store.history()
    table = Table(title=f"{map_path.name}: {len(history)} campaign(s)", title_justify="left")
    for column in ("campaign", "kind", "source", "points", "created", "changes", "map after it"):
        table.add_column(column, justify="right" if column in ("campaign", "points") else "left")
    for campaign, changes in history:
        text = " · ".join(f"{e} +{c['added']} ~{c['updated']} -{c['removed']}" for e in ENTITIES
                          for c in [changes.get(e, {"added": 0, "updated": 0, "removed": 0})] if any(c.values()))
        s = campaign.summary
        after = ", ".join(f"{s[k]} {k}" for k in ("buildings", "facades", "windows", "doors", "structures", "unknown",
                                                  "roofs") if k in s)
        table.add_row(str(campaign.campaign_id), campaign.kind, campaign.source, f"{campaign.n_points:,}",
                      campaign.created[:19], text or "nothing", after)
    table_console().print(table)


@handle_errors
def export_command(map_path: Path = MapArgument,
                   out: Path = typer.Option(..., "--output", "-o", help="CityJSON file to write (e.g. city.city.json).",
                                            dir_okay=False),
                   as_of: Optional[int] = AsOfOption) -> None:
    """Write the map as CityJSON 2.0: Window/Door surfaces under their WallSurface, uncertainties as attributes."""
    from lidarmap.export.cityjson import map_to_cityjson, write_cityjson
    from lidarmap.export.summary import count_map

    building_map = load_map(map_path, as_of)
    doc = map_to_cityjson(building_map, title=f"{map_path.stem} ({_state(building_map, as_of)})")
    write_cityjson(out, doc)
    k = count_map(building_map)
    table_console().print(f"wrote {out} (CityJSON 2.0, {_state(building_map, as_of)}): {k['buildings']} buildings, "
                  f"{k['facades']} façades, {k['windows']} windows, {k['doors']} doors, {k['unknown']} unknown "
                  f"regions, {len(doc['vertices']):,} vertices")


@handle_errors
def render_command(map_path: Path = MapArgument,
                   out_dir: Path = typer.Option(..., "--output", "-o", help="Folder for the PNGs (created).",
                                                file_okay=False),
                   as_of: Optional[int] = AsOfOption, building: Optional[str] = BuildingOption,
                   width: int = typer.Option(1200, "--width", min=300, max=8000, help="Image width in pixels.")) -> None:
    """One PNG per façade (paper Fig. 10): layers coloured, windows red with ε, unknown regions white."""
    from lidarmap.export.render import render_map

    building_map = load_map(map_path, as_of, building)
    with progress() as bar:
        task = bar.add_task("rendering façades", total=None)
        written = render_map(building_map, out_dir, width_px=width,
                             progress=lambda done, total: bar.update(task, completed=done, total=total))
    table_console().print(f"wrote {len(written)} façade image(s) to {out_dir} ({_state(building_map, as_of)})")


map_app.command("update")(update_command)
map_app.command("show")(show_command)
map_app.command("history")(history_command)
map_app.command("export")(export_command)
map_app.command("render")(render_command)
