"""``lidarmap view OUT|MAP|X.glb -o view.html [--as-of N]``: one self-contained HTML page with a 3D viewer.

OUT: a ``lidarmap run`` output folder (its ``buildings.glb``, made from the meshes when an older run has none);
MAP: a façade map (``.lmap``), as of a campaign with ``--as-of``; X.glb: any glb written by lidarmap.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import typer

from lidarmap.cli.common import handle_errors, table_console
from lidarmap.errors import InputError

__all__ = ["register", "view_command"]


def register(app: typer.Typer) -> None:
    """Add ``view`` to the app."""
    app.command("view")(view_command)


def _run_glb(out_dir: Path) -> bytes:
    """A run folder's buildings.glb; made (in memory) from its meshes when the run predates it."""
    glb = out_dir / "buildings.glb"
    if glb.is_file():
        return glb.read_bytes()
    summary = out_dir / "summary.json"
    if not summary.is_file():
        raise InputError("neither buildings.glb nor summary.json here: not a 'lidarmap run' output folder", out_dir)
    from lidarmap.aerial.pipeline import RUN_GLB_TITLE, run_folders, run_glb_buildings
    from lidarmap.export.gltf import glb_bytes

    try:
        run = json.loads(summary.read_text(encoding="utf-8"))
        records, crs_wkt = run["records"], run.get("crs") or ""
        stems = run_folders(run)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"unreadable run summary ({exc})", summary) from None
    return glb_bytes(run_glb_buildings(out_dir, records, stems), crs_wkt, title=RUN_GLB_TITLE)


def _source(source: Path, as_of: int | None) -> tuple[bytes, str, list[dict[str, Any]]]:
    """(glb bytes, title, campaigns) of whatever ``source`` is."""
    from lidarmap.export.gltf import read_glb_json

    if not source.exists():
        raise InputError("not found", source)
    if as_of is not None and (source.is_dir() or source.suffix.lower() == ".glb"):
        raise InputError("--as-of applies to a map only", source)
    if source.is_dir():
        return _run_glb(source), f"{source.resolve().name}: aerial run", []
    if source.suffix.lower() == ".glb":
        data = source.read_bytes()
        try:
            read_glb_json(data)
        except ValueError as exc:
            raise InputError(str(exc), source) from None
        return data, source.stem, []
    from lidarmap.cli.facade_map import _state, load_map
    from lidarmap.export.gltf import map_to_glb

    building_map = load_map(source, as_of)
    title = f"{source.stem} ({_state(building_map, as_of)})"
    campaigns = [{k: v for k, v in dataclasses.asdict(c).items() if k != "summary"} for c in building_map.campaigns]
    return map_to_glb(building_map, title), title, campaigns


SourceArgument = typer.Argument(..., metavar="OUT|MAP|X.glb",
                                help="A 'lidarmap run' output folder, a façade map (.lmap) or a .glb file.")
PageOption = typer.Option(..., "--output", "-o", help="HTML page to write (opens from the file system).",
                          dir_okay=False)
AsOfOption = typer.Option(None, "--as-of", help="A map as it was right after campaign N.")


@handle_errors
def view_command(source: Path = SourceArgument, out: Path = PageOption, as_of: int | None = AsOfOption) -> None:
    """Write one self-contained HTML page (no server, no network) with a 3D viewer: orbit, pick a building for its
    attributes, toggle roofs/walls/openings/unknown regions."""
    from lidarmap.export.gltf import glb_building_ids
    from lidarmap.io.atomic import write_text_atomic
    from lidarmap.viewer import viewer_page

    if out.exists() and out.is_dir():
        raise InputError("output is a folder; give a file name like view.html", out)
    glb, title, campaigns = _source(source, as_of)
    write_text_atomic(out, viewer_page(glb, title, campaigns))
    table_console().print(f"wrote {out} ({len(glb_building_ids(glb))} buildings, {out.stat().st_size / 1e6:.1f} MB); "
                          "open it in a browser")
