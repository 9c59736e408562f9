"""Façade extraction, part 3: what the scanner could not see (§2.4) — ray tracing from the trajectory.

All inputs are in façade coordinates (s, t, d) of one façade: the points and the sensor position at each point's GPS
time (``Trajectory.position_at``). Three masks on the façade grid:

* :func:`occlusion_mask`: cells behind something — for every point measured in front of the main plane (car, tree,
  balcony, sign), the ray sensor -> point is extended to the plane d = 0 and the cells around the hit are marked, with
  a radius that grows with the extension factor λ = d_sensor / (d_sensor - d_point) (the shadow of a sample of
  radius r at the occluder is a disc of radius λ r on the wall).
* :func:`through_cells`: cells the laser went *through* — points far behind the plane (interiors seen through glass)
  mark the cell where their ray crossed the plane: an opening, not a wall, and not an occluder.
* :func:`reach_mask`: cells some trajectory position could have measured (within the campaign's range, elevation
  angles and incidence); cells outside are occluded by the scanner's limits.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from lidarmap.facade.layers import cell_index, square

if TYPE_CHECKING:  # pragma: no cover
    from lidarmap.facade.params import FacadeParams


def sample_spacing(sdt: np.ndarray, max_points: int = 20000, rng: np.random.Generator | None = None) -> float:
    """Median nearest-neighbour distance of points (a subsample of them): their sampling spacing."""
    if len(sdt) < 2:
        return 0.0
    rng = rng or np.random.default_rng(0)
    sample = sdt if len(sdt) <= max_points else sdt[rng.choice(len(sdt), size=max_points, replace=False)]
    dist, _ = cKDTree(sample).query(sample, k=2)
    return float(np.median(dist[:, 1]))


def project_rays(points_sdt: np.ndarray, sensors_sdt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays sensor -> point (extended or not) cross the plane d = 0.

    Returns (s, t, λ) with λ = d_sensor / (d_sensor - d_point): the crossing is sensor + λ (point - sensor); λ > 1
    for points in front of the plane, λ < 1 behind it. Rays parallel to the plane or from behind it give NaN.
    """
    p = np.asarray(points_sdt, dtype=np.float64)
    c = np.asarray(sensors_sdt, dtype=np.float64)
    denom = c[:, 2] - p[:, 2]
    ok = (c[:, 2] > 0) & (denom > 1e-9)
    lam = np.where(ok, c[:, 2] / np.where(ok, denom, 1.0), np.nan)
    s = c[:, 0] + lam * (p[:, 0] - c[:, 0])
    t = c[:, 1] + lam * (p[:, 1] - c[:, 1])
    return s, t, lam


def occlusion_mask(points_sdt: np.ndarray, sensors_sdt: np.ndarray, shape: tuple[int, int], s0: float, t0: float,
                   cell: float, params: "FacadeParams", spacing: float | None = None) -> np.ndarray:
    """Cells shadowed by foreground points (see the module doc); ``points_sdt`` are already the foreground points.

    The shadow radius of a point is λ * max(``occluder_radius``, spacing / 2) (``spacing``: the foreground's
    sampling spacing); the mask is closed by ``occlusion_close_cells`` so that neighbouring shadows join.
    """
    mask = np.zeros(shape, dtype=bool)
    if len(points_sdt) == 0:
        return mask
    s, t, lam = project_rays(points_sdt, sensors_sdt)
    ok = np.isfinite(lam) & (lam >= 1.0)
    r0 = max(params.occlusion.occluder_radius, 0.5 * (spacing or 0.0))
    radius_cells = np.clip(np.round(lam * r0 / cell), 0, params.occlusion.occluder_max_radius_cells).astype(np.int64)
    row, col = cell_index(s, t, cell, s0, t0, shape)
    ok &= row >= 0
    for r in np.unique(radius_cells[ok]):
        sel = ok & (radius_cells == r)
        hits = np.zeros(shape, dtype=bool)
        hits[row[sel], col[sel]] = True
        if r > 0:
            hits = ndimage.binary_dilation(hits, structure=square(int(r)))
        mask |= hits
    if params.occlusion.occlusion_close_cells > 0:
        k = params.occlusion.occlusion_close_cells
        mask = ndimage.binary_closing(np.pad(mask, k), structure=square(k))[k:-k, k:-k] | mask
    return mask


