"""``lidarmap demo``: simulate a small city and run every stage on it, scored against the simulator's truth.

1. ``simulate``: a procedural city (aerial scan, mobile campaigns, footprints, truth) into ``OUT/city``;
2. ``run``: the aerial pipeline (prep, segmentation, densify, flatten, voxels, meshes, CityJSON) into ``OUT/aerial``,
   with segmentation accuracy and voxel IoU against the truth next to the naive baseline;
3. ``map update``: the façade map ``OUT/city.lmap`` from every mobile campaign in turn (refined, not rebuilt), and
   the roofs of the aerial scan, with the per-campaign table of window F1, IoU, plane offset, σ, unknown area, ε;
4. ``map export`` / ``map render`` / ``view``: ``OUT/city.city.json``, one PNG per façade in ``OUT/renders`` and
   the viewer page ``OUT/view.html``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    SeedOption,
    handle_errors,
    params_from,
    progress,
    table_console,
)

#: What a demo writes into its folder (listed in the folder's marker, :mod:`lidarmap.io.outdir`): a later demo
#: replaces these and nothing else.
DEMO_OUTPUTS = ("city", "aerial", "city.lmap", "city.lmap.lock", "city.city.json", "renders", "view.html")


def register(app: typer.Typer) -> None:
    """Add ``demo`` to the app."""
    app.command("demo")(demo_command)


@handle_errors
def demo_command(
    out: Path = typer.Option(Path("lidarmap-demo"), "--out", "-o", help="Output folder (a previous demo there is "
                             "replaced).", file_okay=False),
    seed: Optional[int] = SeedOption,
    buildings: Optional[int] = typer.Option(None, "--buildings", help="Buildings of the simulated city (default 8)."),
    campaigns: Optional[int] = typer.Option(None, "--campaigns", help="Mobile campaigns (default 3)."),
    config: Optional[Path] = ConfigOption,
) -> None:
    """Simulate a small city and run every stage on it: aerial reconstruction and the refined façade map."""
    from lidarmap.sim import SimParams

    started = time.perf_counter()
    sim_params = params_from(SimParams, config, seed=seed, buildings=buildings, campaigns=campaigns)
    _prepare(out)
    console = table_console()
    city = _simulate(out / "city", sim_params)
    console.rule("aerial pipeline (lidarmap run)")
    _aerial(out, city, config, sim_params.seed)
    if sim_params.campaigns:
        console.rule("façade map (lidarmap map update, one campaign after the other)")
        _facade_map(out, city, config, sim_params.seed)
    console.rule("outputs")
    _viewer_page(out)
    _outputs(out)
    console.print(f"demo done in {time.perf_counter() - started:.0f} s")


def _prepare(out: Path) -> None:
    """Refuse a folder that is neither empty nor an earlier demo; clear what an earlier demo wrote (only that)."""
    from lidarmap.io.outdir import claim_out_dir, remove_marked, start_marked_dir

    claim_out_dir(out, "demo", "demo output")
    remove_marked(out)
    start_marked_dir(out, "demo", DEMO_OUTPUTS)


def _simulate(city: Path, params: Any) -> Any:
    from lidarmap.sim import load_truth, simulate

    with progress() as bar:
        tasks: dict[str, int] = {}

        def report(task: str, done: int, total: int) -> None:
            if task not in tasks:
                tasks[task] = bar.add_task(f"simulating {task}", total=total)
            bar.update(tasks[task], completed=done, total=total)

        result = simulate(city, params, report)
    table_console().print(f"simulated a city of {params.buildings} buildings (+1 construction site): "
                          f"{result.als_points:,} aerial points, {len(result.mls)} mobile campaigns "
                          f"({sum(result.mls_points):,} points) in {result.seconds:.0f} s")
    return load_truth(city)


def _aerial(out: Path, truth: Any, config: Path | None, seed: int) -> None:
    from lidarmap.cli.aerial import (
        _pipeline_config,
        print_run_summary,
        run_with_progress,
    )

    city = truth.root
    cfg = _pipeline_config(config, stages=None, method=None, model=None, union=None, voxel_size=None, mesh=None,
                           workers=None, scheduler=None, id_field=None, seed=seed)
    result = run_with_progress([city / "als.laz"], city / "footprints.geojson", out / "aerial", cfg, None)
    print_run_summary(result)
    _aerial_scores(out / "aerial", truth, result, cfg)


def _aerial_scores(run_dir: Path, truth: Any, result: Any, cfg: Any) -> None:
    """Segmentation OA / building IoU and voxel IoU against the truth, next to the delivered labels / naive voxels."""
    from lidarmap.aerial.eval import score_building_voxels
    from lidarmap.aerial.pipeline import load_segmenter
    from lidarmap.io.footprints import read_footprints
    from lidarmap.io.las import read_las
    from lidarmap.io.voxels import read_voxels
    from lidarmap.segment.metrics import evaluate_classes
    from lidarmap.segment.predict import apply_classes, predict

    als = read_las(truth.als)
    true_classes = truth.labels("als").classification
    model, _ = load_segmenter(cfg.run)
    prob = predict(als, model, cfg.segment)
    predicted = apply_classes(als.attrs["classification"], prob, cfg.segment.threshold, cfg.run.union) == 6
    ours, delivered = evaluate_classes(true_classes, predicted), evaluate_classes(
        true_classes, als.attrs["classification"] == 6)
    walls = (true_classes == 6) & (als.attrs["classification"] != 6)
    table = Table(title="aerial results against the simulator's truth", title_justify="left")
    for column in ("", "overall accuracy", "building IoU", "recall of unlabelled building points"):
        table.add_column(column, justify="right" if column else "left")
    table.add_row("delivered classification", f"{delivered['overall_accuracy']:.3f}",
                  f"{delivered['iou']['building']:.3f}", "0.000")
    table.add_row(f"segmentation ({cfg.run.method}{', union' if cfg.run.union else ''})",
                  f"{ours['overall_accuracy']:.3f}", f"{ours['iou']['building']:.3f}",
                  f"{predicted[walls].mean():.3f}" if walls.any() else "-")
    fps = read_footprints(truth.root / "footprints.geojson", crs=als.crs)
    grids = {r["id"]: read_voxels(run_dir / "buildings" / r["id"] / "voxels.npz") for r in result.records}
    scores = score_building_voxels(grids, truth, als, fps, cfg.prep.buffer)
    console = table_console()
    console.print(table)
    if scores:
        ours_iou = float(np.mean([s["iou"] for s in scores.values()]))
        naive_iou = float(np.mean([s["naive_iou"] for s in scores.values()]))
        console.print(f"voxel IoU ({cfg.voxel.size:g} m) against the true buildings, mean of {len(scores)}: "
                      f"pipeline {ours_iou:.3f}, naive baseline (MinecraftUBC: labelled class 6 only) "
                      f"{naive_iou:.3f}")


def _facade_map(out: Path, truth: Any, config: Path | None, seed: int) -> None:
    from lidarmap.cli.facade_map import load_map, stage_params
    from lidarmap.export.cityjson import map_to_cityjson, write_cityjson
    from lidarmap.export.render import render_map
    from lidarmap.facade.eval import evaluate_facades, map_statistics
    from lidarmap.map.apply import apply_campaign, campaign_inputs

    map_path = out / "city.lmap"
    params = stage_params(config)
    footprints = truth.root / "footprints.geojson"
    table = Table(title=f"façade map {map_path} after each campaign (truth: the simulator)", title_justify="left")
    for column in ("campaign", "window F1", "matched IoU", "plane offset cm", "layer σ mm", "unknown m²",
                   "mean ε", "windows", "update s"):
        table.add_column(column, justify="right")
    seen: list[int] = []
    with progress() as bar:
        task = bar.add_task("updating the map", total=len(truth.campaigns))
        for campaign in truth.campaigns:
            inputs = campaign_inputs(campaign.laz, campaign.trajectory, None, footprints, None, None)
            update = apply_campaign(map_path, inputs, params, seed)
            seen.append(campaign.id)
            buildings = list(load_map(map_path, None).buildings.values())
            score = evaluate_facades(buildings, truth, campaign.id, campaigns=seen)
            stats = map_statistics(buildings)
            table.add_row(str(update.campaign.campaign_id), f"{score['window']['f1']:.3f}",
                          _fmt(score["window_mean_iou"]), _fmt(100 * score["offset_mean"], 2),
                          _fmt(1000 * stats["sigma_mean"], 2), f"{stats['unknown_area']:.1f}",
                          _fmt(stats["mean_uncertainty"]), str(stats["windows"]), f"{update.seconds:.1f}")
            bar.advance(task)
        aerial = apply_campaign(map_path, campaign_inputs(None, None, truth.als, footprints, None, None), params, seed)
    console = table_console()
    console.print(table)
    building_map = load_map(map_path, None)
    roofs = sum(len(b.roofs) for b in building_map.buildings.values())
    console.print(f"aerial scan added as campaign {aerial.campaign.campaign_id}: {roofs} roof planes on "
                  f"{sum(1 for b in building_map.buildings.values() if b.roofs)} buildings")
    write_cityjson(out / "city.city.json", map_to_cityjson(building_map))
    render_map(building_map, out / "renders")


def _viewer_page(out: Path) -> None:
    """``OUT/view.html``: the façade map in 3D (the aerial run without campaigns); prints its path."""
    from lidarmap.cli.view import view_command

    source = out / "city.lmap" if (out / "city.lmap").is_file() else out / "aerial"
    view_command(source, out / "view.html", None)
    table_console().print(f"viewer page: {(out / 'view.html').resolve()}")


def _fmt(value: float, digits: int = 3) -> str:
    return f"{value:.{digits}f}" if value is not None and math.isfinite(value) else "-"


def _outputs(out: Path) -> None:
    rows = [
        ("city/", "simulated data: als.laz, mls_<i>.laz, trajectory_<i>.csv, footprints.geojson, truth/"),
        ("aerial/buildings/<id>/", "points.laz, voxels.npz/.vox, mesh.ply/.obj (CRS, double precision)"),
        ("aerial/buildings.city.json", "CityJSON 2.0: LoD1 blocks + LoD2.2 planar faces, footprint coverage"),
        ("aerial/buildings.glb", "glTF 2.0 of the meshes (local origin) for viewers"),
        ("city.lmap", "the façade map (SQLite; try `lidarmap map show` / `map history`)"),
        ("city.city.json", "CityJSON 2.0 of the map: LoD 3 walls with windows/doors, LoD 2, roofs, uncertainties"),
        ("view.html", "3D viewer page of the map (self-contained: open it in a browser)"),
        ("renders/", "one PNG per façade: layers, windows (red, with ε), unknown regions (white)"),
    ]
    table = Table(show_header=False)
    table.add_column("where", style="bold")
    table.add_column("what")
    for where, what in rows:
        if (out / where.split("<")[0].rstrip("/")).exists():
            table.add_row(str(out / where), what)
    table_console().print(table)
