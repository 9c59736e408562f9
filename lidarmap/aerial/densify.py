"""Densification (paper §3.3, Algorithm 1): recursive median split with halos around a pluggable upsampler.

One building's points (after segmentation) come in; the same points (minus statistical outliers) plus new points
on the building's surfaces come out, so that voxels and meshes of sparse walls and roofs are complete. The stage:

1. works in a :class:`~lidarmap.frame.LocalFrame` around the points (float64; float32 only inside the network);
2. removes outliers first (:func:`remove_outliers`): upsampling a noise point multiplies it (paper §4.2);
3. decides how many new points every kept point gets, from the area each point stands for
   (:func:`area_per_point`, :func:`new_point_counts`): ``"uniform"`` fills the sparsest surfaces first, up to one
   target density for the whole building (``ratio`` x input points in all); ``"proportional"`` gives every point
   ``ratio - 1`` new ones. Counts are per point, computed once for the whole building, so they do not jump at
   split planes;
4. splits the points with paper Algorithm 1 (:func:`median_split`: cells of fewer than ``max_leaf`` points go to the
   upsampler, fewer than ``min_leaf`` are returned as is, else split at the median of the longest axis). Unlike the
   paper, every leaf sees a *halo* of ``halo`` metres beyond its cell as context, points within ``halo / 2`` of the
   cell also seed new points, and a leaf keeps only the new points inside its own cell. New points near a split
   plane therefore come from both sides exactly as if there were no split: no seam (paper Fig. 8);
5. upsamples every leaf with an :class:`Upsampler`: :class:`GeometricUpsampler` (here; plane- and edge-aware, never
   bridges a gap wider than the local spacing, so window openings stay open) or the learned
   :class:`lidarmap.aerial.upsampler.LearnedUpsampler` (a small implicit patch model in the spirit of SAPCU);
6. gives new points the colour of their input neighbours by inverse-distance weighting (:func:`transfer_colour`).

Stage API (arrays and small dataclasses, no files)::

    densify(xyz, rgb=None, params=DensifyParams(), seed=0, upsampler=None) -> DensifyResult
    remove_outliers(xyz, k, std_ratio) -> keep mask
    area_per_point(xyz, k) -> (N,) m² per point
    new_point_counts(area, ratio, distribution, max_new, rng) -> (counts, target density)
    median_split(xyz, max_leaf, min_leaf, halo) -> list[Leaf]
    transfer_colour(src_xyz, src_rgb, dst_xyz, k, power) -> (M, 3) uint8
    noise_amplification(dist_in, dist_out, tau) -> dict      # the measured noise metric (needs a true surface)
    seam_ratios(new_split, new_reference, leaves, band) -> dict   # the seam check (vs an unsplit run)

Per-point labels follow with ``labels[result.source_index]`` (new points take their nearest input point's).
"""

from __future__ import annotations

import dataclasses
import math
import time
import typing
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from lidarmap.aerial.surface import (
    area_per_point,
    knn,
    local_planes,
    local_spacing,
    seed_planes,
)
from lidarmap.config import check_params
from lidarmap.errors import ConfigError, InputError
from lidarmap.frame import LocalFrame

__all__ = ["DensifyParams", "DensifyResult", "Leaf", "Upsampler", "GeometricUpsampler", "UPSAMPLERS", "DISTRIBUTIONS",
           "densify", "make_upsampler", "remove_outliers", "area_per_point", "new_point_counts", "median_split",
           "transfer_colour", "noise_amplification", "seam_ratios", "local_spacing", "local_planes", "seed_planes"]

UPSAMPLERS = ("geometric", "learned")
DISTRIBUTIONS = ("uniform", "proportional")