def through_cells(points_sdt: np.ndarray, sensors_sdt: np.ndarray, shape: tuple[int, int], s0: float, t0: float,
                  cell: float) -> np.ndarray:
    """Per-cell count of rays that crossed the plane there and hit something behind it (seen through)."""
    counts = np.zeros(shape, dtype=np.int64)
    if len(points_sdt) == 0:
        return counts
    s, t, lam = project_rays(points_sdt, sensors_sdt)
    ok = np.isfinite(lam) & (lam > 0) & (lam < 1.0)
    row, col = cell_index(s, t, cell, s0, t0, shape)
    ok &= row >= 0
    np.add.at(counts, (row[ok], col[ok]), 1)
    return counts


def reach_limits(points_xyz: np.ndarray, sensors_xyz: np.ndarray,
                 quantile: float = 0.995) -> tuple[float, float, float]:
    """The campaign's scanner limits measured on its own points: (max range, min and max elevation angle, radians)."""
    v = np.asarray(points_xyz) - np.asarray(sensors_xyz)
    rng_ = np.linalg.norm(v, axis=1)
    ok = rng_ > 1e-6
    if not ok.any():
        return 0.0, 0.0, 0.0
    elev = np.arcsin(np.clip(v[ok, 2] / rng_[ok], -1, 1))
    return (float(np.quantile(rng_[ok], quantile)), float(np.quantile(elev, 1 - quantile)),
            float(np.quantile(elev, quantile)))


def reach_mask(sensor_track_sdt: np.ndarray, shape: tuple[int, int], s0: float, t0: float, cell: float,
               limits: tuple[float, float, float], params: "FacadeParams") -> np.ndarray:
    """Cells that at least one trajectory position in front of the plane could have measured.

    A cell is reachable from a position when it lies within ``limits`` (max range times ``reach_margin``, elevation
    angles widened by ``reach_angle_margin_deg``) and the ray meets the wall at less than ``max_incidence_deg``.
    """
    rows, cols = shape
    track = np.asarray(sensor_track_sdt, dtype=np.float64)
    track = track[track[:, 2] > 0] if len(track) else track
    if len(track) == 0:
        return np.zeros(shape, dtype=bool)
    max_range, elev_lo, elev_hi = limits
    max_range *= params.occlusion.reach_margin
    margin = np.radians(params.occlusion.reach_angle_margin_deg)
    sin_lo, sin_hi = np.sin(max(elev_lo - margin, -np.pi / 2)), np.sin(min(elev_hi + margin, np.pi / 2))
    cos_inc = np.cos(np.radians(params.occlusion.max_incidence_deg))
    s = s0 + (np.arange(cols) + 0.5) * cell
    t = t0 + (np.arange(rows) + 0.5) * cell
    ss, tt = np.meshgrid(s, t)
    cells = np.column_stack([ss.ravel(), tt.ravel()])
    # only positions that can reach the façade's bounding box at all
    near = (np.abs(track[:, 2]) <= max_range) & (track[:, 0] >= s[0] - max_range) & (track[:, 0] <= s[-1] + max_range)
    track = track[near]
    out = np.zeros(len(cells), dtype=bool)
    if len(track) == 0:
        return out.reshape(shape)
    chunk = max(1, 2_000_000 // len(track))
    for a in range(0, len(cells), chunk):
        ds = cells[a:a + chunk, 0:1] - track[None, :, 0]
        dt = cells[a:a + chunk, 1:2] - track[None, :, 1]
        dd = track[None, :, 2]
        r = np.sqrt(ds * ds + dt * dt + dd * dd)
        sin_e = dt / r
        ok = (r <= max_range) & (sin_e >= sin_lo) & (sin_e <= sin_hi) & (dd / r >= cos_inc)
        out[a:a + chunk] = ok.any(axis=1)
    return out.reshape(shape)
