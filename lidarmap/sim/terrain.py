"""Sloped, gently undulating terrain as a regular triangulated grid, with exact heights on the mesh."""

from __future__ import annotations

import dataclasses

import numpy as np

from lidarmap.sim.mesh import CLASS_GROUND, KIND, Labels, Soup


@dataclasses.dataclass
class Terrain:
    """z(x, y) = base + slope . (x, y) + sum of sine waves, sampled on a grid of ``cell`` metres (local frame).

    Heights between grid nodes follow the triangulated mesh exactly (each cell split along its (0,0)-(1,1)
    diagonal), so :meth:`height` is the true ground of every simulated point.
    """

    x0: float
    y0: float
    nx: int
    ny: int
    cell: float
    base: float
    slope: tuple[float, float]
    waves: list[tuple[float, float, float, float]]  # amplitude, kx, ky, phase

    @classmethod
    def random(cls, rng: np.random.Generator, bounds: tuple[float, float, float, float],
               cell: float = 1.0) -> "Terrain":
        x0, y0, x1, y1 = bounds
        grade = rng.uniform(0.01, 0.03)  # 1-3 % plane slope in a random direction
        direction = rng.uniform(0, 2 * np.pi)
        waves = []
        for _ in range(3):
            wavelength = rng.uniform(50.0, 120.0)
            heading = rng.uniform(0, 2 * np.pi)
            k = 2 * np.pi / wavelength
            waves.append((float(rng.uniform(0.05, 0.15)), float(k * np.cos(heading)), float(k * np.sin(heading)),
                          float(rng.uniform(0, 2 * np.pi))))
        return cls(x0=float(np.floor(x0)), y0=float(np.floor(y0)), nx=int(np.ceil((x1 - x0) / cell)) + 1,
                   ny=int(np.ceil((y1 - y0) / cell)) + 1, cell=cell, base=float(rng.uniform(40.0, 120.0)),
                   slope=(float(grade * np.cos(direction)), float(grade * np.sin(direction))), waves=waves)

    def analytic(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        z = self.base + self.slope[0] * x + self.slope[1] * y
        for amp, kx, ky, phase in self.waves:
            z = z + amp * np.sin(kx * x + ky * y + phase)
        return z

    def node_xy(self) -> tuple[np.ndarray, np.ndarray]:
        xs = self.x0 + self.cell * np.arange(self.nx)
        ys = self.y0 + self.cell * np.arange(self.ny)
        return xs, ys

    def node_z(self) -> np.ndarray:
        """Node heights (ny, nx)."""
        xs, ys = self.node_xy()
        gx, gy = np.meshgrid(xs, ys, indexing="xy")
        return self.analytic(gx, gy)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0, self.x0 + self.cell * (self.nx - 1), self.y0 + self.cell * (self.ny - 1))

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Mesh height at (N, 2) points (clamped to the grid)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        z = self._z_cache()
        fx = np.clip((xy[:, 0] - self.x0) / self.cell, 0, self.nx - 1 - 1e-9)
        fy = np.clip((xy[:, 1] - self.y0) / self.cell, 0, self.ny - 1 - 1e-9)
        i, j = np.floor(fx).astype(int), np.floor(fy).astype(int)
        u, v = fx - i, fy - j
        z00, z10, z01, z11 = z[j, i], z[j, i + 1], z[j + 1, i], z[j + 1, i + 1]
        lower = u >= v  # triangle (00, 10, 11) else (00, 11, 01)
        return np.where(lower, z00 + u * (z10 - z00) + v * (z11 - z10), z00 + v * (z01 - z00) + u * (z11 - z01))

    def gradient(self, xy: np.ndarray, step: float = 0.5) -> np.ndarray:
        """Horizontal gradient (N, 2) of the mesh height by central differences over ``step`` metres."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        dx = np.array([step, 0.0])
        dy = np.array([0.0, step])
        gx = (self.height(xy + dx) - self.height(xy - dx)) / (2 * step)
        gy = (self.height(xy + dy) - self.height(xy - dy)) / (2 * step)
        return np.stack([gx, gy], 1)

    def _z_cache(self) -> np.ndarray:
        if not hasattr(self, "_z"):
            self._z = self.node_z()
        return self._z

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (nx*ny, 3) and faces (F, 3) of the terrain grid (local frame), faces oriented up."""
        xs, ys = self.node_xy()
        gx, gy = np.meshgrid(xs, ys, indexing="xy")
        verts = np.column_stack([gx.ravel(), gy.ravel(), self._z_cache().ravel()])
        idx = np.arange(self.nx * self.ny).reshape(self.ny, self.nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        return verts, faces

    def soup(self, colour_of: "callable") -> Soup:
        """Labelled terrain triangles; ``colour_of(centroids (N, 2)) -> (rgb (N, 3), reflectance (N,))``."""
        verts, faces = self.mesh()
        tris = verts[faces]
        rgb, refl = colour_of(tris.mean(axis=1)[:, :2])
        soup = Soup()
        soup.add(tris, Labels(classification=CLASS_GROUND, kind=KIND["ground"], rgb=rgb, reflectance=refl),
                 index=np.arange(len(tris)))
        return soup

    @classmethod
    def from_json(cls, doc: dict) -> "Terrain":
        return cls(x0=doc["x0"], y0=doc["y0"], nx=doc["nx"], ny=doc["ny"], cell=doc["cell"], base=doc["base"],
                   slope=tuple(doc["slope"]), waves=[tuple(w) for w in doc["waves"]])

    def to_json(self) -> dict:
        return {"x0": self.x0, "y0": self.y0, "nx": self.nx, "ny": self.ny, "cell": self.cell, "base": self.base,
                "slope": list(self.slope), "waves": [list(w) for w in self.waves]}
