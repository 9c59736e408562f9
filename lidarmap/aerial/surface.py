"""Local surface geometry of a point set: k nearest neighbours, sample spacing, local planes (PCA) and the points on
flat local surfaces. Shared by the geometric and the learned upsampler."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree


def knn(xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the k nearest neighbours of every point (itself first), always 2-D."""
    k = max(1, min(k, len(xyz)))
    dist, idx = cKDTree(xyz).query(xyz, k=k, workers=-1)
    return dist.reshape(len(xyz), k), idx.reshape(len(xyz), k)


def local_spacing(dist: np.ndarray, idx: np.ndarray, k: int = 8) -> np.ndarray:
    """Sample spacing around each point from its k-NN distances (itself in column 0): sqrt(pi r_k² / k), the side of
    the square each point stands for on a surface, then the median over the neighbourhood (robust at edges and for
    isolated points, which take their neighbours' spacing)."""
    kk = min(k, dist.shape[1] - 1)
    if kk < 1:
        return np.zeros(len(dist))
    raw = np.sqrt(math.pi / kk) * dist[:, kk]
    return np.median(raw[idx], axis=1)


def local_planes(xyz: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA plane of every point's neighbourhood ``idx`` (N, k): centroid (N, 3), unit normal (N, 3) and RMS
    residual (N,)."""
    nb = xyz[idx]
    centroid = nb.mean(axis=1)
    centred = nb - centroid[:, None]
    cov = np.einsum("nki,nkj->nij", centred, centred) / idx.shape[1]
    vals, vecs = np.linalg.eigh(cov)
    return centroid, vecs[:, :, 0], np.sqrt(np.maximum(vals[:, 0], 0.0))


def area_per_point(xyz: np.ndarray, k: int = 8) -> np.ndarray:
    """Surface area (m²) each point stands for: pi r_k² / k (r_k the distance to its k-th neighbour), median over
    its k neighbours. On a surface sampled at density rho this is 1 / rho."""
    dist, idx = knn(xyz, k + 1)
    return local_spacing(dist, idx, k) ** 2


def seed_planes(xyz: np.ndarray, cand: np.ndarray, centroid: np.ndarray, normal: np.ndarray, rms: np.ndarray,
                plane_tolerance: float, max_plane_rms: float) -> tuple:
    """Per seed (``cand[:, 0]``, its neighbours in the other columns): the flattest neighbourhood plane among its
    own and its neighbours' (:func:`local_planes`) that the seed lies on (within ``plane_tolerance`` or 3 RMS).
    Returns that plane's centroid, normal, the tolerance used and ``flat``: whether such a plane exists with an
    RMS residual of at most ``max_plane_rms`` (False on clutter, vegetation, noise)."""
    p = xyz[cand[:, 0]]
    off = np.abs(np.einsum("skd,skd->sk", normal[cand], p[:, None] - centroid[cand]))
    tol_k = np.maximum(plane_tolerance, 3.0 * rms[cand])
    score = np.where(off <= tol_k, rms[cand], np.inf)
    choice = np.argmin(score, axis=1)
    rows = np.arange(len(cand))
    best = cand[rows, choice]
    flat = np.isfinite(score[rows, choice]) & (rms[best] <= max_plane_rms)
    return centroid[best], normal[best], tol_k[rows, choice], flat


def flat_points(xyz: np.ndarray, neighbours: int = 12, plane_tolerance: float = 0.08,
                max_plane_rms: float = 0.08) -> np.ndarray:
    """True for points that lie on a flat local surface (:func:`seed_planes`); the geometric upsampler seeds only
    around these, and the learned one can be told to (``LearnedUpsampler.flat_only``)."""
    if len(xyz) < 3:
        return np.zeros(len(xyz), dtype=bool)
    _, idx = knn(xyz, neighbours + 1)
    centroid, normal, rms = local_planes(xyz, idx)
    return seed_planes(xyz, idx, centroid, normal, rms, plane_tolerance, max_plane_rms)[3]
