"""Façade images like Fig. 10 of Zou & Sester: depth layers, windows/doors with ε, unknown regions (matplotlib Agg).

Legend (docs/map.md):

* background dark grey: not observed by any campaign (evidence ``seen == 0``);
* green: the main depth layer where observed; light-green shades / other colours: further depth layers;
* structures (balconies, extrusions): filled in their layer's colour with a yellow outline when they sit on a
  non-main layer, yellow with a dark outline on the main layer (or without a layer);
* red outlines: windows (solid) and doors (dashed), annotated with their uncertainty ε;
* white polygons: unknown regions (occlusions, unexplained holes; ε = ∞);
* axes in metres along the wall (s) and up (t), façade seen from outside.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.patches import Patch, PathPatch
from matplotlib.path import Path as MplPath
from shapely.geometry import Polygon

from lidarmap.facade.model import ElementKind, Facade
from lidarmap.io.atomic import atomic_path
from lidarmap.io.prepdir import shorten_stem
from lidarmap.map.model import BuildingMap

__all__ = ["render_facade", "render_map", "facade_image_size", "facade_filename", "MAIN_COLOUR", "STRUCTURE_COLOUR",
           "LAYER_COLOURS", "WINDOW_COLOUR", "UNKNOWN_COLOUR", "UNOBSERVED_COLOUR"]

MAIN_COLOUR = "#2e9e3a"          # main façade layer (green)
STRUCTURE_COLOUR = "#f2d22e"     # structures on the façade (yellow)
LAYER_COLOURS = ("#a6e39a", "#6fc7b6", "#c8e67a", "#8fb8e8", "#d6a6e8")  # further layers: light green first
WINDOW_COLOUR = "#e3201b"        # windows and doors (red outlines)
UNKNOWN_COLOUR = "#ffffff"       # unknown regions (white)
UNOBSERVED_COLOUR = "#3a3a3a"    # never seen
HOLE_COLOUR = "#1c1c1c"          # seen through (window votes)

#: Figure margins in pixels: left, right, top, bottom (title above, labels and legend below).
MARGINS = (80, 30, 60, 130)


def facade_image_size(facade: Facade, width_px: int = 1200) -> tuple[int, int]:
    """(width, height) in pixels of :func:`render_facade`'s PNG: the plot keeps the façade's aspect ratio."""
    s0, s1, t0, t1 = (float(x) for x in facade.extent)
    left, right, top, bottom = MARGINS
    plot_w = max(width_px - left - right, 100)
    aspect = abs(t1 - t0) / abs(s1 - s0) if abs(s1 - s0) > 0 else 1.0
    plot_h = int(round(min(max(plot_w * aspect, 120), 3 * width_px)))
    return int(width_px), int(plot_h + top + bottom)


def facade_filename(building_id: str, facade_id: int) -> str:
    """``<building>_facade<NN>.png`` with anything but letters, digits, '.', '_' and '-' replaced by '_' (a long id
    cut, with a hash: :func:`lidarmap.io.prepdir.shorten_stem`)."""
    safe = shorten_stem(re.sub(r"[^A-Za-z0-9._-]+", "_", str(building_id)).strip("._") or "building", building_id)
    return f"{safe}_facade{int(facade_id):02d}.png"


def _polygon_path(polygon: Polygon) -> MplPath:
    rings = [polygon.exterior, *polygon.interiors]
    verts, codes = [], []
    for ring in rings:
        xy = np.asarray(ring.coords)[:, :2]
        if len(xy) < 3:
            continue
        verts.extend(xy.tolist())
        codes.extend([MplPath.MOVETO] + [MplPath.LINETO] * (len(xy) - 2) + [MplPath.CLOSEPOLY])
    return MplPath(verts, codes)


def _polygons(geom) -> list[Polygon]:
    if geom is None or geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom]
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]


def _layer_colours(facade: Facade) -> dict[int, str]:
    """Main layer green; the others (heaviest first) light green, then the rest of the palette."""
    colours: dict[int, str] = {}
    others = sorted((la for la in facade.layers if la.layer_id != facade.main_layer), key=lambda la: -la.weight)
    if facade.main_layer is not None:
        colours[int(facade.main_layer)] = MAIN_COLOUR
    for i, la in enumerate(others):
        colours[int(la.layer_id)] = LAYER_COLOURS[i % len(LAYER_COLOURS)]
    return colours


def _evidence_image(facade: Facade) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
    ev = facade.evidence
    if ev is None or ev.seen.size == 0:
        return None
    rows, cols = ev.seen.shape
    rgba = np.zeros((rows, cols, 4))
    rgba[...] = to_rgba(UNOBSERVED_COLOUR)
    seen = np.asarray(ev.seen) > 0
    rgba[seen] = to_rgba(MAIN_COLOUR, 0.85)
    holes = seen & (np.asarray(ev.window_votes) > 0) & (np.asarray(ev.object_votes) <= 0)
    rgba[holes] = to_rgba(HOLE_COLOUR)
    extent = (ev.s0, ev.s0 + cols * ev.cell, ev.t0, ev.t0 + rows * ev.cell)
    return rgba, extent


def render_facade(facade: Facade, path: str | Path, title: str | None = None, width_px: int = 1200,
                  dpi: int = 100) -> Path:
    """One PNG of a façade (size :func:`facade_image_size`), written atomically; returns ``path``."""
    path = Path(path)
    w_px, h_px = facade_image_size(facade, width_px)
    left, right, top, bottom = MARGINS
    fig = Figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((left / w_px, bottom / h_px, (w_px - left - right) / w_px, (h_px - top - bottom) / h_px))
    s0, s1, t0, t1 = (float(x) for x in facade.extent)
    ax.set_facecolor(UNOBSERVED_COLOUR)
    colours = _layer_colours(facade)
    image = _evidence_image(facade)
    if image is not None:
        rgba, extent = image
        ax.imshow(rgba, origin="lower", extent=extent, interpolation="nearest", zorder=1)
    else:
        ax.add_patch(PathPatch(_polygon_path(Polygon([(s0, t0), (s1, t0), (s1, t1), (s0, t1)])),
                               facecolor=MAIN_COLOUR, alpha=0.85, edgecolor="none", zorder=1))
    ax.add_patch(PathPatch(_polygon_path(Polygon([(s0, t0), (s1, t0), (s1, t1), (s0, t1)])), facecolor="none",
                           edgecolor="#bbbbbb", linewidth=1.0, linestyle=":", zorder=2))
    label_size = max(6, min(10, int(9 * width_px / 1200)))
    for element in facade.elements:
        polys = _polygons(element.polygon)
        if not polys:
            continue
        if element.is_unknown:
            for p in polys:
                ax.add_patch(PathPatch(_polygon_path(p), facecolor=to_rgba(UNKNOWN_COLOUR, 0.5),
                                       edgecolor=UNKNOWN_COLOUR, linewidth=2.0, zorder=4))  # solid white boundary
            continue
        if element.kind in (ElementKind.WINDOW, ElementKind.DOOR):
            style = "-" if element.kind is ElementKind.WINDOW else "--"
            for p in polys:
                ax.add_patch(PathPatch(_polygon_path(p), facecolor="none", edgecolor=WINDOW_COLOUR, linewidth=2.0,
                                       linestyle=style, zorder=5))
            c = polys[0].representative_point()
            tag = "ε" if element.kind is ElementKind.WINDOW else "door ε"
            ax.text(c.x, c.y, f"{tag}={element.uncertainty:.3f}", color="white", fontsize=label_size, ha="center",
                    va="center", zorder=6, bbox={"boxstyle": "round,pad=0.15", "facecolor": WINDOW_COLOUR,
                                                 "edgecolor": "none", "alpha": 0.8})
            continue
        layer_colour = colours.get(int(element.layer_id)) if element.layer_id is not None else None
        on_layer = layer_colour not in (None, MAIN_COLOUR)  # a structure proud of / behind the main wall
        fill, edge = (layer_colour, STRUCTURE_COLOUR) if on_layer else (STRUCTURE_COLOUR, "#8a7a10")
        for p in polys:
            ax.add_patch(PathPatch(_polygon_path(p), facecolor=fill, alpha=0.9, edgecolor=edge, linewidth=1.5,
                                   zorder=3))
        if math.isfinite(element.uncertainty):
            c = polys[0].representative_point()
            ax.text(c.x, c.y, f"ε={element.uncertainty:.3f}", color="black", fontsize=label_size - 1, ha="center",
                    va="center", zorder=6)
    pad = 0.02 * max(s1 - s0, t1 - t0, 1.0)
    ax.set_xlim(s0 - pad, s1 + pad)
    ax.set_ylim(t0 - pad, t1 + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("s along the wall (m)")
    ax.set_ylabel("t up (m)")
    ax.grid(True, color="#777777", linewidth=0.3, alpha=0.5)
    handles = []
    for la in sorted(facade.layers, key=lambda la: (la.layer_id != facade.main_layer, -la.weight)):
        name = "main layer" if la.layer_id == facade.main_layer else f"layer {la.layer_id}"
        handles.append(Patch(facecolor=colours.get(int(la.layer_id), MAIN_COLOUR), edgecolor="black",
                             label=f"{name}: μ={la.mu:+.2f} m σ={la.sigma * 100:.1f} cm w={la.weight:.2f}"))
    if not facade.layers:
        handles.append(Patch(facecolor=MAIN_COLOUR, edgecolor="black", label="façade plane"))
    handles += [Patch(facecolor=STRUCTURE_COLOUR, edgecolor="black", label="structure (fill: its layer)"),
                Patch(facecolor="none", edgecolor=WINDOW_COLOUR, linewidth=2, label="window / door (ε)"),
                Patch(facecolor=UNKNOWN_COLOUR, edgecolor="black", label="unknown (ε = ∞)"),
                Patch(facecolor=UNOBSERVED_COLOUR, edgecolor="black", label="not observed")]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=label_size, frameon=False,
               bbox_to_anchor=(0.5, 0.0))
    campaigns = ", ".join(str(c) for c in facade.campaigns) or "none"
    fig.suptitle(title or f"façade {facade.facade_id}", fontsize=12, y=1 - 12 / h_px, va="top")
    ax.set_title(f"σ = {facade.sigma * 100:.1f} cm · {facade.n_points:,} points · campaigns {campaigns}",
                 fontsize=label_size)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path


def render_map(building_map: BuildingMap, out_dir: str | Path, width_px: int = 1200,
               progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """One PNG per façade of every building into ``out_dir`` (created); returns the paths in map order.

    ``progress(done, total)`` is called after each façade.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(bid, facade) for bid, building in building_map.buildings.items() for facade in building.facades]
    written: list[Path] = []
    used: set[str] = set()
    for done, (bid, facade) in enumerate(jobs, start=1):
        name = facade_filename(bid, facade.facade_id)
        stem, k = name[:-4], 1
        while name in used:  # two ids that sanitise to one name
            k += 1
            name = f"{stem}-{k}.png"
        used.add(name)
        title = f"building {bid} · façade {facade.facade_id}"
        written.append(render_facade(facade, out_dir / name, title=title, width_px=width_px))
        if progress is not None:
            progress(done, len(jobs))
    return written
