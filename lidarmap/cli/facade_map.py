"""``lidarmap map ...``: the persistent façade map, refined campaign by campaign (docs/map.md).

::

    lidarmap map update MAP --points MLS.laz --trajectory T.csv --footprints F.geojson   # a mobile campaign
    lidarmap map update MAP --points MLS.ply [--columns ...] [--crs EPSG:N] [-f F]      # PLY/XYZ (docs/mls.md)
    lidarmap map update MAP --aerial ALS.laz [--footprints F.geojson]                    # roof planes
    lidarmap map show MAP [--building ID] [--as-of N]
    lidarmap map history MAP
    lidarmap map export MAP -o city.city.json [--as-of N]
    lidarmap map render MAP -o renders/ [--as-of N] [--building ID]

``update`` holds the map's writer lock from start to end, refuses a campaign whose files were applied before (same
bytes: :func:`lidarmap.map.store.campaign_fingerprint`) before reading them, and writes the new state in one
transaction; a map that does not exist yet is created (in the points' CRS) only when the first campaign commits.
Heavy modules are imported inside the commands so that ``lidarmap --help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import typer
from rich.markup import escape
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    CrsOption,
    IdFieldOption,
    JsonOption,
    SeedOption,
    echo_json,
    handle_errors,
    json_mode,
    params_from,
    progress,
    table_console,
)
from lidarmap.errors import ConfigError, InputError

if TYPE_CHECKING:
    from lidarmap.map.apply import UpdateResult
    from lidarmap.map.model import BuildingMap

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


def stage_params(config: Path | None) -> tuple[Any, Any]:
    """FacadeParams (``[facade]``) and RefineParams (``[refine]``) from the config file; errors name the file."""
    from lidarmap.facade.params import FacadeParams
    from lidarmap.map.refine import RefineParams

    try:
        return params_from(FacadeParams, config), params_from(RefineParams, config)
    except ConfigError as exc:
        if exc.path is None and config is not None:
            raise ConfigError(exc.problem, config) from None
        raise


def update_params(config: Path | None, workers: int | None = None, scheduler: str | None = None) -> Any:
    """UpdateParams (``[update]``) from the config file, ``--workers`` / ``--scheduler`` overriding it."""
    from lidarmap.map.update import UpdateParams

    return params_from(UpdateParams, config, workers=workers, scheduler=scheduler)


def mls_params(config: Path | None) -> tuple[Any, Any]:
    """SensorParams (``[sensors]``) and DiscoverParams (``[discover]``): campaigns without trajectory file or
    footprints (docs/mls.md)."""
    from lidarmap.facade.discover import DiscoverParams
    from lidarmap.facade.sensors import SensorParams

    return params_from(SensorParams, config), params_from(DiscoverParams, config)


_UPDATE_STEPS = ("fingerprint", "reading points", "reading footprints", "refining the map", "committing")


@handle_errors
def update_command(
    map_path: Path = MapArgument,
    points: Optional[Path] = typer.Option(None, "--points", help="Mobile campaign points: LAS/LAZ, PLY or text "
                                          "(.xyz/.txt/.csv); see docs/mls.md.", dir_okay=False),
    trajectory: Optional[Path] = typer.Option(None, "--trajectory", help="Trajectory CSV of the mobile campaign "
                                              "(the points need GPS time); without it the points' sensor origins "
                                              "or a path estimated from the cloud.", dir_okay=False),
    aerial: Optional[Path] = typer.Option(None, "--aerial", help="Aerial scan (LAS/LAZ): adds roof planes.",
                                          dir_okay=False),
    footprints: Optional[Path] = typer.Option(None, "--footprints", "-f", help="Building footprints (GeoJSON; "
                                              "GeoPackage/Shapefile/FlatGeobuf with the gis extra); optional with "
                                              "--aerial (default: the map's buildings).", dir_okay=False),
    id_field: Optional[str] = IdFieldOption,
    crs: Optional[str] = CrsOption,
    columns: Optional[str] = typer.Option(None, "--columns", help="Columns of a text point file, e.g. "
                                          "x,y,z,intensity,gps_time ('_' skips one); default: its header line."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes for the buildings of a mobile "
                                          "campaign (dask LocalCluster; default 1: this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address for multi-machine "
                                            "updates, e.g. tcp://10.0.0.5:8786."),
    seed: Optional[int] = SeedOption,
    config: Optional[Path] = ConfigOption,
    json_output: bool = JsonOption,
) -> None:
    """Fuse one campaign into the map (created if missing): façades, layers, windows, doors, occlusions or roofs."""
    from lidarmap.map.apply import apply_campaign, campaign_inputs

    json_mode(json_output)
    inputs = campaign_inputs(points, trajectory, aerial, footprints, id_field, crs, columns)
    params = stage_params(config)
    update = update_params(config, workers, scheduler)
    with progress(transient=True) as bar:
        task = bar.add_task("map update", total=len(_UPDATE_STEPS))

        def step(name: str) -> None:
            bar.update(task, description=name, completed=_UPDATE_STEPS.index(name))

        def buildings(done: int, total: int) -> None:
            bar.update(task, description=f"refining the map ({done}/{total} buildings)")

        result = apply_campaign(map_path, inputs, params, 0 if seed is None else seed, step, update, buildings,
                                *mls_params(config))
    if json_output:
        echo_json({"map": str(map_path), "campaign": _campaign_json(result.campaign), "counts": result.counts,
                   "changes": result.changes, "failed": result.failed, "seconds": round(result.seconds, 3)})
    else:
        _print_update(map_path, result)


def _campaign_json(campaign: Any) -> dict[str, Any]:
    import dataclasses

    return dataclasses.asdict(campaign)


def _change_text(change: dict[str, int]) -> tuple[str, str, str]:
    return tuple(str(change.get(k, 0)) for k in ("added", "updated", "removed"))  # type: ignore[return-value]


def _print_update(map_path: Path, result: UpdateResult) -> None:
    from lidarmap.map.store import ENTITIES

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
    from lidarmap.map.store import MapStore

    with MapStore.open(map_path, readonly=True) as store:
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


def _show_json(building_map: BuildingMap, map_path: Path, as_of: int | None, crs: str) -> dict[str, Any]:
    """``map show --json``: the same rows as the tables, as one object (numbers unrounded, ε ∞ as null)."""
    from lidarmap.export.summary import element_class

    def facade(f: Any) -> dict[str, Any]:
        return {"facade": f.facade_id, "normal": [float(v) for v in f.frame.normal[:2]], "offset": f.frame.offset,
                "sigma": f.sigma, "extent": list(f.extent), "main_layer": f.main_layer, "points": f.n_points,
                "campaigns": list(f.campaigns),
                "layers": [{"layer": la.layer_id, "mu": la.mu, "sigma": la.sigma, "weight": la.weight}
                           for la in f.layers],
                "elements": [{"element": e.element_id, "kind": element_class(e).rstrip("s"), "layer": e.layer_id,
                              "uncertainty": None if e.uncertainty == float("inf") else e.uncertainty,
                              "area": e.polygon.area, "bounds": list(e.polygon.bounds), "points": e.n_points,
                              "campaigns": list(e.campaigns)} for e in f.elements]}

    return {"map": str(map_path), "state": _state(building_map, as_of), "crs": crs,
            "buildings": [{"id": bid, "footprint_area": b.footprint.area, "roofs": len(b.roofs),
                           "facades": [facade(f) for f in b.facades]} for bid, b in building_map.buildings.items()]}


@handle_errors
def show_command(map_path: Path = MapArgument, building: Optional[str] = BuildingOption,
                 as_of: Optional[int] = AsOfOption, json_output: bool = JsonOption) -> None:
    """Tables of the map: buildings, façades (plane, σ, extent, layers), elements (kind, layer, ε, area)."""
    from pyproj import CRS

    building_map = load_map(map_path, as_of, building)
    crs = CRS.from_user_input(building_map.crs_wkt).name if building_map.crs_wkt else "unknown CRS"
    if json_output:
        echo_json(_show_json(building_map, map_path, as_of, crs))
        return
    title = f"{map_path.name}: {_state(building_map, as_of)}, {crs}"
    out = table_console()
    out.print(_buildings_table(building_map, title))
    out.print(_facades_table(building_map))
    table, total = _elements_table(building_map, None if building else SHOW_ELEMENTS)
    out.print(table)
    if total > SHOW_ELEMENTS and building is None:
        out.print(f"… {total - SHOW_ELEMENTS} more elements (use --building ID)")


@handle_errors
def history_command(map_path: Path = MapArgument, json_output: bool = JsonOption) -> None:
    """One row per campaign: what it was and what it changed (added ~updated -removed per entity)."""
    from lidarmap.map.store import ENTITIES, MapStore

    with MapStore.open(map_path, readonly=True) as store:
        history = store.history()
    if json_output:
        echo_json({"map": str(map_path), "campaigns": [{**_campaign_json(c), "changes": changes}
                                                        for c, changes in history]})
        return
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
                   out: Path = typer.Option(..., "--output", "-o", help="File to write: CityJSON (e.g. city.city.json) or glTF "
                             "binary for viewers (a name ending .glb).",
                                            dir_okay=False),
                   as_of: Optional[int] = AsOfOption) -> None:
    """Write the map as CityJSON 2.0 (Window/Door surfaces under their WallSurface, uncertainties as attributes) or,
    for a .glb name, as glTF 2.0 for viewers."""
    from lidarmap.export.cityjson import map_to_cityjson, write_cityjson
    from lidarmap.export.summary import count_map

    building_map = load_map(map_path, as_of)
    if out.suffix.lower() == ".glb":
        from lidarmap.export.gltf import glb_building_ids, map_to_glb
        from lidarmap.io.atomic import write_bytes_atomic

        data = write_bytes_atomic(out, map_to_glb(building_map, f"{map_path.stem} ({_state(building_map, as_of)})"))
        return table_console().print(f"wrote {out} (glTF 2.0, {_state(building_map, as_of)}): "
                                     f"{len(glb_building_ids(data.read_bytes()))} buildings")
    doc = map_to_cityjson(building_map, title=f"{map_path.stem} ({_state(building_map, as_of)})")
    write_cityjson(out, doc)
    k = count_map(building_map)
    table_console().print(f"wrote {out} (CityJSON 2.0, {_state(building_map, as_of)}): {k['buildings']} buildings, "
                  f"{k['facades']} façades, {k['windows']} windows, {k['doors']} doors, {k['unknown']} unknown "
                  f"regions, {len(doc['vertices']):,} vertices")


#: Kind of the output-folder marker of ``map render`` (:mod:`lidarmap.io.outdir`).
RENDER_KIND = "render"


@handle_errors
def render_command(map_path: Path = MapArgument,
                   out_dir: Path = typer.Option(..., "--output", "-o", help="Folder for the PNGs (created; an "
                                                "empty folder or an earlier render, whose PNGs are replaced: files "
                                                "of yours there are never touched).", file_okay=False),
                   as_of: Optional[int] = AsOfOption, building: Optional[str] = BuildingOption,
                   width: int = typer.Option(1200, "--width", min=300, max=8000, help="Image width in pixels.")) -> None:
    """One PNG per façade (paper Fig. 10): layers coloured, windows red with ε, unknown regions white."""
    from lidarmap.export.render import render_map
    from lidarmap.io.outdir import atomic_out_dir, claim_out_dir

    claim_out_dir(out_dir, RENDER_KIND)  # before loading the map: a wrong folder is refused at once
    building_map = load_map(map_path, as_of, building)
    # rendered into a temporary folder published at the end: a failure leaves no PNGs behind; the folder holds
    # one render (replace=True), so PNGs of façades an earlier render had and this one has not are removed
    with atomic_out_dir(out_dir, RENDER_KIND, replace=True) as tmp, progress() as bar:
        task = bar.add_task("rendering façades", total=None)
        written = render_map(building_map, tmp, width_px=width,
                             progress=lambda done, total: bar.update(task, completed=done, total=total))
    table_console().print(f"wrote {len(written)} façade image(s) to {out_dir} ({_state(building_map, as_of)})")


map_app.command("update")(update_command)
map_app.command("show")(show_command)
map_app.command("history")(history_command)
map_app.command("export")(export_command)
map_app.command("render")(render_command)
