"""Visibility truth per campaign and façade, on a grid of façade cells.

Grid layout: ``grid[j, i]`` is the cell s in [i*c, (i+1)*c), t in [j*c, (j+1)*c) of the façade (c = cell size),
covering s in [0, width) and t in [0, t_top) (t = 0 is the façade origin, the lowest terrain along it).

* ``seen``: the line of sight from the sensor -- at the profile whose scan plane passes through the cell centre,
  within max range -- first meets a surface of this façade (wall, reveal, room, door, structure, or the dark
  absorber behind a window) rather than a car, a tree, another building or the terrain. Occlusion truth that does
  not depend on the angular step.
* ``hit``: cells where at least one of the campaign's actual pulses ended on this façade (the pulse's crossing of the
  façade plane for recessed surfaces, its hit for the rest).
"""

from __future__ import annotations

import numpy as np

from lidarmap.sim.buildings import Facade
from lidarmap.sim.raycast import Tracer


def grid_shape(f: Facade, cell: float) -> tuple[int, int]:
    return max(1, int(np.ceil(f.t_top / cell))), max(1, int(np.ceil(f.width / cell)))


def seen_grid(tracer: Tracer, f: Facade, sensors: np.ndarray, plane_normals: np.ndarray, cell: float,
              max_range: float) -> np.ndarray:
    """Cells of ``f`` with a clear line of sight from the profile plane through them (see module doc)."""
    rows, cols = grid_shape(f, cell)
    grid = np.zeros((rows, cols), bool)
    t = (np.arange(rows) + 0.5) * cell
    h = plane_normals
    hu = h @ f.u
    usable = np.abs(hu) > 0.1  # profile planes nearly parallel to the wall never sweep across it
    if not usable.any():
        return grid
    h, p, hu = h[usable], sensors[usable], hu[usable]
    # s where profile plane k (h . (x - p) = 0) crosses the façade line at height t_j
    s = ((np.einsum("ij,ij->i", h, p - f.origin))[:, None] - t[None, :] * h[:, 2:3]) / hu[:, None]
    k, j = np.nonzero((s >= 0) & (s < f.width))
    if len(k) == 0:
        return grid
    s = s[k, j]
    target = f.origin + s[:, None] * f.u + t[j][:, None] * np.array([0.0, 0.0, 1.0])
    ray = target - p[k]
    dist = np.linalg.norm(ray, axis=1)
    facing = (p[k] - target) @ f.normal > 0.05
    ok = facing & (dist <= max_range) & (dist > 0.5)
    k, j, s, ray, dist = k[ok], j[ok], s[ok], ray[ok], dist[ok]
    tri, _ = tracer.first_hit(p[k], ray / dist[:, None])
    seen = (tri >= 0) & (tracer.scene.facade_id[np.maximum(tri, 0)] == f.id)
    i = np.minimum((s / cell).astype(int), cols - 1)
    grid[j[seen], i[seen]] = True
    return grid


class HitGrids:
    """Accumulates, chunk by chunk, the cells where actual pulses ended on each façade (see module doc)."""

    def __init__(self, facades: list[Facade], cell: float):
        self.cell = cell
        self.facades = {f.id: f for f in facades}
        self.grids = {f.id: np.zeros(grid_shape(f, cell), bool) for f in facades}

    def add(self, facade_of_tri: np.ndarray, origins: np.ndarray, dirs: np.ndarray, stop_tri: np.ndarray,
            stop_range: np.ndarray) -> None:
        ended = np.flatnonzero(stop_tri >= 0)
        fid = facade_of_tri[stop_tri[ended]]
        for face_id in np.unique(fid[fid >= 0]):  # one vectorised pass per façade
            f = self.facades.get(int(face_id))
            if f is not None:
                sel = ended[fid == face_id]
                self._mark(f, origins[sel], dirs[sel], stop_range[sel])

    def _mark(self, f: Facade, o: np.ndarray, d: np.ndarray, dist: np.ndarray) -> None:
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        hit = f.to_facade(o + dist[:, None] * d)
        behind = hit[:, 2] < -1e-6  # recessed surfaces: use where the pulse crossed the wall plane
        denom = d[behind] @ f.normal
        cross = (f.origin - o[behind]) @ f.normal / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        hit[behind] = f.to_facade(o[behind] + cross[:, None] * d[behind])
        grid = self.grids[f.id]
        i, j = np.floor(hit[:, 0] / self.cell), np.floor(hit[:, 1] / self.cell)
        ok = np.isfinite(i) & np.isfinite(j) & (i >= 0) & (i < grid.shape[1]) & (j >= 0) & (j < grid.shape[0])
        grid[j[ok].astype(int), i[ok].astype(int)] = True


def visible_fraction(grid: np.ndarray, rect: tuple[float, float, float, float], cell: float) -> float:
    """Fraction of the cells whose centres fall in [s0, s1] x [t0, t1] that are set in ``grid``."""
    s0, s1, t0, t1 = rect
    cs = (np.arange(grid.shape[1]) + 0.5) * cell
    ct = (np.arange(grid.shape[0]) + 0.5) * cell
    cols = (cs >= s0) & (cs <= s1)
    rows = (ct >= t0) & (ct <= t1)
    block = grid[np.ix_(rows, cols)]
    return float(block.mean()) if block.size else 0.0
