"""How much of a building's footprint its points cover, and the part of the footprint that may be modelled.

A building cut by the edge of the tiles (or by a gap in the scan) has points over only part of its footprint; the
surface mesh would otherwise extrude the whole footprint to the nearest roof heights and invent a roof where nothing
was measured (Delft: a roof to x = 85,056.5 for points that stop at x <= 85,000).

The footprint is rasterised in ``cell`` x ``cell`` m cells (cells whose centre lies inside it); a cell is covered when
it holds at least one of the building's points, after a morphological closing of one cell (isolated empty cells of
sparse scans, ~2% of the cells at 4 points/m² and 1 m cells, are not gaps). ``coverage`` is the covered share of the
footprint's cells. Below ``min_coverage`` the building is **partial**: it is modelled over the covered cells grown by
``margin`` m and cut to the footprint, and marked so in building.json, the run table and the CityJSON attributes.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry.base import BaseGeometry

from lidarmap.config import check_params

__all__ = ["Coverage", "CoverageParams", "footprint_coverage"]


@dataclasses.dataclass(frozen=True)
class CoverageParams:
    """``[coverage]``: the share of each footprint that its points cover, and what a partly covered building gets.

    cell (1.0): raster cell (m) of the footprint; a cell with at least one building point is covered (a cell of a
        few points at the 8-25 points/m² of national scans; raise it for sparser data).
    min_coverage (0.6): a building whose covered share is below this is partial: modelled over the covered part
        only, status "partial"; 0 = never.
    margin (0.5): the covered cells are grown by this (m) before cutting the footprint (the outermost points lie up
        to a point spacing inside the real edge; the cells already reach up to ``cell`` beyond them).
    """

    section = "coverage"
    constraints: ClassVar[dict[str, str]] = {"cell": "> 0", "min_coverage": "[0, 1]", "margin": ">= 0"}

    cell: float = 1.0
    min_coverage: float = 0.6
    margin: float = 0.5

    def __post_init__(self) -> None:
        check_params(self)


@dataclasses.dataclass
class Coverage:
    """``share`` of the footprint's cells covered (0-1); ``partial`` below ``min_coverage``; ``outline``: the part of
    the footprint to model (the footprint itself unless partial)."""

    share: float
    partial: bool
    outline: BaseGeometry

    @property
    def status(self) -> str:
        return "partial" if self.partial else "complete"


def _covered_cells(xy: np.ndarray, footprint: BaseGeometry, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inside, covered, origin): boolean rasters of the footprint's cells and of the cells holding points."""
    x0, y0, x1, y1 = footprint.bounds
    origin = np.floor(np.array([x0, y0]) / cell) * cell
    shape = (int(np.ceil((x1 - origin[0]) / cell)) + 1, int(np.ceil((y1 - origin[1]) / cell)) + 1)
    ci, cj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    inside = shapely.contains_xy(footprint, origin[0] + (ci + 0.5) * cell, origin[1] + (cj + 0.5) * cell)
    ij = np.floor((np.asarray(xy, dtype=np.float64) - origin) / cell).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < shape), axis=1)
    hits = np.zeros(shape, dtype=bool)
    hits[ij[ok, 0], ij[ok, 1]] = True
    padded = np.pad(hits, 1)
    closed = ndimage.binary_closing(padded, structure=np.ones((3, 3), dtype=bool))[1:-1, 1:-1] | hits
    return inside, closed, origin


def footprint_coverage(xy: np.ndarray, footprint: BaseGeometry, params: CoverageParams = CoverageParams()
                       ) -> Coverage:
    """The coverage of ``footprint`` (CRS polygon) by the building's points ``xy`` (N, 2); see the module docstring.

    A footprint too small to hold a cell centre counts as covered when any point lies in it.
    """
    inside, covered, origin = _covered_cells(xy, footprint, params.cell)
    if not inside.any():
        share = float(len(xy) > 0 and shapely.contains_xy(footprint, xy[:, 0], xy[:, 1]).any())
    else:
        share = float((covered & inside).sum() / inside.sum())
    if share >= params.min_coverage:
        return Coverage(share=share, partial=False, outline=footprint)
    i, j = np.nonzero(covered & inside)
    cells = shapely.box(origin[0] + i * params.cell, origin[1] + j * params.cell,
                        origin[0] + (i + 1) * params.cell, origin[1] + (j + 1) * params.cell)
    part = shapely.union_all(cells).buffer(params.margin, join_style="mitre") if len(cells) else shapely.Polygon()
    return Coverage(share=share, partial=True, outline=shapely.make_valid(part.intersection(footprint)))
