"""``lidarmap simulate OUT_DIR``: a procedural city scanned by simulated aerial and mobile LiDAR, with truth."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    SeedOption,
    console,
    handle_errors,
    params_from,
    progress,
)


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the app."""
    app.command("simulate")(simulate_command)


#: Kind of the output-folder marker of ``simulate`` (:mod:`lidarmap.io.outdir`).
SIMULATE_KIND = "simulate"


@handle_errors
def simulate_command(
    out_dir: Path = typer.Argument(..., help="Folder to write the simulated data and truth into (created; an "
                                   "empty folder or an earlier simulation, which is replaced: files of yours there "
                                   "are never touched).",
                                   file_okay=False),
    seed: Optional[int] = SeedOption,
    buildings: Optional[int] = typer.Option(None, "--buildings", help="Existing buildings (default 8); one "
                                            "construction site is always added."),
    campaigns: Optional[int] = typer.Option(None, "--campaigns", help="Mobile campaigns (default 3)."),
    family: Optional[str] = typer.Option(None, "--family", help="Scene family: standard (default) or hard "
                                         "(randomised façades, glass, grazing side walls, varied campaigns; "
                                         "docs/simulator.md)."),
    mls_format: Optional[str] = typer.Option(None, "--mls-format", help="Mobile campaigns as laz (default), ply "
                                             "(binary) or ply_ascii, as public MLS data sets come (docs/mls.md)."),
    mls_origins: Optional[bool] = typer.Option(None, "--mls-origins/--no-mls-origins", help="PLY: per-point "
                                               "sensor origins x_origin, y_origin, z_origin (default: none)."),
    mls_gps_time: Optional[bool] = typer.Option(None, "--mls-gps-time/--no-mls-gps-time", help="PLY: per-point "
                                                "GPS time (default: yes)."),
    config: Optional[Path] = ConfigOption,
) -> None:
    """Simulate a city (aerial als.laz, mobile mls_<i>.laz + trajectory_<i>.csv, footprints.geojson, truth/)."""
    from lidarmap.io.outdir import atomic_out_dir
    from lidarmap.sim import (  # imported here: keeps `lidarmap --help` fast
        SimParams,
        simulate,
    )

    params = params_from(SimParams, config, seed=seed, buildings=buildings, campaigns=campaigns, family=family,
                         mls_format=mls_format, mls_origins=mls_origins, mls_gps_time=mls_gps_time)
    # simulated into a temporary folder published at the end: an error leaves out_dir as it was; a new simulation
    # replaces what an earlier one there wrote (replace=True), and only that
    with atomic_out_dir(out_dir, SIMULATE_KIND, replace=True) as tmp, progress() as bar:
        tasks: dict[str, int] = {}

        def report(task: str, done: int, total: int) -> None:
            if task not in tasks:
                tasks[task] = bar.add_task(task, total=total)
            bar.update(tasks[task], completed=done, total=total)

        result = simulate(tmp, params, report)
    table = Table(title=f"simulated {params.family} seed {params.seed} into {out_dir}", title_justify="left")
    table.add_column("file")
    table.add_column("points", justify="right")
    table.add_row(result.als.name, f"{result.als_points:,}")
    for path, n in zip(result.mls, result.mls_points):
        table.add_row(path.name, f"{n:,}")
    for path in result.trajectories:
        table.add_row(path.name, "")
    table.add_row(result.footprints.name, "")
    table.add_row("truth/", "")
    console.print(table)
    console.print(f"done in {result.seconds:.1f} s")
