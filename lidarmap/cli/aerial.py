"""The aerial reconstruction commands: ``densify``, ``flatten``, ``voxelize``, ``mesh`` (one stage each, on LAS/LAZ
files of segmented buildings) and ``run`` (the whole pipeline from tiles + footprints). See docs/pipeline.md.

The stage commands work on the class-6 (building) points of each input, e.g. the ``points.laz`` of a building, the
output of ``lidarmap segment predict`` or of another stage command, and write one output per input into ``-o DIR``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, Optional

import typer
from rich.markup import escape
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    CrsOption,
    FootprintsOption,
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

InputsArgument = typer.Argument(..., help="LAS/LAZ files (their class-6 points are the building).")
OutOption = typer.Option(..., "--out", "-o", help="Output folder (created; an empty folder or an earlier output of "
                         "the same command: files of yours there are never replaced).", file_okay=False)


def register(app: typer.Typer) -> None:
    """Add densify, flatten, voxelize, mesh and run to the app."""
    app.command("densify")(densify_command)
    app.command("flatten")(flatten_command)
    app.command("voxelize")(voxelize_command)
    app.command("mesh")(mesh_command)
    app.command("run")(run_command)


def _check_inputs(paths: list[Path]) -> None:
    seen: set[Path] = set()
    for path in paths:
        if not path.exists():
            raise InputError("file not found", path)
        if path.resolve() in seen:
            raise InputError("input given twice", path)
        seen.add(path.resolve())


def output_stem(path: Path) -> str:
    """The name an input's outputs start with: its file name without ``.laz``/``.las``/``.voxels.npz``."""
    name = path.name
    return name.removesuffix(".voxels.npz") if name.endswith(".voxels.npz") else path.stem


def _check_stems(paths: list[Path]) -> None:
    """Refuse inputs whose outputs would have the same name (``A/points.laz`` and ``B/points.laz``: the second
    would replace the first), naming both."""
    seen: dict[str, Path] = {}
    for path in paths:
        stem = output_stem(path).lower()
        if stem in seen:
            raise InputError(f"{seen[stem]} and {path} would write outputs of the same name "
                             f"'{output_stem(path)}'; rename one or run them into separate -o folders")
        seen[stem] = path


def _each(paths: list[Path], description: str, work: Callable[[Path, Path], Any], out_dir: Path,
          kind: str) -> list[Any]:
    """Run ``work(input, output_prefix)`` on every input under a progress bar; results in input order.

    Outputs go to a temporary folder published into ``out_dir`` at the end (:func:`lidarmap.io.outdir.atomic_out_dir`):
    an error leaves ``out_dir`` as it was; files of the user's there are never replaced.
    """
    from lidarmap.io.outdir import atomic_out_dir

    _check_inputs(paths)
    _check_stems(paths)
    results = []
    with atomic_out_dir(out_dir, kind, replace=False) as tmp, progress() as bar:
        task = bar.add_task(description, total=len(paths))
        for path in paths:
            results.append(work(path, tmp / output_stem(path)))
            bar.advance(task)
    return results


def _read_building_points(path: Path, crs: str | None, min_points: int = 3):
    from lidarmap.aerial.pipeline import building_mask
    from lidarmap.io.las import read_las

    cloud = read_las(path, crs=crs)
    n = int(building_mask(cloud).sum())
    if n < min_points:
        raise InputError(f"only {n} building (class 6) points; need at least {min_points} "
                         "(segment the file first: lidarmap segment predict)", path)
    return cloud


def _table(title: str, columns: list[str], rows: list[list[Any]]) -> None:
    table = Table(title=title, title_justify="left")
    for i, column in enumerate(columns):
        table.add_column(column, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*[f"{v:,}" if isinstance(v, int) else f"{v:.3g}" if isinstance(v, float) else str(v)
                        for v in row])
    table_console().print(table)


# ----------------------------------------------------------------------------------------------------------------------
# densify / flatten


