"""Façade extraction, part 2: the 2.5D depth grid, GMM depth layers (§2.3), objects per layer and eq. (1)-(2).

Grids follow :class:`lidarmap.facade.observe.model.FacadeEvidence`: shape (rows, cols), row i covers t in [t0 + i*cell, ...), column
j covers s in [s0 + j*cell, ...).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import TYPE_CHECKING

import numpy as np
import shapely
from scipy import ndimage
from scipy.special import erf
from shapely.geometry import MultiPoint, Polygon

from lidarmap.facade.model import Layer

if TYPE_CHECKING:  # pragma: no cover
    from lidarmap.facade.params import FacadeParams


# ----------------------------------------------------------------------------------------------------------------------
# Grid


@dataclasses.dataclass
class DepthGrid:
    """A 2.5D depth image of façade points: per-cell point count and mean depth, and each point's cell."""

    cell: float
    s0: float
    t0: float
    count: np.ndarray  # (rows, cols) int
    depth: np.ndarray  # (rows, cols) float, NaN where empty
    row: np.ndarray  # (N,) per point, -1 outside the grid
    col: np.ndarray  # (N,)

    @property
    def shape(self) -> tuple[int, int]:
        return self.count.shape  # type: ignore[return-value]

    @property
    def inside(self) -> np.ndarray:
        return self.row >= 0

    def flat(self) -> np.ndarray:
        """Flat cell index per point (-1 outside)."""
        return np.where(self.row >= 0, self.row * self.shape[1] + self.col, -1)


def grid_shape(extent: tuple[float, float, float, float], cell: float) -> tuple[int, int]:
    """(rows, cols) of a grid covering extent (s0, s1, t0, t1) with square cells."""
    s0, s1, t0, t1 = extent
    return max(1, int(math.ceil((t1 - t0) / cell - 1e-9))), max(1, int(math.ceil((s1 - s0) / cell - 1e-9)))