@dataclasses.dataclass(frozen=True)
class DensifyParams:
    """Parameters of ``lidarmap densify`` (``[densify]`` table of a config file). Lengths in metres.

    Amount and placement
        ratio (2.0): output points / kept input points (paper: 2x); 1 adds nothing (outlier removal only).
        distribution ("uniform"): how the new points are spread. "uniform": sparse surfaces are filled first, up to
            one target density for the whole building (water-filling; dense roofs may get no new points while
            sparse walls get many); "proportional": every point gets ``ratio - 1`` new ones (local density x ratio,
            as the paper intended, but without its seams).
        max_new_per_point (16): at most this many new points around one input point (limits extrapolation from
            very sparse samples; with "uniform" the target density rises until the budget is spent).
        density_k (8): neighbours for the area each point stands for (pi r_k² / k, median over the neighbours).
    Recursive median split (paper Algorithm 1)
        max_leaf (5000): cells with fewer points than this go to the upsampler (paper: 5000) ...
        min_leaf (100): ... cells with fewer than this are returned as is (paper: 100).
        halo (2.0): each leaf sees the points up to this far beyond its cell (along each axis) as context; those
            within ``halo / 2`` also seed new points; only new points inside the cell are kept. Must exceed the
            reach of the upsampler (about ``gap_factor`` x the local spacing).
    Upsampler
        upsampler ("geometric"): "geometric" (:class:`GeometricUpsampler`) or "learned" (the shipped
            :class:`lidarmap.aerial.upsampler.LearnedUpsampler`). Geometric is the default: on simulated buildings its
            new points are 5x closer to the true surface, it puts fewer of them into window openings, multiplies
            no noise and is 3.5x faster (docs/densify.md, bench_densify).
        weights (""): weights file of the learned upsampler (``scripts/train_upsampler.py``); "" = the shipped one.
        neighbours (12): neighbours of a point for its local plane and for the triangles new points are drawn in.
        gap_factor (1.5): new points are drawn in triangles of input points whose edges are all shorter than this
            x the local spacing: gaps wider than that (window openings, roof edges) are never bridged.
        plane_tolerance (0.08): a neighbour within this of a point's plane lies on the same surface (edge-aware:
            points across a ridge or a roof-wall edge are not used).
        max_plane_rms (0.08): points whose best local plane has a larger RMS residual (vegetation, clutter, noise)
            get no new points.
    Outliers (removed before upsampling)
        outlier_k (12): neighbours of the outlier score; 0 turns outlier removal off.
        outlier_std (3.0): a point is an outlier when its score exceeds the mean score by more than this many
            standard deviations. The score is log(its mean distance to the k neighbours / the largest such mean
            distance among those neighbours): local, so sparse walls next to dense roofs survive
            (:func:`remove_outliers`).
    Colour
        colour_k (4): input neighbours whose colours are averaged for a new point ...
        colour_power (2.0): ... with weights 1 / distance ** power.
    """

    section = "densify"
    constraints: ClassVar[dict[str, str]] = {
        "ratio": ">= 0",
        "distribution": "in uniform, proportional",
        "max_new_per_point": ">= 0",
        "density_k": ">= 0",
        "max_leaf": ">= 0",
        "min_leaf": ">= 0",
        "halo": ">= 0",
        "upsampler": "in geometric, learned",
        "neighbours": ">= 0",
        "gap_factor": ">= 0",
        "plane_tolerance": ">= 0",
        "max_plane_rms": ">= 0",
        "outlier_k": ">= 0",
        "outlier_std": ">= 0",
        "colour_k": ">= 0",
        "colour_power": ">= 0",
    }

    ratio: float = 2.0
    distribution: str = "uniform"
    max_new_per_point: int = 16
    density_k: int = 8
    max_leaf: int = 5000
    min_leaf: int = 100
    halo: float = 2.0
    upsampler: str = "geometric"
    weights: str = ""
    neighbours: int = 12
    gap_factor: float = 1.5
    plane_tolerance: float = 0.08
    max_plane_rms: float = 0.08
    outlier_k: int = 12
    outlier_std: float = 3.0
    colour_k: int = 4
    colour_power: float = 2.0

    def __post_init__(self) -> None:
        check_params(self)
        checks = [
            (math.isfinite(self.ratio) and 1.0 <= self.ratio <= 64.0, "ratio must be in [1, 64]"),
            (self.distribution in DISTRIBUTIONS, f"distribution must be one of {', '.join(DISTRIBUTIONS)}"),
            (self.max_new_per_point >= 1, "max_new_per_point must be >= 1"),
            (self.density_k >= 2, "density_k must be >= 2"),
            (self.max_leaf >= 2 and 0 <= self.min_leaf <= self.max_leaf,
             "need max_leaf >= 2 and 0 <= min_leaf <= max_leaf"),
            (math.isfinite(self.halo) and self.halo >= 0, "halo must be a finite number >= 0"),
            (self.upsampler in UPSAMPLERS, f"upsampler must be one of {', '.join(UPSAMPLERS)}"),
            (self.neighbours >= 3, "neighbours must be >= 3"),
            (self.gap_factor > 0 and self.plane_tolerance > 0 and self.max_plane_rms > 0,
             "gap_factor, plane_tolerance and max_plane_rms must be > 0"),
            (self.outlier_k >= 0 and self.outlier_std > 0, "need outlier_k >= 0 and outlier_std > 0"),
            (self.colour_k >= 1 and self.colour_power >= 0, "need colour_k >= 1 and colour_power >= 0"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"densify parameters: {message}")


@dataclasses.dataclass
class DensifyResult:
    """Output of :func:`densify`.

    xyz: (M, 3) float64 CRS coordinates: the kept input points first (in input order, coordinates untouched), then
        the new points. rgb: (M, 3) uint8 or ``None`` (input colour, then transferred colour). is_new: (M,) bool.
    source_index: (M,) int64 index into the *input* arrays: the point itself, or for a new point its nearest kept
        input point (labels follow with ``labels[source_index]``). stats: counts and timings (see :func:`densify`).
    """

    xyz: np.ndarray
    rgb: np.ndarray | None
    is_new: np.ndarray
    source_index: np.ndarray
    stats: dict

    def __len__(self) -> int:
        return len(self.xyz)


class Upsampler(typing.Protocol):
    """What the median split calls on every leaf.

    ``upsample(xyz, n_new, rng)`` gets the leaf's points with their halo (local frame, float64, (N, 3)) and how many
    new points to place around each of them (``n_new``: (N,) int, 0 for points that are context only) and returns
    the new points (K, 3), K about ``n_new.sum()`` (fewer where the upsampler declines: gaps, non-planar clutter).
    New points must lie near their seed point (within the halo); the caller keeps those inside the leaf's cell.
    """

    name: str

    def upsample(self, xyz: np.ndarray, n_new: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...


# ----------------------------------------------------------------------------------------------------------------------
# Neighbourhoods


def new_point_counts(area: np.ndarray, ratio: float, distribution: str, max_new: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """How many new points each input point gets, and the target surface density (points/m²).

    "uniform": water-filling. Find the density rho such that sum_i clip(rho a_i - 1, 0, max_new) = (ratio - 1) N,
    where a_i = ``area[i]``: every point whose area holds fewer than rho points gets the difference, so the output
    density is rho wherever the input was sparser and unchanged where it was denser. "proportional": ratio - 1
    each (target density reported as NaN). Fractions are rounded stochastically (``rng``), so the expected total is
    exact and no region is biased.
    """
    n = len(area)
    budget = (ratio - 1.0) * n
    if n == 0 or budget <= 0:
        return np.zeros(n, dtype=np.int64), float("nan")
    if distribution == "proportional":
        want = np.full(n, min(ratio - 1.0, float(max_new)))
        rho = float("nan")
    else:
        area = np.maximum(np.asarray(area, dtype=np.float64), 1e-12)

        def total(r: float) -> float:
            return float(np.clip(r * area - 1.0, 0.0, max_new).sum())

        lo, hi = 0.0, 1.0 / area.min()
        while total(hi) < budget and hi < 1e12 and total(hi) < max_new * n:
            hi *= 2.0
        for _ in range(60):  # bisection on a monotone piecewise-linear function
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if total(mid) < budget else (lo, mid)
        rho = hi
        want = np.clip(rho * area - 1.0, 0.0, max_new)
    base = np.floor(want)
    counts = base + (rng.random(n) < want - base)
    return counts.astype(np.int64), float(rho)


# ----------------------------------------------------------------------------------------------------------------------
# Outliers


def remove_outliers(xyz: np.ndarray, k: int = 12, std_ratio: float = 3.0) -> np.ndarray:
    """Keep-mask of a local statistical outlier filter (SOR on a density-normalised score).

    d_i is a point's mean distance to its k nearest neighbours; its score is log(d_i / max_j d_j) over those
    neighbours j, and it is an outlier when the score exceeds the mean score of all points by more than
    ``std_ratio`` standard deviations. The classic filter compares d_i with the mean of all d, which removes the
    sparse walls of an airborne scan next to its dense roofs; here a point is only an outlier when it is farther
    from its neighbours than any of them is from theirs: stray returns, not sparse surfaces. (On simulated
    buildings with stray points: ~60 % of the strays go, fewer than 0.1 % of the true points; bench_densify.)
    """
    n = len(xyz)
    if k <= 0 or n <= k + 1:
        return np.ones(n, dtype=bool)
    dist, idx = knn(xyz, k + 1)
    mean_d = np.maximum(dist[:, 1:].mean(axis=1), 1e-9)
    score = np.log(mean_d / mean_d[idx[:, 1:]].max(axis=1))
    spread = score.std()
    if spread <= 0:
        return np.ones(n, dtype=bool)
    return score <= score.mean() + std_ratio * spread


# ----------------------------------------------------------------------------------------------------------------------
# Recursive median split (paper Algorithm 1) with halos


@dataclasses.dataclass
class Leaf:
    """A cell of the median split: ``lo <= x < hi`` per axis (±inf on the outer sides, so the cells partition
    space); ``core``: indices of the points in the cell; ``halo``: indices of the points outside it but within the
    cell grown by ``halo`` along every axis; ``upsample``: False for cells with fewer than ``min_leaf`` points
    (Algorithm 1 returns them as is)."""

    lo: np.ndarray
    hi: np.ndarray
    core: np.ndarray
    halo: np.ndarray
    upsample: bool

    @property
    def context(self) -> np.ndarray:
        return np.concatenate([self.core, self.halo])

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """True for points inside the cell (half-open, like the split)."""
        return _in_cell(xyz, self.lo, self.hi)

    def near(self, xyz: np.ndarray, margin: float) -> np.ndarray:
        """True for points inside the cell grown by ``margin`` along every axis."""
        return _in_cell(xyz, self.lo - margin, self.hi + margin, closed=True)


def _in_cell(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, closed: bool = False) -> np.ndarray:
    upper = xyz <= hi if closed else xyz < hi
    return np.all((xyz >= lo) & upper, axis=1)


def _split_value(values: np.ndarray) -> float | None:
    """The median (paper), moved up to the next distinct value when it equals the minimum (many ties), so both
    sides are non-empty; ``None`` when all values are equal."""
    lo, median = values.min(), float(np.median(values))
    if median > lo:
        return median
    above = values[values > lo]
    return float(above.min()) if len(above) else None


def median_split(xyz: np.ndarray, max_leaf: int = 5000, min_leaf: int = 100, halo: float = 2.0) -> list[Leaf]:
    """Paper Algorithm 1 with halos: split cells of ``max_leaf`` or more points at the median of the longest axis of
    their points' bounding box until they hold fewer; every point ends in exactly one leaf's ``core``. Leaves come in
    depth-first order, lower side first. Each level only looks at its parent's context, so the cost is O(N log N)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    everything = np.arange(n)
    stack = [(np.full(3, -np.inf), np.full(3, np.inf), everything, everything)]
    leaves: list[Leaf] = []
    while stack:
        lo, hi, core, context = stack.pop()
        value = None
        if len(core) >= max_leaf:
            pts = xyz[core]
            axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
            value = _split_value(pts[:, axis])
        if value is None:
            halo_idx = context[~_in_cell(xyz[context], lo, hi)]
            leaves.append(Leaf(lo, hi, core, halo_idx, upsample=len(core) >= min_leaf))
            continue
        children = []
        for lower in (True, False):
            c_lo, c_hi = lo.copy(), hi.copy()
            (c_hi if lower else c_lo)[axis] = value
            children.append((c_lo, c_hi, core[_in_cell(xyz[core], c_lo, c_hi)],
                             context[_in_cell(xyz[context], c_lo - halo, c_hi + halo, closed=True)]))
        stack.extend(reversed(children))  # lower side popped first
    return leaves


# ----------------------------------------------------------------------------------------------------------------------
# Geometric upsampler


@dataclasses.dataclass(frozen=True)
class GeometricUpsampler:
    """Plane- and edge-aware resampling inside the local sample's footprint.

    For a seed point p: among the planes of its neighbours' neighbourhoods (PCA) that p lies on, the flattest one
    (neighbourhoods straddling an edge are never the flattest, so edges are not rounded). Its neighbours on that
    plane and closer than ``gap_factor`` x the local spacing form triangles with p whose three edges are all that
    short; new points are drawn uniformly in the half-size corner (p, mid(p, a), mid(p, b)) of a random such
    triangle and projected onto the plane. Nothing is placed across a gap wider than the local spacing allows
    (windows stay open), beyond the outermost samples (edges stay sharp) or around points without a flat
    neighbourhood (clutter and surviving noise are not amplified).
    """

    neighbours: int = 12
    gap_factor: float = 1.5
    plane_tolerance: float = 0.08
    max_plane_rms: float = 0.08
    spacing_k: int = 8
    name: typing.ClassVar[str] = "geometric"

    def upsample(self, xyz: np.ndarray, n_new: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        xyz = np.asarray(xyz, dtype=np.float64)
        n_new = np.asarray(n_new, dtype=np.int64)
        src = np.flatnonzero(n_new > 0)
        if len(xyz) < 3 or len(src) == 0:
            return np.zeros((0, 3))
        dist, idx = knn(xyz, self.neighbours + 1)
        centroid, normal, rms = local_planes(xyz, idx)
        spacing = local_spacing(dist, idx, self.spacing_k)
        plane_c, plane_n, tol, flat = self._seed_planes(xyz, idx[src], centroid, normal, rms)
        nb = idx[src, 1:]
        pairs_a, pairs_b, pair_ok = self._triangles(xyz, src, nb, plane_c, plane_n, tol, spacing[src])
        n_pairs = pair_ok.sum(axis=1)
        counts = np.where(flat & (n_pairs > 0), n_new[src], 0)
        owner = np.repeat(np.arange(len(src)), counts)
        if len(owner) == 0:
            return np.zeros((0, 3))
        rank = np.floor(rng.random(len(owner)) * n_pairs[owner]).astype(np.int64)
        cum = np.cumsum(pair_ok, axis=1, dtype=np.int16)
        pick = np.empty(len(owner), dtype=np.int64)
        for a in range(0, len(owner), 20000):  # bounded memory: (chunk, pairs) at a time
            sl = slice(a, a + 20000)
            pick[sl] = (cum[owner[sl]] <= rank[sl, None]).sum(axis=1)
        u, v = rng.random((2, len(owner)))
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        p = xyz[src[owner]]
        qa = xyz[nb[owner, pairs_a[pick]]]
        qb = xyz[nb[owner, pairs_b[pick]]]
        new = p + 0.5 * (u[:, None] * (qa - p) + v[:, None] * (qb - p))
        c, nrm = plane_c[owner], plane_n[owner]
        return new - np.einsum("ij,ij->i", new - c, nrm)[:, None] * nrm

    def _seed_planes(self, xyz, cand, centroid, normal, rms):
        return seed_planes(xyz, cand, centroid, normal, rms, self.plane_tolerance, self.max_plane_rms)

    def _triangles(self, xyz, src, nb, plane_c, plane_n, tol, spacing):
        """Valid triangles (seed, a, b): a, b on the seed's plane, all edges shorter than the gap, not degenerate.
        Edge lengths and areas come from the Gram matrix of the neighbour vectors (one small matmul per seed)."""
        gap2 = (self.gap_factor * spacing) ** 2
        rel = xyz[nb] - xyz[src][:, None]
        gram = np.einsum("ski,sli->skl", rel, rel)
        d2 = np.einsum("skk->sk", gram)
        on_plane = np.abs(np.einsum("skd,sd->sk", xyz[nb] - plane_c[:, None], plane_n)) <= tol[:, None]
        valid = on_plane & (d2 <= gap2[:, None]) & (d2 > 0)
        a, b = np.triu_indices(nb.shape[1], 1)
        ga, gb, gab = d2[:, a], d2[:, b], gram[:, a, b]
        ab2 = ga + gb - 2.0 * gab            # |qa - qb|²
        area2 = ga * gb - gab ** 2           # |(qa - p) x (qb - p)|² (Lagrange's identity)
        ok = valid[:, a] & valid[:, b] & (ab2 <= gap2[:, None]) & (area2 > 1e-6 * gap2[:, None] ** 2)
        return a, b, ok


def make_upsampler(params: DensifyParams) -> Upsampler:
    """The upsampler named by ``params.upsampler`` (the learned one loads the shipped weights)."""
    if params.upsampler == "learned":
        from lidarmap.aerial.upsampler import (
            load_upsampler,  # torch only when asked for
        )

        return load_upsampler(params.weights or None)
    return GeometricUpsampler(neighbours=params.neighbours, gap_factor=params.gap_factor,
                              plane_tolerance=params.plane_tolerance, max_plane_rms=params.max_plane_rms)


# ----------------------------------------------------------------------------------------------------------------------
# Colour


def transfer_colour(src_xyz: np.ndarray, src_rgb: np.ndarray, dst_xyz: np.ndarray, k: int = 4,
                    power: float = 2.0) -> np.ndarray:
    """Colour of ``dst_xyz`` from the ``k`` nearest source points, weighted by 1 / distance ** power (a point that
    coincides with a source point takes its colour). Vectorised; (M, 3) uint8."""
    src_rgb = np.asarray(src_rgb)
    if len(dst_xyz) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    if len(src_xyz) == 0:
        raise InputError("no source points to take colours from")
    k = max(1, min(k, len(src_xyz)))
    dist, idx = cKDTree(src_xyz).query(dst_xyz, k=k)
    dist, idx = dist.reshape(len(dst_xyz), k), idx.reshape(len(dst_xyz), k)
    exact = dist <= 1e-9
    with np.errstate(divide="ignore"):
        w = np.where(exact.any(axis=1, keepdims=True), exact.astype(np.float64), 1.0 / dist ** power)
    rgb = np.einsum("mk,mkc->mc", w, src_rgb[idx].astype(np.float64)) / w.sum(axis=1, keepdims=True)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------------------
# The stage


def _check_input(xyz, rgb) -> tuple[np.ndarray, np.ndarray | None]:
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.issubdtype(xyz.dtype, np.number):
        raise InputError(f"densify: points must be an (N, 3) array, got shape {xyz.shape}")
    xyz = xyz.astype(np.float64, copy=False)
    if not np.all(np.isfinite(xyz)):
        raise InputError("densify: points contain NaN or infinite coordinates")
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (len(xyz), 3):
            raise InputError(f"densify: colours must be an ({len(xyz)}, 3) array, got shape {rgb.shape}")
        if rgb.dtype != np.uint8:
            if rgb.size and (rgb.min() < 0 or rgb.max() > 255):
                raise InputError("densify: colours must be 8-bit (0-255)")
            rgb = rgb.astype(np.uint8)
    return xyz, rgb


def densify(xyz: np.ndarray, rgb: np.ndarray | None = None, params: DensifyParams = DensifyParams(), seed: int = 0,
            upsampler: Upsampler | None = None) -> DensifyResult:
    """Densify one building's points (CRS coordinates, float64 (N, 3); colour (N, 3) uint8 or ``None``).

    ``upsampler`` overrides ``params.upsampler`` (e.g. a :class:`~lidarmap.aerial.upsampler.LearnedUpsampler` loaded from
    another weights file). Same input, params and seed give the same output. ``stats``: ``points_in``,
    ``outliers_removed``, ``points_kept``, ``new_requested``, ``new_points``, ``ratio`` (achieved output / kept),
    ``target_density`` (points/m², "uniform" only), ``leaves``, ``leaves_upsampled``, ``leaves_as_is``,
    ``upsampler``, ``seconds`` (per step and ``total``).
    """
    started = time.perf_counter()
    xyz, rgb = _check_input(xyz, rgb)
    stats: dict[str, typing.Any] = {"points_in": len(xyz), "seconds": {}}
    seconds = stats["seconds"]
    ups = upsampler if upsampler is not None else make_upsampler(params)
    stats["upsampler"] = ups.name
    frame = LocalFrame.around(xyz) if len(xyz) else LocalFrame()
    local = frame.to_local(xyz)

    tick = time.perf_counter()
    kept = np.flatnonzero(remove_outliers(local, params.outlier_k, params.outlier_std))
    pts = local[kept]
    seconds["outliers"] = time.perf_counter() - tick
    stats["outliers_removed"] = len(xyz) - len(kept)
    stats["points_kept"] = len(kept)

    tick = time.perf_counter()
    counts_rng, leaf_seed = np.random.default_rng([seed, 0]), [seed, 1]
    if len(pts) > params.density_k and params.ratio > 1.0:
        area = area_per_point(pts, params.density_k)
        counts, rho = new_point_counts(area, params.ratio, params.distribution, params.max_new_per_point,
                                       counts_rng)
    else:
        counts, rho = np.zeros(len(pts), dtype=np.int64), float("nan")
    leaves = median_split(pts, params.max_leaf, params.min_leaf, params.halo)
    seconds["split"] = time.perf_counter() - tick
    stats.update(new_requested=int(counts.sum()), target_density=rho, leaves=len(leaves),
                 leaves_upsampled=sum(leaf.upsample for leaf in leaves),
                 leaves_as_is=sum(not leaf.upsample for leaf in leaves))

    tick = time.perf_counter()
    new = [np.zeros((0, 3))]
    for number, leaf in enumerate(leaves):
        if not leaf.upsample:
            continue
        context = leaf.context
        seeds = np.where(leaf.near(pts[context], 0.5 * params.halo), counts[context], 0)
        if seeds.sum() == 0:
            continue
        cand = ups.upsample(pts[context], seeds, np.random.default_rng([*leaf_seed, number]))
        new.append(cand[leaf.contains(cand)])
    new_local = np.concatenate(new)
    seconds["upsample"] = time.perf_counter() - tick

    tick = time.perf_counter()
    nearest = cKDTree(pts).query(new_local)[1] if len(new_local) else np.zeros(0, dtype=np.int64)
    out_rgb = None
    if rgb is not None:
        new_rgb = transfer_colour(pts, rgb[kept], new_local, params.colour_k, params.colour_power)
        out_rgb = np.concatenate([rgb[kept], new_rgb])
    seconds["colour"] = time.perf_counter() - tick

    out_xyz = np.concatenate([xyz[kept], frame.to_crs(new_local)])
    is_new = np.concatenate([np.zeros(len(kept), bool), np.ones(len(new_local), bool)])
    source = np.concatenate([kept, kept[nearest]]).astype(np.int64)
    stats["new_points"] = len(new_local)
    stats["ratio"] = len(out_xyz) / len(kept) if len(kept) else float("nan")
    seconds["total"] = time.perf_counter() - started
    return DensifyResult(xyz=out_xyz, rgb=out_rgb, is_new=is_new, source_index=source, stats=stats)


# ----------------------------------------------------------------------------------------------------------------------
# Measurements


def noise_amplification(dist_in: np.ndarray, dist_out: np.ndarray, tau: float = 0.25) -> dict:
    """How much off-surface noise densification adds, from distances to a true surface.

    ``dist_in``: distance of every input point to the true surface; ``dist_out``: of every output point (kept +
    new). A point is *noise* when farther than ``tau``. Returns ``noise_in``/``noise_out`` (counts),
    ``frac_in``/``frac_out`` (shares of all points) and ``amplification`` = noise_out / noise_in: 1 means the
    noise was carried over but not multiplied, the output/input ratio means it grew like the data (the paper's
    SAPCU behaviour), < 1 means outlier removal took more noise away than upsampling added.
    """
    dist_in, dist_out = np.asarray(dist_in), np.asarray(dist_out)
    noise_in, noise_out = int(np.count_nonzero(dist_in > tau)), int(np.count_nonzero(dist_out > tau))
    return {
        "tau": tau, "noise_in": noise_in, "noise_out": noise_out,
        "frac_in": noise_in / max(len(dist_in), 1), "frac_out": noise_out / max(len(dist_out), 1),
        "amplification": noise_out / noise_in if noise_in else float("nan"),
    }


def seam_ratios(new_split: np.ndarray, new_reference: np.ndarray, leaves: list[Leaf], band: float = 0.5) -> dict:
    """The seam check: density of new points at the split planes, relative to a run without splitting.

    ``new_split``: new points of a run split into ``leaves`` (from :func:`median_split`); ``new_reference``: new
    points of the same input, parameters and seed in one leaf (``max_leaf`` above the point count); one frame for
    all. Dividing by the reference cancels the geometry (walls, edges, density changes that happen to lie near a
    plane), so what remains is the split's own trace. For each leaf's lower face on each axis (each split plane
    once per cell it bounds), within the leaf's extent on the other axes, new points within ``band`` of the plane
    are counted on the leaf's side (a) and on the other side (b), in both runs; pooled over all faces:

    * ``band`` = (a + b)_split / (a + b)_reference: 1 when the planes leave no trace, < 1 for thinned seam lines
      (paper Fig. 8), > 1 for piled-up ones;
    * ``across`` = (a_split / a_reference) / (b_split / b_reference): 1 when the density does not jump across;
    * ``planes``: faces counted; ``points``: reference new points within the bands; ``counts``: the four pooled
      counts (a, b split; a, b reference), to pool over several inputs.
    """
    sums = np.zeros(4)  # split a, split b, reference a, reference b
    planes = 0
    for leaf in leaves:
        for axis in range(3):
            v = leaf.lo[axis]
            if not np.isfinite(v):
                continue
            others = [a for a in range(3) if a != axis]
            counts = []
            for pts in (new_split, new_reference):
                pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
                use = np.all((pts[:, others] >= leaf.lo[others]) & (pts[:, others] < leaf.hi[others]), axis=1)
                off = pts[use, axis] - v
                counts += [np.count_nonzero((off >= 0) & (off < band)), np.count_nonzero((off < 0) & (off > -band))]
            if counts[2] and counts[3]:
                planes += 1
                sums += counts
    out = {"band": float("nan"), "across": float("nan"), "planes": planes, "points": int(sums[2] + sums[3]),
           "counts": sums.astype(np.int64).tolist()}
    if planes and sums[1]:
        out["band"] = float((sums[0] + sums[1]) / (sums[2] + sums[3]))
        out["across"] = float((sums[0] / sums[2]) / (sums[1] / sums[3]))
    return out