@handle_errors
def densify_command(
    inputs: list[Path] = InputsArgument,
    out_dir: Path = OutOption,
    ratio: Optional[float] = typer.Option(None, "--ratio", help="Output / input building points (default 2)."),
    distribution: Optional[str] = typer.Option(None, "--distribution", help="uniform (default: sparse surfaces "
                                               "filled first) or proportional (ratio - 1 new points per point)."),
    upsampler: Optional[str] = typer.Option(None, "--upsampler", help="geometric (default) or learned."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Weights of the learned upsampler (default: "
                                           "shipped)."),
    halo: Optional[float] = typer.Option(None, "--halo", help="Overlap (m) of the median-split leaves (default 2)."),
    max_leaf: Optional[int] = typer.Option(None, "--max-leaf", help="Leaves below this many points are upsampled "
                                           "(default 5000)."),
    min_leaf: Optional[int] = typer.Option(None, "--min-leaf", help="Leaves below this are kept as they are "
                                           "(default 100)."),
    crs: Optional[str] = CrsOption,
    seed: Optional[int] = SeedOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Densify the building points: input points kept (outliers become class 7), new points appended (class 6, LAS
    synthetic flag), colour carried over by inverse-distance-weighted neighbours."""
    from lidarmap.aerial.densify import DensifyParams
    from lidarmap.aerial.pipeline import densify_cloud
    from lidarmap.io.las import write_las

    params = params_from(DensifyParams, config, ratio=ratio, distribution=distribution, upsampler=upsampler,
                         weights=None if weights is None else str(weights), halo=halo, max_leaf=max_leaf,
                         min_leaf=min_leaf)

    def work(path: Path, prefix: Path) -> list[Any]:
        cloud = _read_building_points(path, crs)
        dense, stats = densify_cloud(cloud, params, seed or 0)
        write_las(prefix.with_name(f"{prefix.name}.laz"), dense)
        return [path.name, len(cloud), stats["outliers_removed"], stats["new_points"], len(dense)]

    rows = _each(inputs, "densifying", work, out_dir, "densify")
    _table(f"densified into {out_dir}", ["file", "points in", "outliers", "new points", "points out"], rows)


@handle_errors
def flatten_command(
    inputs: list[Path] = InputsArgument,
    out_dir: Path = OutOption,
    method: Optional[str] = typer.Option(None, "--method", help="region (default) or paper (Algorithm 2)."),
    distance: Optional[float] = typer.Option(None, "--distance", help="Inlier distance to a plane (m, default "
                                             "0.08)."),
    min_points: Optional[int] = typer.Option(None, "--min-points", help="Planes with fewer points are not kept "
                                             "(default 30)."),
    regularise: Optional[bool] = typer.Option(None, "--regularise/--no-regularise", help="Make near-vertical "
                                              "planes vertical, snap walls to the main axes (default on)."),
    crs: Optional[str] = CrsOption,
    seed: Optional[int] = SeedOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Detect planes in the building points and move their points onto them (extra dimension plane_id); writes
    <name>.laz and <name>.planes.json (normal, offset, rms, points of every plane)."""
    from lidarmap.aerial.flatten import FlattenParams
    from lidarmap.aerial.pipeline import flatten_cloud
    from lidarmap.io.atomic import write_text_atomic
    from lidarmap.io.las import write_las

    params = params_from(FlattenParams, config, method=method, distance=distance, min_points=min_points,
                         regularise=regularise)

    def work(path: Path, prefix: Path) -> list[Any]:
        cloud = _read_building_points(path, crs)
        flat, stats = flatten_cloud(cloud, params, seed or 0)
        write_las(prefix.with_name(f"{prefix.name}.laz"), flat)
        write_text_atomic(prefix.with_name(f"{prefix.name}.planes.json"), json.dumps(stats["plane_list"], indent=1))
        return [path.name, int((flat.attrs["classification"] == 6).sum()), stats["planes"],
                stats["planar_share"], stats["mean_move"]]

    rows = _each(inputs, "flattening", work, out_dir, "flatten")
    _table(f"flattened into {out_dir}", ["file", "building points", "planes", "on a plane", "mean move (m)"], rows)


# ----------------------------------------------------------------------------------------------------------------------
# voxelize / mesh


@handle_errors
def voxelize_command(
    inputs: list[Path] = InputsArgument,
    out_dir: Path = OutOption,
    size: Optional[float] = typer.Option(None, "--size", help="Voxel size (m, default 1)."),
    min_points: Optional[int] = typer.Option(None, "--min-points", help="Voxels with fewer points are dropped "
                                             "(default 1)."),
    naive: bool = typer.Option(False, "--naive", help="The MinecraftUBC baseline instead: class-6 points only, "
                               "floor truncation, voxels with one point dropped, median class."),
    vox: bool = typer.Option(True, "--vox/--no-vox", help="Also write MagicaVoxel <name>.vox."),
    ply: bool = typer.Option(False, "--ply", help="Also write <name>.cubes.ply (one cube per voxel)."),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Building voxels with the true majority label (building vs the rest, noise left out) and mean colour:
    <name>.voxels.npz (voxel size, origin and CRS kept; docs/voxel_mesh.md), .vox, .cubes.ply."""
    from lidarmap.aerial.pipeline import building_voxels
    from lidarmap.aerial.voxel import VoxelParams, voxelize_naive
    from lidarmap.io.las import read_las
    from lidarmap.io.voxels import write_vox, write_voxel_ply, write_voxels

    params = params_from(VoxelParams, config, size=size, min_points=min_points)

    def work(path: Path, prefix: Path) -> list[Any]:
        cloud = read_las(path, crs=crs)
        if "classification" not in cloud.attrs:
            raise InputError("the points have no classification", path)
        if naive:
            grid = voxelize_naive(cloud.xyz, cloud.attrs["classification"], cloud.rgb8(), params.size, crs=cloud.crs)
        else:
            grid = building_voxels(cloud, params)
        write_voxels(prefix.with_name(f"{prefix.name}.voxels.npz"), grid)
        if vox and len(grid.ijk):
            write_vox(prefix.with_name(f"{prefix.name}.vox"), grid)
        if ply and len(grid.ijk):
            write_voxel_ply(prefix.with_name(f"{prefix.name}.cubes.ply"), grid)
        return [path.name, len(cloud), len(grid.ijk), grid.size]

    rows = _each(inputs, "voxelizing", work, out_dir, "voxelize")
    _table(f"voxels in {out_dir}" + (" (naive baseline)" if naive else ""), ["file", "points", "voxels", "size"],
           rows)


@handle_errors
def mesh_command(
    inputs: list[Path] = typer.Argument(..., help="LAS/LAZ files (class-6 points) or voxel files (.voxels.npz)."),
    out_dir: Path = OutOption,
    method: str = typer.Option("surface", "--method", help="surface (2.5D reconstruction from points), voxels "
                               "(watertight voxel mesh) or both."),
    size: Optional[float] = typer.Option(None, "--size", help="Voxel size (m) of voxel meshes made from points "
                                         "(default 0.5)."),
    footprints: Optional[Path] = typer.Option(None, "--footprints", "-f", help="Footprints (GeoJSON): each "
                                              "input's outline is the footprint holding most of its points."),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Meshes of buildings in the input CRS with double-precision coordinates: <name>.ply and <name>.obj (method
    surface or voxels), or <name>.surface.* and <name>.voxels.* (both)."""
    from lidarmap.aerial.mesh import MeshParams

    if method not in ("surface", "voxels", "both"):
        raise ConfigError(f"unknown --method {method!r} (known: surface, voxels, both)")
    params = params_from(MeshParams, config)
    kinds = ["surface", "voxels"] if method == "both" else [method]
    fps = None
    if footprints is not None:
        from lidarmap.io.footprints import read_footprints

        fps = read_footprints(footprints)

    def work(path: Path, prefix: Path) -> list[Any]:
        from lidarmap.io.meshfile import write_mesh

        meshes = _meshes_of(path, kinds, params, size or 0.5, fps, crs)
        for kind, mesh in meshes.items():
            name = prefix.name if len(meshes) == 1 else f"{prefix.name}.{kind}"
            crs_of = mesh.metadata.get("crs")  # the input's: the PLY header and a .prj sidecar name it
            write_mesh(prefix.with_name(f"{name}.ply"), mesh, crs_of)
            write_mesh(prefix.with_name(f"{name}.obj"), mesh, crs_of)
        return [[path.name, kind, len(m.faces), "yes" if m.is_watertight else "no"] for kind, m in meshes.items()]

    rows = [row for rows in _each(inputs, "meshing", work, out_dir, "mesh") for row in rows]
    _table(f"meshes in {out_dir}", ["input", "mesh", "triangles", "watertight"], rows)


def _meshes_of(path: Path, kinds: list[str], params: Any, size: float, fps: Any, crs: str | None) -> dict[str, Any]:
    """Meshes of one input: a voxel file gives a voxel mesh; points give either kind."""
    import dataclasses

    from lidarmap.aerial.mesh import surface_mesh, voxel_mesh
    from lidarmap.aerial.pipeline import building_mask
    from lidarmap.aerial.voxel import VoxelParams, voxelize
    from lidarmap.io.voxels import read_voxels

    if path.name.endswith(".npz"):
        if kinds != ["voxels"]:
            raise ConfigError("a voxel file gives only a voxel mesh: use --method voxels", path)
        grid = read_voxels(path)
        return _with_crs({"voxels": voxel_mesh(grid, params)}, grid.crs)
    cloud = _read_building_points(path, crs)
    building = building_mask(cloud)
    xyz = cloud.xyz[building]
    rgb = cloud.rgb8()
    rgb = None if rgb is None else rgb[building]
    out = {}
    if "surface" in kinds:
        footprint = None
        if fps is not None:
            fps_here = fps.to_crs(cloud.crs) if cloud.crs is not None else fps
            footprint = _footprint_of(xyz, fps_here, path)
        out["surface"] = surface_mesh(xyz, params, footprint=footprint, rgb=rgb)
    if "voxels" in kinds:
        grid = voxelize(xyz, None, rgb, dataclasses.replace(VoxelParams(), size=size), crs=cloud.crs)
        out["voxels"] = voxel_mesh(grid, params)
    return _with_crs(out, cloud.crs)


def _with_crs(meshes: dict[str, Any], crs: Any) -> dict[str, Any]:
    """Meshes with their CRS in ``metadata["crs"]`` (None when unknown)."""
    for mesh in meshes.values():
        mesh.metadata["crs"] = crs
    return meshes


def _footprint_of(xyz: Any, fps: Any, path: Path) -> Any:
    import numpy as np
    import shapely

    counts = [int(shapely.contains_xy(poly, xyz[:, 0], xyz[:, 1]).sum()) for poly in fps.polygons]
    best = int(np.argmax(counts))
    if counts[best] == 0:
        raise InputError("no footprint contains any of the building points (wrong footprints file or CRS?)", path)
    return fps.polygons[best]


# ----------------------------------------------------------------------------------------------------------------------
# run


@handle_errors
def run_command(
    tiles: list[Path] = typer.Argument(..., help="LAS/LAZ tiles (merged while streaming)."),
    footprints: Path = FootprintsOption,
    out_dir: Path = typer.Option(..., "--out", "-o", help="Output folder; an earlier run there is resumed "
                                 "(finished buildings are skipped).", file_okay=False),
    stages: Optional[str] = typer.Option(None, "--stages", help="Stages after segmentation, in order, e.g. "
                                         "'densify,flatten' (default), 'flatten,densify', 'flatten' or 'none'."),
    method: Optional[str] = typer.Option(None, "--method", help="Segmentation: pointnet2 (default) or baseline."),
    model: Optional[Path] = typer.Option(None, "--model", help="Segmentation model file (default: shipped)."),
    union: Optional[bool] = typer.Option(None, "--union/--no-union", help="Keep input class-6 points as building "
                                         "(default on)."),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="Voxel size of the voxel output (m, "
                                               "default 1)."),
    mesh: Optional[str] = typer.Option(None, "--mesh", help="Mesh written as mesh.ply/.obj: surface (default) or "
                                       "voxels."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (dask; default 1)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address for multi-machine "
                                            "runs, e.g. tcp://10.0.0.5:8786."),
    id_field: Optional[str] = IdFieldOption,
    crs: Optional[str] = CrsOption,
    seed: Optional[int] = SeedOption,
    config: Optional[Path] = ConfigOption,
    json_output: bool = JsonOption,
) -> None:
    """The whole aerial pipeline: prep -> segment -> densify/flatten -> voxelize -> mesh, per building, into
    OUT/buildings/<id>/ (points.laz, voxels.npz/.vox, mesh.ply/.obj), OUT/summary.json, OUT/buildings.city.json,
    OUT/buildings.gpkg (every footprint with its status, for a GIS)."""
    json_mode(json_output)
    pipeline_config = _pipeline_config(config, stages=stages, method=method, model=model, union=union,
                                       voxel_size=voxel_size, mesh=mesh, workers=workers, scheduler=scheduler,
                                       id_field=id_field, seed=seed)
    result = run_with_progress(tiles, footprints, out_dir, pipeline_config, crs)
    if json_output:
        echo_json(run_json(result))
    else:
        print_run_summary(result)
    if not result.records:
        raise InputError("no building could be reconstructed (see the failures above)", footprints)


def _pipeline_config(config: Path | None, *, stages: str | None, method: str | None, model: Path | None,
                     union: bool | None, voxel_size: float | None, mesh: str | None, workers: int | None,
                     scheduler: str | None, id_field: str | None, seed: int | None) -> Any:
    from lidarmap.aerial.coverage import CoverageParams
    from lidarmap.aerial.densify import DensifyParams
    from lidarmap.aerial.flatten import FlattenParams
    from lidarmap.aerial.mesh import MeshParams
    from lidarmap.aerial.pipeline import PipelineConfig, RunParams, check_stage_names
    from lidarmap.aerial.prep import PrepParams
    from lidarmap.aerial.voxel import VoxelParams
    from lidarmap.export.planar import PlanarParams
    from lidarmap.segment.predict import PredictParams

    # params_from refuses tables no command knows (lidarmap.config.KNOWN_TABLES)
    return PipelineConfig(
        run=params_from(RunParams, config, stages=None if stages is None else check_stage_names(stages),
                        method=method, model=None if model is None else str(model), union=union, mesh=mesh,
                        workers=workers, scheduler=scheduler, seed=seed),
        prep=params_from(PrepParams, config, id_field=id_field),
        segment=params_from(PredictParams, config),
        densify=params_from(DensifyParams, config),
        flatten=params_from(FlattenParams, config),
        voxel=params_from(VoxelParams, config, size=voxel_size),
        mesh=params_from(MeshParams, config),
        coverage=params_from(CoverageParams, config),
        lod22=params_from(PlanarParams, config),
    )


def run_with_progress(tiles: list[Path], footprints: Path, out_dir: Path, pipeline_config: Any,
                      crs: str | None) -> Any:
    """``run_pipeline`` with a progress bar per step (shared with ``lidarmap demo``)."""
    from lidarmap.aerial.pipeline import check_out_dir, run_pipeline
    from lidarmap.io.footprints import read_footprints
    from lidarmap.io.tiles import scan_tiles

    check_out_dir(out_dir)
    fps = read_footprints(footprints, id_field=pipeline_config.prep.id_field)
    total = scan_tiles(tiles, crs).points
    with progress() as bar:
        tasks: dict[str, int] = {}
        names = {"read": "reading tiles", "segment": "segmenting", "buildings": "reconstructing buildings"}

        def report(step: str, done: int, total_steps: int) -> None:
            if step not in tasks:
                tasks[step] = bar.add_task(names[step], total=total if step == "read" else total_steps)
            if step == "read":
                bar.advance(tasks[step], done)
            else:
                bar.update(tasks[step], completed=done, total=total_steps)

        return run_pipeline(tiles, fps, out_dir, pipeline_config, crs=crs, report=report)


def run_json(result: Any) -> dict[str, Any]:
    """``run --json``: what the run did and where its outputs are (per building its building.json record)."""
    out = result.out_dir
    return {"out_dir": str(out), "processed": result.processed, "skipped": result.skipped, "failed": result.failed,
            "dropped": result.dropped, "seconds": round(result.seconds, 3),
            "outputs": {"summary": str(out / "summary.json"), "cityjson": str(out / "buildings.city.json"),
                        "geopackage": str(out / "buildings.gpkg")},
            "buildings": [{k: v for k, v in r.items() if k != "fingerprint"} for r in result.records]}


def print_run_summary(result: Any) -> None:
    """The per-building table, failures, and where the outputs are."""
    rows = []
    for r in result.records:
        state = "skipped (done)" if r["id"] in result.skipped else "done"
        coverage = r.get("coverage")
        covered = "" if coverage is None else f"{coverage:.2f}" + (" partial" if r.get("status") == "partial" else "")
        rows.append([r["id"], r["points"], r["building_points"], r.get("new_points", 0), r.get("planes", 0),
                     r["voxels"], r["mesh_faces"][r["mesh"]], "yes" if r["watertight"][r["mesh"]] else "no",
                     covered, r["seconds"]["total"], state])
    _table(f"lidarmap run -> {result.out_dir}", ["building", "points", "building pts", "new pts", "planes",
                                                  "voxels", "mesh triangles", "watertight", "coverage", "s", ""],
           rows)
    out = table_console()
    for bid, reason in result.failed.items():
        out.print(f"[yellow]failed[/] {bid}: {escape(reason)}", highlight=False)
    if result.dropped:
        out.print(f"{len(result.dropped)} footprint(s) dropped by prep (see summary.json)")
    out.print(f"{len(result.processed)} reconstructed, {len(result.skipped)} already done, "
              f"{len(result.failed)} failed in {result.seconds:.1f} s; CityJSON: "
              f"{result.out_dir / 'buildings.city.json'}", highlight=False)
