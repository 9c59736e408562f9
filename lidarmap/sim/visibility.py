"""Visibility truth per campaign and façade, on a grid of façade cells.

Grid layout: ``grid[j, i]`` is the cell s in [i*c, (i+1)*c), t in [j*c, (j+1)*c) of the façade (c = cell size),
covering s in [0, width) and t in [0, t_top) (t = 0 is the façade origin, the lowest terrain along it).

* ``seen``: the line of sight from the sensor -- at the profile whose scan plane passes through the cell centre,
  within max range -- first meets a surface of this façade (wall, reveal, room, door, glass, curtain, structure, or
  the dark absorber behind a window) rather than a car, a tree, another building or the terrain. Occlusion truth
  that does not depend on the angular step. What the structures (balconies, shutters, cornices) are scored by.
* ``wall_seen``: ``seen``, less the cells whose line of sight ends on a structure standing in front of the wall (a
  balcony's parapet): the wall and its openings behind it are as hidden as behind a tree. What the windows and
  doors are scored by (since 2026-11-26; before, a window wholly behind a parapet counted as seen).
* ``hit``: cells where at least one of the campaign's actual pulses ended on this façade (the pulse's crossing of the
  façade plane for recessed surfaces, its hit for the rest).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lidarmap.sim.buildings import Facade
from lidarmap.sim.mesh import KIND
from lidarmap.sim.raycast import Tracer


def grid_shape(f: Facade, cell: float) -> tuple[int, int]:
    return max(1, int(np.ceil(f.t_top / cell))), max(1, int(np.ceil(f.width / cell)))


@dataclasses.dataclass(frozen=True)
class Observability:
    """When a cell with a line of sight counts as seen (the hard family; the defaults accept every such cell).

    ``max_incidence``: largest angle (degrees) between the line of sight and the wall normal;
    ``max_spacing``: largest expected distance (metres) between samples at the cell -- between neighbouring
    profiles' stripes along the wall, and between pulses within a profile (:func:`pulse_spacing`);
    ``angular_step``: the scanner's angle between pulses, degrees.
    """

    max_incidence: float = 90.0
    max_spacing: float = np.inf
    angular_step: float = 0.4

    @property
    def limited(self) -> bool:
        return self.max_incidence < 90.0 or np.isfinite(self.max_spacing)


def seen_grid(tracer: Tracer, f: Facade, sensors: np.ndarray, plane_normals: np.ndarray, cell: float,
              max_range: float, observability: Observability = Observability()) -> tuple[np.ndarray, np.ndarray]:
    """Cells of ``f`` with a clear line of sight from the profile plane through them: ``(seen, wall_seen)`` (see
    module doc).

    With a limited ``observability`` the profiles are also interpolated (up to 8 in between) where their stripes
    on the wall lie farther apart than half a cell, so a wall swept at a grazing angle is judged everywhere.
    """
    rows, cols = grid_shape(f, cell)
    grid = np.zeros((rows, cols), bool)
    wall = np.zeros((rows, cols), bool)
    t = (np.arange(rows) + 0.5) * cell
    h = plane_normals
    stripe = np.zeros(len(h))
    if observability.limited:
        sensors, h, stripe = _densified(f, sensors, h, cell)
    hu = h @ f.u
    usable = np.abs(hu) > 0.1  # profile planes nearly parallel to the wall never sweep across it
    if not usable.any():
        return grid, wall
    h, p, hu, stripe = h[usable], sensors[usable], hu[usable], stripe[usable]
    # s where profile plane k (h . (x - p) = 0) crosses the façade line at height t_j
    s = ((np.einsum("ij,ij->i", h, p - f.origin))[:, None] - t[None, :] * h[:, 2:3]) / hu[:, None]
    k, j = np.nonzero((s >= 0) & (s < f.width))
    if len(k) == 0:
        return grid, wall
    s = s[k, j]
    target = f.origin + s[:, None] * f.u + t[j][:, None] * np.array([0.0, 0.0, 1.0])
    ray = target - p[k]
    dist = np.linalg.norm(ray, axis=1)
    facing = (p[k] - target) @ f.normal > 0.05
    ok = facing & (dist <= max_range) & (dist > 0.5)
    if observability.limited:
        cos_inc = np.maximum((p[k] - target) @ f.normal / np.maximum(dist, 1e-9), 1e-6)
        in_profile = pulse_spacing(ray / np.maximum(dist, 1e-9)[:, None], h[k], f.normal, dist,
                                    np.radians(observability.angular_step))
        ok &= (cos_inc >= np.cos(np.radians(observability.max_incidence)))
        ok &= (np.maximum(in_profile, stripe[k]) <= observability.max_spacing)
    k, j, s, ray, dist = k[ok], j[ok], s[ok], ray[ok], dist[ok]
    tri, _ = tracer.first_hit(p[k], ray / dist[:, None])
    scene, first = tracer.scene, np.maximum(tri, 0)
    seen = (tri >= 0) & (scene.facade_id[first] == f.id)
    at_wall = seen & (scene.kind[first] != KIND["structure"])
    i = np.minimum((s / cell).astype(int), cols - 1)
    grid[j[seen], i[seen]] = True
    wall[j[at_wall], i[at_wall]] = True
    return grid, wall


def pulse_spacing(r: np.ndarray, h: np.ndarray, n: np.ndarray, dist: np.ndarray, step: float) -> np.ndarray:
    """Distance on the wall between neighbouring pulses of one profile (metres).

    A pulse turning by dθ in its profile plane (normal h) moves its hit on the wall (normal n) by
    dist * |r' - r (n.r') / (n.r)| dθ, with r' = h x r the direction the pulse turns to.
    """
    turn = np.cross(h, r)
    turn /= np.maximum(np.linalg.norm(turn, axis=1, keepdims=True), 1e-12)
    nr = r @ n
    nr = np.where(np.abs(nr) > 1e-6, nr, 1e-6)
    return dist * step * np.linalg.norm(turn - r * ((turn @ n) / nr)[:, None], axis=1)


def _densified(f: Facade, sensors: np.ndarray, normals: np.ndarray,
               cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses interpolated between the profiles and each pose's stripe spacing on the wall (of the real profiles).

    Consecutive profile planes (normal h, sensor moving by step along the track T) cross the wall (axis u)
    step * |h.T| / |h.u| apart.
    """
    forward = np.gradient(sensors, axis=0)  # per pose: step along the track
    along = np.abs(np.einsum("ij,ij->i", normals, forward))
    hu = np.abs(normals @ f.u)
    stripe = np.where(hu > 1e-6, along / np.maximum(hu, 1e-6), np.inf)
    usable = hu > 0.1
    spacing = float(np.median(stripe[usable])) if usable.any() and np.isfinite(stripe[usable]).any() else 0.0
    m = int(np.clip(np.ceil(spacing / (cell / 2)), 1, 8)) if np.isfinite(spacing) else 1
    if m == 1 or len(sensors) < 2:
        return sensors, normals, stripe
    x = np.arange(len(sensors))
    fine = np.linspace(0, len(sensors) - 1, (len(sensors) - 1) * m + 1)
    dense = np.column_stack([np.interp(fine, x, sensors[:, k]) for k in range(3)])
    dense_n = np.column_stack([np.interp(fine, x, normals[:, k]) for k in range(3)])
    dense_n /= np.linalg.norm(dense_n, axis=1, keepdims=True)
    return dense, dense_n, np.interp(fine, x, stripe)


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
