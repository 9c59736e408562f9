"""Which parts of each façade the pulses actually reached.

A pulse observes a façade cell when, coming from outside (its origin in front of the wall's reference plane,
heading into it), it crosses the plane inside the cell before anything stopped it: its first hit (sub-ray 0,
the first surface in its way, leaves included) lies at most ``TOLERANCE`` in front of the plane or behind it, or
there is none. The tolerance absorbs the wall's lean (up to 0.3 deg) and its relief. The pulse must also be one the
wall would have answered there: with its whole energy on the wall's reflectance at that incidence and range, above
the scanner's detection threshold (the same rule as the laser physics). A pulse that crosses a far, grazing wall
too weakly to return from it cannot tell an opening from the wall either: without that rule, windows on a wall
whose returns stop at some range counted as observed although nothing in the data could show them. Two grids per
façade: 0.2 m cells (openings) and 0.5 m cells (wall area), both anchored at the façade origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CELL = 0.2
WALL_CELL = 0.5
TOLERANCE = 0.10  # m in front of the reference plane still counts as reaching it
OPENING_MARGIN = 0.3  # wall cells must keep this far from every opening


@dataclass
class ObsFacade:
    id: int
    o: np.ndarray
    u: np.ndarray
    n: np.ndarray
    width: float
    height: float
    refl: float = 0.5  # the wall's reflectance

    @property
    def shape(self) -> tuple:
        return int(np.ceil(self.width / CELL)), int(np.ceil(self.height / CELL))

    @property
    def wall_shape(self) -> tuple:
        return int(np.floor(self.width / WALL_CELL)), int(np.floor(self.height / WALL_CELL))


def empty_grids(facades: list[ObsFacade]) -> list:
    return [(np.zeros(f.shape, bool), np.zeros(f.wall_shape, bool)) for f in facades]


def observe(O: np.ndarray, D: np.ndarray, first_t: np.ndarray, facades: list[ObsFacade], max_range: float,
            grids: list) -> None:
    """Mark (in place) the cells of every façade that these pulses crossed unobstructed."""
    for f, (fine, coarse) in zip(facades, grids):
        so = (O - f.o) @ f.n
        dn = D @ f.n
        m = np.flatnonzero((so > 0) & (dn < -1e-6))
        if not len(m):
            continue
        tc = so[m] / -dn[m]
        with np.errstate(invalid="ignore"):
            reach = so[m] + dn[m] * first_t[m]
        ok = (tc <= max_range) & ~(reach > TOLERANCE) & wall_detectable(f.refl, -dn[m], tc, max_range)
        m, tc = m[ok], tc[ok]
        c = O[m] + D[m] * tc[:, None]
        s = (c - f.o) @ f.u
        t = c[:, 2] - f.o[2]
        for grid, size in ((fine, CELL), (coarse, WALL_CELL)):
            i, j = np.floor(s / size).astype(np.int64), np.floor(t / size).astype(np.int64)
            inside = (i >= 0) & (j >= 0) & (i < grid.shape[0]) & (j < grid.shape[1])
            grid[i[inside], j[inside]] = True


def wall_detectable(refl: float, cos: np.ndarray, rng: np.ndarray, max_range: float) -> np.ndarray:
    """Whether a whole pulse on the wall (reflectance ``refl``, incidence cosine ``cos``, range ``rng``) returns:
    the detection rule of physics.combine (reflectance x (0.2 + 0.8 cos) x (max range / r)^2 >= 0.8)."""
    return refl * (0.2 + 0.8 * cos) * (max_range / np.maximum(rng, 1e-6)) ** 2 >= 0.8


def opening_fraction(fine: np.ndarray, rect) -> float:
    """Share of the 0.2 m cells whose centre lies inside rect that were observed."""
    s0, s1, t0, t1 = rect
    ci = (np.arange(fine.shape[0]) + 0.5) * CELL
    cj = (np.arange(fine.shape[1]) + 0.5) * CELL
    mi = (ci > s0) & (ci < s1)
    mj = (cj > t0) & (cj < t1)
    cells = fine[np.ix_(mi, mj)]
    return float(cells.mean()) if cells.size else 0.0


def wall_mask(f: ObsFacade, rects: list, ground_t) -> np.ndarray:
    """0.5 m cells of bare wall: above the ground line, under the eave, clear of every opening by 0.3 m."""
    ni, nj = f.wall_shape
    s0 = np.arange(ni) * WALL_CELL
    ground = np.array([np.max(ground_t(np.linspace(a, a + WALL_CELL, 6))) for a in s0]) if ni else np.zeros(0)
    t0 = np.arange(nj) * WALL_CELL
    mask = t0[None, :] >= ground[:, None]
    for a, b, c, d in rects:
        hit_s = (s0 + WALL_CELL > a - OPENING_MARGIN) & (s0 < b + OPENING_MARGIN)
        hit_t = (t0 + WALL_CELL > c - OPENING_MARGIN) & (t0 < d + OPENING_MARGIN)
        mask &= ~(hit_s[:, None] & hit_t[None, :])
    return mask
