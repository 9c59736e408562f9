"""Ground surface for the height-above-ground feature: from class 2 when the file has it, else estimated.

The estimate is a simple progressive morphological filter (SMRF-like, Pingel et al. 2013): a grid of per-cell
minimum heights is opened with growing windows; cells that drop by more than ``threshold + slope * window radius``
belong to objects (buildings, trees). The remaining cells are the ground; holes under objects are filled by
normalised Gaussian convolution, so the surface follows the surrounding terrain. Everything is vectorised on a grid
(scipy.ndimage), so a 1 km2 tile at 1 m takes about a second.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

#: Cells whose minimum lies this far below the median of their neighbourhood are low outliers (multipath, birds).
LOW_OUTLIER_M = 1.5


@dataclasses.dataclass
class GroundGrid:
    """Ground heights on a regular grid: value ``z[j, i]`` at the centre of cell (x0 + i*cell, y0 + j*cell)."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray  # (ny, nx) float64

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear ground height at points (N, 2); outside the grid the border value holds."""
        col = (xy[:, 0] - self.x0) / self.cell - 0.5
        row = (xy[:, 1] - self.y0) / self.cell - 0.5
        return ndimage.map_coordinates(self.z, [row, col], order=1, mode="nearest")


def _grid_index(xy: np.ndarray, cell: float) -> tuple[float, float, np.ndarray, np.ndarray, tuple[int, int]]:
    x0, y0 = np.floor(xy.min(axis=0) / cell) * cell
    i = ((xy[:, 0] - x0) / cell).astype(np.int64)
    j = ((xy[:, 1] - y0) / cell).astype(np.int64)
    return float(x0), float(y0), i, j, (int(j.max()) + 1, int(i.max()) + 1)


def _cell_reduce(xy: np.ndarray, z: np.ndarray, cell: float, how: str) -> tuple[float, float, np.ndarray]:
    """Per-cell minimum or mean of ``z`` (NaN where a cell is empty)."""
    x0, y0, i, j, shape = _grid_index(xy, cell)
    flat = j * shape[1] + i
    grid = np.full(shape[0] * shape[1], np.nan)
    if how == "min":
        order = np.lexsort((z, flat))  # by cell, then height: the first of each cell is its minimum
        first = np.r_[True, flat[order][1:] != flat[order][:-1]]
        grid[flat[order][first]] = z[order][first]
    else:
        total = np.bincount(flat, weights=z, minlength=grid.size)
        count = np.bincount(flat, minlength=grid.size)
        grid[count > 0] = total[count > 0] / count[count > 0]
    return x0, y0, grid.reshape(shape)


def fill_holes(z: np.ndarray, known: np.ndarray, max_sigma: float = 64.0) -> np.ndarray:
    """Fill cells where ``known`` is False by normalised Gaussian convolution at growing scales.

    Small holes get values from close neighbours, large ones (under big buildings) from a wider ring.
    """
    out = np.where(known, z, 0.0)
    filled = known.copy()
    if not filled.any():
        return np.zeros_like(z)
    sigma = 1.0
    while not filled.all():
        num = ndimage.gaussian_filter(np.where(known, z, 0.0), sigma, mode="nearest")
        den = ndimage.gaussian_filter(known.astype(np.float64), sigma, mode="nearest")
        take = ~filled & (den > 1e-3)
        out[take] = num[take] / den[take]
        filled |= take
        if sigma >= max_sigma:  # what is still empty is far from any ground: nearest value
            idx = ndimage.distance_transform_edt(~filled, return_distances=False, return_indices=True)
            out = out[tuple(idx)]
            break
        sigma *= 2.0
    return out


def ground_from_points(xy: np.ndarray, z: np.ndarray, cell: float) -> GroundGrid:
    """Ground surface from points known to be ground (class 2): per-cell mean, holes filled."""
    x0, y0, grid = _cell_reduce(xy, z, cell, "mean")
    return GroundGrid(x0, y0, cell, fill_holes(grid, np.isfinite(grid)))


def estimate_ground(xy: np.ndarray, z: np.ndarray, cell: float = 1.0, max_window: float = 40.0,
                    slope: float = 0.3, threshold: float = 0.5) -> GroundGrid:
    """Ground surface estimated from all points with a progressive morphological filter (see module doc).

    ``max_window`` (m) is the widest object the filter removes; ``slope`` (m/m) the steepest terrain kept;
    ``threshold`` (m) the height step always allowed.
    """
    x0, y0, zmin = _cell_reduce(xy, z, cell, "min")
    present = np.isfinite(zmin)
    surface = fill_holes(zmin, present, max_sigma=4.0)
    # low outliers would be kept as ground by an opening (it only removes bumps): lift them to their surroundings
    median = ndimage.median_filter(surface, size=5, mode="nearest")
    low = surface < median - LOW_OUTLIER_M
    surface[low] = median[low]
    objects = np.zeros_like(present)
    radius, max_radius = 1, max(1, int(round(max_window / 2 / cell)))
    while True:
        opened = ndimage.grey_opening(surface, size=(2 * radius + 1, 2 * radius + 1), mode="nearest")
        objects |= (surface - opened) > threshold + slope * radius * cell
        surface = opened
        if radius >= max_radius:
            break
        radius = min(max_radius, radius * 2)
    ground = present & ~objects & ~low
    return GroundGrid(x0, y0, cell, fill_holes(np.where(ground, zmin, 0.0), ground))
