"""``lidarmap prep TILES... --footprints F -o DIR``: tiles + footprints -> one LAZ per building and an index."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    CrsOption,
    FootprintsOption,
    IdFieldOption,
    console,
    handle_errors,
    params_from,
    progress,
)


def register(app: typer.Typer) -> None:
    """Add ``prep`` to the app."""
    app.command("prep")(prep_command)


@handle_errors
def prep_command(
    tiles: list[Path] = typer.Argument(..., help="LAS/LAZ tiles (any number; merged while streaming)."),
    footprints: Path = FootprintsOption,
    out_dir: Path = typer.Option(..., "--out", "-o", help="Output folder (created; an earlier prep output there "
                                 "is replaced).", file_okay=False),
    buffer: Optional[float] = typer.Option(None, "--buffer", help="Keep points within this distance (m) of a "
                                           "footprint (default 5)."),
    id_field: Optional[str] = IdFieldOption,
    status_field: Optional[str] = typer.Option(None, "--status-field", help="Footprint property holding the "
                                               "construction status (default 'status')."),
    min_height: Optional[float] = typer.Option(None, "--min-height", help="Drop buildings lower than this (m, "
                                               "default 3)."),
    rotation: Optional[float] = typer.Option(None, "--rotation", help="Rotation (degrees about z) of the local "
                                             "frame stored with the outputs (default 0)."),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Split tiles into buildings: buildings/<id>.laz, buildings.csv (index), frame.json, prep.json."""
    from lidarmap.aerial.pipeline import prep_tiles
    from lidarmap.aerial.prep import PrepParams
    from lidarmap.io.crs import parse_crs
    from lidarmap.io.footprints import read_footprints
    from lidarmap.io.prepdir import check_out_dir, write_prep
    from lidarmap.io.tiles import scan_tiles

    params = params_from(PrepParams, config, buffer=buffer, id_field=id_field, status_field=status_field,
                         min_height=min_height, rotation_deg=rotation)
    parse_crs(crs)  # a bad --crs is reported before any reading
    check_out_dir(out_dir)
    fps = read_footprints(footprints, id_field=params.id_field)
    total = scan_tiles(tiles, crs).points
    with progress() as bar:
        reading = bar.add_task("reading tiles", total=total)
        result = prep_tiles(tiles, fps, params, crs=crs, progress=lambda n: bar.advance(reading, n))
        writing = bar.add_task("writing buildings", total=len(result.buildings))
        write_prep(out_dir, result, progress=lambda n: bar.advance(writing, n))
    table = Table(title=f"prep into {out_dir}", title_justify="left", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value", justify="right")
    table.add_row("points read", f"{result.points_read:,}")
    table.add_row("points kept", f"{result.points_kept:,}")
    table.add_row("footprints", f"{result.footprints:,}")
    table.add_row("buildings written", f"{len(result.buildings):,}")
    for reason, count in _reason_counts(result.dropped).items():
        table.add_row(f"dropped: {reason}", f"{count:,}")
    if result.repaired:
        table.add_row("repaired (self-intersecting)", f"{len(result.repaired):,}")
    console.print(table)
    console.print(f"done in {result.seconds:.1f} s ({result.points_per_second:,.0f} points/s)")


def _reason_counts(dropped: dict[str, str]) -> dict[str, int]:
    """How many footprints were dropped for each kind of reason (the text before any parenthesis)."""
    counts: dict[str, int] = {}
    for reason in dropped.values():
        key = reason.split(" (")[0]
        counts[key] = counts.get(key, 0) + 1
    return counts
