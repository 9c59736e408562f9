"""Exact point-to-triangle-mesh distances without spatial-index extras (no rtree): for tests and benchmarks.

Candidates come from a KD-tree over samples spread on every triangle at most ``spacing`` apart; any triangle
that could be closer than the best candidate has a sample within (best sample distance + spacing), so the
k-nearest samples are widened until that ball is covered. The result is exact, not approximate.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from points p (N, 3) to triangles (a, b, c) (N, 3 each), row by row (Ericson's region test)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_face, w_face = vb / denom, vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    closest = a + v_face[:, None] * ab + w_face[:, None] * ac
    regions = [
        ((d1 <= 0) & (d2 <= 0), a),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[:, None] * ab),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[:, None] * ac),
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + t_bc[:, None] * (c - b)),
    ]
    done = np.zeros(len(p), bool)
    for mask, point in regions:
        use = mask & ~done
        closest[use] = point[use]
        done |= use
    closest = np.where(np.isfinite(closest), closest, a)  # degenerate triangles: fall back to a corner
    return np.linalg.norm(p - closest, axis=1)


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", x, y)


class MeshDistance:
    """Distances from points to a fixed set of triangles (T, 3, 3)."""

    def __init__(self, triangles: np.ndarray, spacing: float = 0.5):
        self.triangles = np.asarray(triangles, dtype=np.float64)
        self.spacing = spacing
        samples, owner = _surface_samples(self.triangles, spacing)
        self._owner = owner
        self._tree = cKDTree(samples)

    def __call__(self, points: np.ndarray, k: int = 32) -> tuple[np.ndarray, np.ndarray]:
        """Distance (N,) of each point to the mesh and the index of a closest triangle."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        dist = np.full(len(points), np.inf)
        tri = np.full(len(points), -1, np.int64)
        todo = np.arange(len(points))
        while len(todo):
            kk = min(k, self._tree.n)
            sample_d, sample_i = self._tree.query(points[todo], k=kk)
            sample_d, sample_i = sample_d.reshape(len(todo), kk), sample_i.reshape(len(todo), kk)
            cand = self._owner[sample_i]  # (M, k) triangle ids (repeats are harmless)
            rows = np.repeat(np.arange(len(todo)), kk)
            t = self.triangles[cand.ravel()]
            d = point_triangle_distance(points[todo][rows], t[:, 0], t[:, 1], t[:, 2]).reshape(len(todo), kk)
            best = np.argmin(d, axis=1)
            dist[todo] = d[np.arange(len(todo)), best]
            tri[todo] = cand[np.arange(len(todo)), best]
            # the ball (nearest sample + spacing) must lie within the k samples examined, else look further
            covered = (sample_d[:, -1] > sample_d[:, 0] + self.spacing) | (kk == self._tree.n)
            todo = todo[~covered]
            k *= 4
        return dist, tri


def _surface_samples(triangles: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on each triangle on a barycentric grid whose step is at most ``spacing``."""
    edges = np.stack([triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 1],
                      triangles[:, 0] - triangles[:, 2]], 1)
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(int)
    out, owner = [], []
    for n in np.unique(steps):  # one vectorised batch per subdivision level
        ids = np.flatnonzero(steps == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j) <= n
        u, v = (i[keep] / n), (j[keep] / n)
        t = triangles[ids]
        pts = t[:, None, 0] + u[None, :, None] * (t[:, None, 1] - t[:, None, 0]) \
            + v[None, :, None] * (t[:, None, 2] - t[:, None, 0])
        out.append(pts.reshape(-1, 3))
        owner.append(np.repeat(ids, len(u)))
    return np.concatenate(out), np.concatenate(owner)
