"""``lidarmap info FILE``."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from lidarmap.cli.common import console, handle_errors
from lidarmap.io.info import las_info, points_info

ASPRS_CLASSES = {0: "never classified", 1: "unclassified", 2: "ground", 3: "low vegetation", 4: "medium vegetation",
                 5: "high vegetation", 6: "building", 7: "low point (noise)", 9: "water", 17: "bridge deck",
                 18: "high noise"}


def register(app: typer.Typer) -> None:
    app.command("info")(info)


@handle_errors
def info(
    file: Path = typer.Argument(..., help="LAS/LAZ, PLY or text (.xyz/.txt/.csv) point file."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (for scripts)."),
    crs: str = typer.Option(None, "--crs", help="CRS to assume when the file has none, e.g. EPSG:28992."),
    columns: str = typer.Option(None, "--columns", help="Columns of a text point file, e.g. x,y,z,intensity "
                                "(docs/mls.md)."),
) -> None:
    """Summarise a point file: points, format, CRS, bounds, density, classes, returns, GPS time, extra dims."""
    from lidarmap.io.points import point_format

    summary = las_info(file, crs=crs) if point_format(file) == "las" else points_info(file, crs, columns)
    if as_json:
        typer.echo(json.dumps(summary))
        return
    table = Table(title=str(file), show_header=False, title_justify="left")
    table.add_column("field", style="bold")
    table.add_column("value")
    crs_info = summary["crs"]
    table.add_row("points", f"{summary['point_count']:,}")
    table.add_row("format", summary.get("format") or f"LAS {summary['las_version']}, point format "
                  f"{summary['point_format']}" + (" (LAZ)" if summary["compressed"] else ""))
    table.add_row("CRS", "none (use --crs)" if crs_info is None else
                  f"{crs_info['name']} (EPSG:{crs_info['epsg']})" if crs_info["epsg"] else crs_info["name"])
    if summary["bounds"]:
        lo, hi = summary["bounds"]["min"], summary["bounds"]["max"]
        table.add_row("bounds", f"x {lo[0]:.3f} .. {hi[0]:.3f}\ny {lo[1]:.3f} .. {hi[1]:.3f}\nz {lo[2]:.3f} .. {hi[2]:.3f}")
        unit = _area_unit(crs_info)
        table.add_row("density", f"{summary['density']:.1f} pts/{unit} over {summary['area_covered']:.0f} {unit} covered")
    table.add_row("classes", "\n".join(f"{k:>3} {ASPRS_CLASSES.get(int(k), ''):<18} {v:,}"
                                       for k, v in summary["classes"].items()))
    table.add_row("returns", ", ".join(f"{k}: {v:,}" for k, v in summary["returns"].items()))
    if summary["gps_time"]:
        table.add_row("GPS time", f"{summary['gps_time']['min']:.3f} .. {summary['gps_time']['max']:.3f}")
    table.add_row("extra dims", ", ".join(summary["extra_dimensions"]) or "none")
    console.print(table)


def _area_unit(crs_info: dict | None) -> str:
    """'m²' or 'ft²' when the CRS says so; a file without CRS has unknown units."""
    units = ((crs_info or {}).get("units") or "").lower()
    if units in ("metre", "meter"):
        return "m²"
    if "foot" in units or "feet" in units:
        return "ft²"
    return "unit²"
