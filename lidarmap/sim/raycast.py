"""Pulse tracing with Embree (through trimesh) and exact float64 ranges, with multiple returns through leaves.

Embree finds which triangle a ray meets first (float32 internally); the range is then recomputed in float64 from
that triangle's plane, so simulated points sit on the true surfaces to ~1e-9 m before noise is added.

Embree (the ``embreex`` package) exists for x86-64 only. ``LIDARMAP_RAY_ENGINE`` picks the engine: ``auto`` (the
default: Embree when it imports, else trimesh's own tracer), ``embree`` or ``triangle`` (trimesh's numpy tracer with
an R-tree, any machine, slower). Both give the same first triangle except for rays that graze an edge.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
import trimesh

from lidarmap.errors import ConfigError
from lidarmap.sim.mesh import ABSORBER, GLASS, LEAF, SceneMesh

#: Environment variable choosing the ray engine, and its values.
ENGINE_ENV = "LIDARMAP_RAY_ENGINE"
ENGINES = ("auto", "embree", "triangle")

STEP = 1e-3  # restart distance past a leaf so Embree does not report the same leaf again


def _embree_available() -> bool:
    try:
        import embreex  # noqa: F401
    except ImportError:
        return False
    return True


def ray_engine(name: str | None = None) -> str:
    """The engine to use, "embree" or "triangle", from ``name`` or ``LIDARMAP_RAY_ENGINE`` (default "auto")."""
    choice = (name or os.environ.get(ENGINE_ENV) or "auto").strip().lower()
    if choice not in ENGINES:
        raise ConfigError(f"{ENGINE_ENV}={choice!r}: use one of {', '.join(ENGINES)}")
    if choice == "triangle":
        return choice
    if _embree_available():
        return "embree"
    if choice == "embree":
        raise ConfigError(f"{ENGINE_ENV}=embree but embreex is not installed (x86-64 only); "
                          "use auto or triangle")
    return "triangle"


def intersector(mesh: trimesh.Trimesh, engine: str) -> Any:
    """trimesh's ray intersector of ``engine`` ("embree" or "triangle") for ``mesh``."""
    if engine == "embree":
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    else:
        from trimesh.ray.ray_triangle import RayMeshIntersector
    return RayMeshIntersector(mesh)


@dataclasses.dataclass
class Returns:
    """Returns of traced pulses, grouped by pulse and ordered by range.

    ``ray``/``tri``/``range``/``return_number`` have one entry per return; ``number_of_returns`` too (the
    pulse's total). ``stop_tri``/``stop_range`` have one entry per pulse: the surface that ended it (an opaque
    surface or an absorber; -1 when it left the scene or ran out of range) -- used for visibility truth.
    """

    ray: np.ndarray
    tri: np.ndarray
    range: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    stop_tri: np.ndarray
    stop_range: np.ndarray


class Tracer:
    """Casts rays against one :class:`SceneMesh` (local frame) with ``engine`` (see :func:`ray_engine`).

    ``seed`` seeds the per-pulse draws that decide whether glass returns a pulse: calls to :meth:`trace` in the
    same order give the same draws, so a campaign is deterministic.
    """

    def __init__(self, scene: SceneMesh, seed: int | list[int] = 0, engine: str | None = None):
        self.scene = scene
        self.engine = ray_engine(engine)
        self._glass_draws = np.random.default_rng(seed)
        self._has_glass = bool((scene.behaviour == GLASS).any())
        tris = scene.triangles
        n = len(tris)
        mesh = trimesh.Trimesh(vertices=tris.reshape(-1, 3), faces=np.arange(3 * n).reshape(n, 3), process=False,
                               validate=False)
        self._intersector = intersector(mesh, self.engine)
        normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        self.normal = normal / np.where(length > 0, length, 1.0)
        self.plane_offset = np.einsum("ij,ij->i", self.normal, tris[:, 0])

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray,
                  start: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """First triangle beyond ``start`` metres along each ray and its exact range (inf when none)."""
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        start = np.broadcast_to(np.asarray(start, dtype=np.float64), (len(origins),))
        if len(origins) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        tri = np.asarray(self._intersector.intersects_first(origins + dirs * start[:, None], dirs), dtype=np.int64)
        rng = np.full(len(origins), np.inf)
        hit = tri >= 0
        n = self.normal[tri[hit]]
        denom = np.einsum("ij,ij->i", n, dirs[hit])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.plane_offset[tri[hit]] - np.einsum("ij,ij->i", n, origins[hit])) / denom
        # grazing hits have no stable plane intersection: keep Embree's verdict at the start distance
        t = np.where(np.isfinite(t), np.maximum(t, start[hit]), start[hit])
        rng[hit] = t
        return tri, rng

    def trace(self, origins: np.ndarray, dirs: np.ndarray, max_range: float, max_returns: int = 5,
              min_separation: float = 1.0, max_steps: int = 16) -> Returns:
        """Follow each pulse through leaves until an opaque surface, an absorber, the range limit or 5 returns.

        A leaf reflects part of the pulse (a return) and lets the rest through; surfaces closer than
        ``min_separation`` to the previous return merge with it (no new return), as in a real receiver. Glass
        returns a pulse (which ends there) when the pulse's draw falls under the pane's ``return_fraction``;
        otherwise the pulse passes without a return (one draw per pulse, whatever it meets).
        """
        dirs = np.asarray(dirs, dtype=np.float64)
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        n = len(origins)
        start = np.zeros(n)
        last = np.full(n, -np.inf)
        count = np.zeros(n, np.int64)
        stop_tri = np.full(n, -1, np.int64)
        stop_range = np.full(n, np.inf)
        active = np.arange(n)
        draw = self._glass_draws.random(n) if self._has_glass else np.zeros(n)
        rays, tris, ranges = [], [], []
        for _ in range(max_steps):
            if len(active) == 0:
                break
            tri, t = self.first_hit(origins[active], dirs[active], start[active])
            ok = (tri >= 0) & (t <= max_range)
            active, tri, t = active[ok], tri[ok], t[ok]
            behaviour = self.scene.behaviour[tri]
            passes = (behaviour == GLASS) & (draw[active] >= self.scene.return_fraction[tri])
            absorbed = behaviour == ABSORBER
            separate = (t - last[active]) >= min_separation
            record = ~absorbed & ~passes & separate
            rays.append(active[record])
            tris.append(tri[record])
            ranges.append(t[record])
            last[active[record]] = t[record]
            count[active[record]] += 1
            stops = (behaviour != LEAF) & ~passes
            stop_tri[active[stops]] = tri[stops]
            stop_range[active[stops]] = t[stops]
            go_on = ((behaviour == LEAF) & (count[active] < max_returns)) | passes
            start[active[go_on]] = t[go_on] + STEP
            active = active[go_on]
        ray = np.concatenate(rays) if rays else np.zeros(0, np.int64)
        order = np.lexsort((np.concatenate(ranges) if ranges else np.zeros(0), ray))
        ray = ray[order]
        rng = (np.concatenate(ranges) if ranges else np.zeros(0))[order]
        tri = (np.concatenate(tris) if tris else np.zeros(0, np.int64))[order]
        first = np.searchsorted(ray, ray, side="left")
        return_number = (np.arange(len(ray)) - first + 1).astype(np.uint8)
        number = count[ray].astype(np.uint8)
        return Returns(ray=ray, tri=tri, range=rng, return_number=return_number, number_of_returns=number,
                       stop_tri=stop_tri, stop_range=stop_range)
