"""The ground: a gently sloping, undulating street with a cambered road, curbs, sidewalks and a cross street.

Heights are an analytic function of (x, y) in the local frame; the ground mesh samples it on a grid that has
lines just either side of every curb so that the curb is a near-vertical step. The truth (ground lines of the
façades) is evaluated from the same function.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import GROUND, Materials, MeshBuilder

CURB_RUN = 0.01  # horizontal run of the curb face (m): the step is near vertical
SIDEWALK_FALL = 0.015  # sidewalks fall 1.5 % toward the curb (drainage)


@dataclass
class Terrain:
    length: float
    slope: float
    amps: np.ndarray
    wavelengths: np.ndarray
    phases: np.ndarray
    camber: float
    road_half: float
    curb: float
    sidewalk: dict  # side (+1 = y > 0, -1 = y < 0) -> width (m)
    cross: tuple | None = None  # (side, x0, x1): a cross street opening on that side

    def base(self, x) -> np.ndarray:
        """Height of the street axis at x: slope plus small undulations."""
        x = np.asarray(x, float)
        wave = sum(a * np.sin(2 * np.pi * x / w + p) for a, w, p in zip(self.amps, self.wavelengths, self.phases))
        return self.slope * x + wave

    def in_cross(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self.cross is None:
            return np.zeros(np.broadcast(x, y).shape, bool)
        side, x0, x1 = self.cross
        return (np.sign(y) == side) & (np.abs(y) > self.road_half) & (x > x0 + CURB_RUN / 2) & (x < x1 - CURB_RUN / 2)

    def z(self, x, y) -> np.ndarray:
        """Ground height at (x, y)."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        ay = np.abs(y)
        road = -self.camber * np.minimum(ay, self.road_half)
        sw = np.where(y >= 0, self.sidewalk[1], self.sidewalk[-1])
        walk = (-self.camber * self.road_half + self.curb
                + SIDEWALK_FALL * np.clip(ay - self.road_half, 0.0, sw))
        on_walk = ay > self.road_half + CURB_RUN / 2
        cross = self.in_cross(x, y)
        flat_road = np.full_like(road, -self.camber * self.road_half)
        rel = np.where(cross, flat_road, np.where(on_walk, walk, road))
        return self.base(x) + rel

    def is_road(self, x, y) -> np.ndarray:
        return (np.abs(y) <= self.road_half + CURB_RUN / 2) | self.in_cross(x, y)


def draw_terrain(rng, length: float) -> Terrain:
    """Slope 0-4 % along the street, undulations of a few cm, camber 1.5-2.5 %, curb 0.12-0.15 m."""
    n = 3
    return Terrain(
        length=length,
        slope=float(rng.uniform(0.0, 0.04) * rng.choice([-1, 1])),
        amps=rng.uniform(0.01, 0.06, n), wavelengths=rng.uniform(8.0, 45.0, n),
        phases=rng.uniform(0, 2 * np.pi, n),
        camber=float(rng.uniform(0.015, 0.025)),
        road_half=float(rng.uniform(6.0, 8.0)),
        curb=float(rng.uniform(0.12, 0.15)),
        sidewalk={1: float(rng.uniform(2.0, 5.0)), -1: float(rng.uniform(2.0, 5.0))},
    )


def ground_mesh(terrain: Terrain, y_extent: float, mats: Materials, rng) -> MeshBuilder:
    """Height-field triangles over x in [-25, L + 25], |y| <= y_extent, with grid lines at the curbs."""
    rh = terrain.road_half
    xs = [np.arange(-25.0, terrain.length + 25.0 + 1e-9, 1.0)]
    if terrain.cross is not None:
        _, x0, x1 = terrain.cross
        xs.append([x0, x0 + CURB_RUN, x1 - CURB_RUN, x1])
    ys = [np.arange(-y_extent, y_extent + 1e-9, 1.0), [-rh - CURB_RUN, -rh, rh, rh + CURB_RUN]]
    xg = np.unique(np.round(np.concatenate(xs), 4))
    yg = np.unique(np.round(np.concatenate(ys), 4))
    X, Y = np.meshgrid(xg, yg, indexing="ij")
    P = np.stack([X, Y, terrain.z(X, Y)], -1)
    a, b, c, d = P[:-1, :-1], P[1:, :-1], P[1:, 1:], P[:-1, 1:]
    tris = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3), np.stack([a, c, d], -2).reshape(-1, 3, 3)])
    cen = tris.mean(1)
    road = terrain.is_road(cen[:, 0], cen[:, 1])
    curb = ~road & (np.abs(np.abs(cen[:, 1]) - rh) < CURB_RUN)
    asphalt = mats.add(GROUND, refl=float(rng.uniform(0.10, 0.18)), relief=0.004)
    paving = mats.add(GROUND, refl=float(rng.uniform(0.22, 0.40)), relief=0.003)
    stone = mats.add(GROUND, refl=float(rng.uniform(0.30, 0.45)), relief=0.002)
    mb = MeshBuilder()
    mb.add(tris[road], asphalt)
    mb.add(tris[curb], stone)
    mb.add(tris[~road & ~curb], paving)
    return mb