def cell_index(s: np.ndarray, t: np.ndarray, cell: float, s0: float, t0: float,
               shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of (s, t) positions; both -1 outside the grid."""
    fs = (np.asarray(s, dtype=np.float64) - s0) / cell
    ft = (np.asarray(t, dtype=np.float64) - t0) / cell
    bad = ~(np.isfinite(fs) & np.isfinite(ft))
    col = np.floor(np.where(bad, -1.0, np.clip(fs, -1.0, shape[1] + 1.0))).astype(np.int64)
    row = np.floor(np.where(bad, -1.0, np.clip(ft, -1.0, shape[0] + 1.0))).astype(np.int64)
    out = (row < 0) | (row >= shape[0]) | (col < 0) | (col >= shape[1])
    return np.where(out, -1, row), np.where(out, -1, col)


def depth_grid(sdt: np.ndarray, cell: float, extent: tuple[float, float, float, float]) -> DepthGrid:
    """Rasterise façade points (s, t, d) on a ``cell`` grid over ``extent``: counts and mean depth per cell."""
    sdt = np.asarray(sdt, dtype=np.float64).reshape(-1, 3)
    shape = grid_shape(extent, cell)
    row, col = cell_index(sdt[:, 0], sdt[:, 1], cell, extent[0], extent[2], shape)
    inside = row >= 0
    flat = row[inside] * shape[1] + col[inside]
    size = shape[0] * shape[1]
    count = np.bincount(flat, minlength=size)
    total = np.bincount(flat, weights=sdt[inside, 2], minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return DepthGrid(cell, float(extent[0]), float(extent[2]), count.reshape(shape), depth.reshape(shape), row, col)


# ----------------------------------------------------------------------------------------------------------------------
# Layers


def fit_layers(depths: np.ndarray, params: "FacadeParams", seed: int = 0) -> list[Layer]:
    """Depth layers of a façade: a 1D Gaussian mixture over ``depths`` with 1..``gmm_max_components`` components,
    chosen by BIC (sklearn, seeded); components closer than ``min_layer_separation`` are merged (moment matching) and
    components lighter than ``gmm_min_weight`` dropped. Layers are returned sorted by depth (deepest first), with
    ids 0..k-1 and ``n_points`` the points each one explains best.
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.mixture import GaussianMixture

    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return []
    rng = np.random.default_rng(seed)
    sample = d if len(d) <= params.layers.gmm_max_samples else rng.choice(d, size=params.layers.gmm_max_samples, replace=False)
    x = sample[:, None]
    best, best_bic = None, np.inf
    max_k = int(max(1, min(params.layers.gmm_max_components, len(np.unique(sample)))))
    for k in range(1, max_k + 1):
        gmm = GaussianMixture(n_components=k, covariance_type="full", random_state=seed, n_init=params.layers.gmm_n_init,
                              reg_covar=params.layers.gmm_reg_var, max_iter=200, init_params="k-means++")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            gmm.fit(x)
        bic = gmm.bic(x)
        if bic < best_bic - 1e-9:
            best, best_bic = gmm, bic
    assert best is not None
    comps = [[float(w), float(m), float(v)] for w, m, v in
             zip(best.weights_, best.means_.ravel(), best.covariances_.ravel())]
    comps = _merge_components(comps, params.layers.min_layer_separation)
    total = sum(w for w, _, _ in comps)
    comps = [c for c in comps if c[0] / total >= params.layers.gmm_min_weight] or [max(comps, key=lambda c: c[0])]
    total = sum(w for w, _, _ in comps)
    comps.sort(key=lambda c: c[1])
    layers = [Layer(layer_id=i, mu=m, sigma=math.sqrt(max(v, 1e-12)), weight=w / total)
              for i, (w, m, v) in enumerate(comps)]
    labels = assign_layers(d, layers, sigma_k=np.inf)
    counts = np.bincount(labels[labels >= 0], minlength=len(layers))
    for layer, n in zip(layers, counts):
        layer.n_points = int(n)
    return layers


def _merge_components(comps: list[list[float]], separation: float) -> list[list[float]]:
    """Merge mixture components (weight, mean, variance) whose means are closer than ``separation``.

    Two components of similar spread are one layer split in two: moment matching. A component more than twice as
    broad as its heavier neighbour is clutter around that layer (reveals, mixed cells): the heavier one absorbs its
    weight and keeps its own mean and spread, so a layer's σ stays the surface's noise.
    """
    comps = sorted(comps, key=lambda c: c[1])
    merged = True
    while merged and len(comps) > 1:
        merged = False
        gaps = [comps[i + 1][1] - comps[i][1] for i in range(len(comps) - 1)]
        i = int(np.argmin(gaps))
        if gaps[i] < separation:
            (w1, m1, v1), (w2, m2, v2) = comps[i], comps[i + 1]
            w = w1 + w2
            heavy, light = ((w1, m1, v1), (w2, m2, v2)) if w1 >= w2 else ((w2, m2, v2), (w1, m1, v1))
            if light[2] > 4.0 * heavy[2]:
                comps[i:i + 2] = [[w, heavy[1], heavy[2]]]
            else:
                m = (w1 * m1 + w2 * m2) / w
                v = (w1 * (v1 + m1 * m1) + w2 * (v2 + m2 * m2)) / w - m * m
                comps[i:i + 2] = [[w, m, v]]
            merged = True
    return comps


def assign_layers(depths: np.ndarray, layers: list[Layer], sigma_k: float = 3.0) -> np.ndarray:
    """Index (into ``layers``) of the most probable layer of each depth; -1 beyond ``sigma_k`` of that layer."""
    d = np.asarray(depths, dtype=np.float64).ravel()
    if not layers:
        return np.full(len(d), -1, dtype=np.int64)
    mu = np.array([la.mu for la in layers])
    sig = np.array([la.sigma for la in layers])
    w = np.array([la.weight for la in layers])
    z = (d[:, None] - mu) / sig
    logp = np.log(np.maximum(w, 1e-300)) - np.log(sig) - 0.5 * z * z
    best = np.argmax(logp, axis=1)
    far = np.abs(z[np.arange(len(d)), best]) > sigma_k
    return np.where(far, -1, best).astype(np.int64)


def uncertainty_eq1(mu: float, sigma: float, mean_depth: float) -> tuple[float, float]:
    """Paper eq. (1)-(2): confidence α = 1 - (cdf(μ+|μ-d̄|) - cdf(μ-|μ-d̄|)) and uncertainty ε = 1 - α.

    With cdf the normal N(μ, σ) CDF, cdf(μ+δ) - cdf(μ-δ) = erf(δ / (σ√2)); an object lying exactly on its layer
    has α = 1, ε = 0; ε -> 1 as the object's mean depth d̄ leaves the layer.
    """
    delta = abs(float(mu) - float(mean_depth))
    if sigma <= 0:  # a degenerate layer: any offset lies outside it
        mass = 1.0 if delta > 0 else 0.0
    else:
        mass = float(erf(delta / (float(sigma) * math.sqrt(2.0))))
    alpha = 1.0 - mass
    return alpha, 1.0 - alpha


# ----------------------------------------------------------------------------------------------------------------------
# Objects and polygons


def square(radius: int) -> np.ndarray:
    return np.ones((2 * radius + 1, 2 * radius + 1), dtype=bool)


def grow_regions(mask: np.ndarray, close_cells: int, min_cells: int,
                 min_width_cells: int = 1) -> tuple[np.ndarray, int]:
    """Objects of one layer: iterative region growing on the cell grid (4-connected components) after closing gaps
    of up to ``2 * close_cells`` cells and removing parts thinner than ``min_width_cells`` (opening); components
    smaller than ``min_cells`` are dropped (label 0)."""
    m = mask.astype(bool)
    if close_cells > 0:
        padded = np.pad(m, close_cells)
        padded = ndimage.binary_closing(padded, structure=square(close_cells))
        m = padded[close_cells:-close_cells, close_cells:-close_cells] | m
    if min_width_cells > 1:
        m = ndimage.binary_opening(m, structure=np.ones((min_width_cells, min_width_cells), dtype=bool))
    labels, n = ndimage.label(m)
    if n == 0:
        return labels, 0
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= min_cells
    keep[0] = False
    remap = np.zeros(n + 1, dtype=np.int64)
    remap[keep] = np.arange(1, int(keep.sum()) + 1)
    return remap[labels], int(keep.sum())


def closing_radius(count: np.ndarray, cell: float, min_close: int, max_close: int, window: float = 1.0) -> np.ndarray:
    """Per cell, the radius (cells) of the closing :func:`close_sampling_gaps` applies there: the local point
    spacing / cell (spacing from the point density over a ``window`` metre neighbourhood), clipped to
    [``min_close``, ``max_close``]."""
    k = max(1, int(round(window / cell)))
    density = np.maximum(ndimage.uniform_filter(count.astype(np.float64), size=k, mode="constant"), 0.0) / (cell * cell)
    with np.errstate(divide="ignore"):
        spacing = np.where(density > 1e-9, 1.0 / np.sqrt(np.maximum(density, 1e-9)), np.inf)
    return np.clip(np.round(spacing / cell), min_close, max_close).astype(np.int64)


def close_sampling_gaps(count: np.ndarray, cell: float, min_close: int, max_close: int,
                        window: float = 1.0, radius: np.ndarray | None = None) -> np.ndarray:
    """Observed cells with sampling gaps closed: a cell is observed when it holds points, or when a closing of
    radius r fills it, r = :func:`closing_radius` (or ``radius``, when the caller has it). Square structuring
    elements keep rectangular holes larger than the element exactly as they are."""
    observed = count > 0
    if max_close <= 0 or not observed.any():
        return observed
    if radius is None:
        radius = closing_radius(count, cell, min_close, max_close, window)
    out = observed.copy()
    for r in range(max(1, min_close), max_close + 1):
        sel = radius == r
        if not sel.any():
            continue
        closed = ndimage.binary_closing(np.pad(observed, r, mode="edge"), structure=square(r))[r:-r, r:-r]
        out |= closed & sel
    return out


def mask_to_polygons(mask: np.ndarray, s0: float, t0: float, cell: float) -> list[Polygon]:
    """Exact polygons of a cell mask (union of horizontal runs of cells); one polygon per 4-connected part."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return []
    padded = np.pad(mask, ((0, 0), (1, 1)))
    diff = np.diff(padded.astype(np.int8), axis=1)
    r_start, c_start = np.nonzero(diff == 1)
    r_end, c_end = np.nonzero(diff == -1)
    boxes = shapely.box(s0 + c_start * cell, t0 + r_start * cell, s0 + c_end * cell, t0 + (r_end + 1) * cell)
    union = shapely.union_all(boxes, grid_size=cell * 1e-3)
    union = shapely.simplify(union, cell * 1e-3)
    parts = [g for g in getattr(union, "geoms", [union]) if isinstance(g, Polygon) and not g.is_empty]
    return parts


def outline_polygon(st: np.ndarray, cell: float, ratio: float) -> Polygon | None:
    """Concave hull (shapely, ``ratio`` 0 = most concave, 1 = convex hull) of an object's (s, t) samples, buffered by
    half a cell so that the outline encloses the cells it comes from."""
    st = np.unique(np.round(np.asarray(st, dtype=np.float64) / (cell * 0.5)) * (cell * 0.5), axis=0)
    if len(st) < 3:
        return None
    hull = shapely.concave_hull(MultiPoint(st), ratio=ratio)
    if hull.geom_type != "Polygon":
        hull = hull.buffer(cell * 0.5, join_style="mitre")
    else:
        hull = hull.buffer(cell * 0.5, join_style="mitre")
    if hull.geom_type == "MultiPolygon":
        hull = max(hull.geoms, key=lambda g: g.area)
    return hull if isinstance(hull, Polygon) and not hull.is_empty else None
