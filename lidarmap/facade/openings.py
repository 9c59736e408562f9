"""Façade extraction, part 4: holes -> windows, doors and unknown regions (§2.4, eq. 3).

The input is a *value grid* over the façade (the paper's Figure 6): 1 = hole (not observed, not occluded, or seen
through), 0 = occluded (or beyond the scanner's reach), -1 = wall or another object observed there. Holes are
4-connected components of the 1-cells. A hole whose fill ratio (hole cells / bounding-box cells) reaches ``Ta`` gets
a rectangle: Canny edges of the hole, near-vertical and near-horizontal Hough lines, every pair of vertical and pair
of horizontal lines a candidate, and the candidate minimising eq. (3) wins.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from lidarmap.facade.model import ElementKind

if TYPE_CHECKING:  # pragma: no cover
    from lidarmap.facade.params import FacadeParams

HOLE, OCCLUDED, OBJECT = 1, 0, -1


def window_uncertainty_eq3(values: np.ndarray, rect: tuple[int, int, int, int]) -> float:
    """Paper eq. (3): ε_w = (N_diff + N_obj) / N_hole for a rectangle (r0, r1, c0, c1) of cells [r0, r1) x [c0, c1).

    ``values`` is a value grid (1 hole, 0 occluded, -1 other object). N_hole counts the 1-cells; N_diff the cells
    where rectangle and hole differ (non-1 cells inside the rectangle plus 1-cells outside it); N_obj the -1 cells
    inside the rectangle (they count twice: a window does not contain wall).
    """
    v = np.asarray(values)
    r0, r1, c0, c1 = rect
    inside = v[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)]
    n_hole = int(np.count_nonzero(v == HOLE))
    if n_hole == 0:
        return math.inf
    ones_in = int(np.count_nonzero(inside == HOLE))
    n_diff = (inside.size - ones_in) + (n_hole - ones_in)
    n_obj = int(np.count_nonzero(inside == OBJECT))
    return (n_diff + n_obj) / n_hole


def integral_image(mask: np.ndarray, dtype=np.int64) -> np.ndarray:
    out = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=dtype)
    out[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0), axis=1)
    return out


def box_sums(integral: np.ndarray, r0, r1, c0, c1) -> np.ndarray:
    return integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]


def hough_positions(hole: np.ndarray, params: "FacadeParams") -> tuple[np.ndarray, np.ndarray]:
    """Column and row positions of near-vertical / near-horizontal lines on the hole's Canny edges (Hough peaks)."""
    from skimage.feature import canny
    from skimage.transform import hough_line, hough_line_peaks

    edges = canny(hole.astype(float), sigma=params.openings.canny_sigma, low_threshold=0.1, high_threshold=0.3)
    if not edges.any():
        return np.zeros(0), np.zeros(0)
    tilt = np.radians(params.openings.hough_max_tilt_deg)
    k = max(1, int(params.openings.hough_angle_steps))
    vert = np.linspace(-tilt, tilt, 2 * k + 1)
    horiz = np.pi / 2 + vert
    rows, cols = hole.shape
    result = []
    for thetas, centre in ((vert, rows / 2.0), (horiz, cols / 2.0)):
        acc, angles, dists = hough_line(edges, theta=thetas)
        _, ang, dist = hough_line_peaks(acc, angles, dists, num_peaks=params.openings.hough_lines, min_distance=2,
                                        threshold=max(2.0, 0.2 * acc.max()))
        if thetas is vert:  # x cos θ + y sin θ = dist  ->  x at the patch's middle row
            pos = (dist - centre * np.sin(ang)) / np.cos(ang)
        else:  # y at the patch's middle column
            pos = (dist - centre * np.cos(ang)) / np.sin(ang)
        result.append(np.asarray(pos, dtype=np.float64))
    return result[0], result[1]


def fit_rectangle(hole_mask: np.ndarray, values: np.ndarray | None = None,
                  params: "FacadeParams | None" = None) -> tuple[tuple[int, int, int, int], float]:
    """Best rectangle (r0, r1, c0, c1) — cells [r0, r1) x [c0, c1) — for a hole, minimising eq. (3), and its ε_w.

    ``hole_mask`` marks the hole's cells; ``values`` (same shape, optional) gives the other cells' meaning (0
    occluded, -1 object; default: everything else is -1). Candidate sides come from Hough lines on the hole's Canny
    edges (each line tried at ``hough_offsets`` cells either side, since Canny puts a binary edge on either side of
    the boundary) plus the hole's bounding box; all pairs are scored at once with integral images.
    """
    from lidarmap.facade.params import FacadeParams

    params = params or FacadeParams()
    hole = np.asarray(hole_mask, dtype=bool)
    if values is None:
        vals = np.where(hole, HOLE, OBJECT)
    else:
        vals = np.where(hole, HOLE, np.where(np.asarray(values) == HOLE, OCCLUDED, np.asarray(values)))
    n_hole = int(hole.sum())
    if n_hole == 0:
        return (0, 0, 0, 0), math.inf
    rr, cc = np.nonzero(hole)
    pad = params.openings.hough_offsets + 2
    r_lo, r_hi = max(rr.min() - pad, 0), min(rr.max() + 1 + pad, hole.shape[0])
    c_lo, c_hi = max(cc.min() - pad, 0), min(cc.max() + 1 + pad, hole.shape[1])
    patch_hole = hole[r_lo:r_hi, c_lo:c_hi]
    patch_vals = vals[r_lo:r_hi, c_lo:c_hi]
    xs, ys = hough_positions(np.pad(patch_hole, 2), params)
    xs, ys = xs - 2, ys - 2
    off = np.arange(-params.openings.hough_offsets, params.openings.hough_offsets + 2)
    # a line at pixel x may be the boundary at x (left side) or x + 1 (right side): try both plus offsets
    bbox_cols = [cc.min() - c_lo, cc.max() + 1 - c_lo]  # the hole's bounding box is always a candidate
    bbox_rows = [rr.min() - r_lo, rr.max() + 1 - r_lo]
    col_cands = np.concatenate([(np.round(xs)[:, None] + off[None, :]).ravel(), bbox_cols])
    row_cands = np.concatenate([(np.round(ys)[:, None] + off[None, :]).ravel(), bbox_rows])
    col_cands = np.clip(col_cands, 0, patch_hole.shape[1]).astype(np.int64)
    row_cands = np.clip(row_cands, 0, patch_hole.shape[0]).astype(np.int64)
    col_cands, row_cands = np.unique(col_cands), np.unique(row_cands)
    ci, cj = np.triu_indices(len(col_cands), k=1)
    ri, rj = np.triu_indices(len(row_cands), k=1)
    if len(ci) == 0 or len(ri) == 0:
        rect = (int(rr.min()), int(rr.max()) + 1, int(cc.min()), int(cc.max()) + 1)
        return rect, window_uncertainty_eq3(vals, rect)
    c0, c1 = col_cands[ci], col_cands[cj]
    r0, r1 = row_cands[ri], row_cands[rj]
    ones = integral_image(patch_hole)
    objs = integral_image(patch_vals == OBJECT)
    R0, C0 = np.meshgrid(r0, c0, indexing="ij")
    R1, C1 = np.meshgrid(r1, c1, indexing="ij")
    ones_in = box_sums(ones, R0, R1, C0, C1)
    obj_in = box_sums(objs, R0, R1, C0, C1)
    area = (R1 - R0) * (C1 - C0)
    eps = ((area - ones_in) + (n_hole - ones_in) + obj_in) / n_hole
    best = np.unravel_index(int(np.argmin(eps)), eps.shape)
    rect = (int(R0[best]) + r_lo, int(R1[best]) + r_lo, int(C0[best]) + c_lo, int(C1[best]) + c_lo)
    return rect, float(eps[best])


@dataclasses.dataclass
class Opening:
    """A hole classified as window, door or unknown; ``rect`` in cells when it has a fitted rectangle.

    ``mask`` holds the hole's own cells (value 1); ``region`` adds the occluded cells that were bridged to join
    hole parts split by a thin occluder (a pole, a trunk).
    """

    kind: ElementKind
    mask: np.ndarray  # (rows, cols) bool
    rect: tuple[int, int, int, int] | None
    uncertainty: float
    fill_ratio: float
    occluded_border: float
    n_cells: int
    region: np.ndarray | None = None
    bounds: tuple[float, float, float, float] | None = None  # s_lo, s_hi, t_lo, t_hi (metres) of the rectangle
    kind_undecided: bool = False  # a window only for want of leaf evidence (door_or_window_verdict)

    @property
    def window_evidence(self) -> bool:
        """Whether the hole counts as a window/door vote (rectangular enough, maybe partly occluded)."""
        return self.kind in (ElementKind.WINDOW, ElementKind.DOOR) or self.rect is not None


def hole_regions(values: np.ndarray, params: "FacadeParams") -> tuple[np.ndarray, np.ndarray, int]:
    """Hole candidates of a value grid: (hole cells, labelled regions, count).

    Hole cells are the 1-cells after an opening by a ``hole_open_cells`` square (fringes of unobserved wall along
    shadow edges are not openings); regions are 4-connected components of the hole cells after a closing by a
    ``bridge_cells`` square that may only add occluded cells (joins the parts of an opening behind a thin
    occluder). A square element keeps rectangles larger than it unchanged.
    """
    values = np.asarray(values)
    hole = values == HOLE
    if params.openings.hole_open_cells > 0:
        hole = ndimage.binary_opening(hole, structure=np.ones((2 * params.openings.hole_open_cells + 1,) * 2, bool))
    region = hole
    k = params.openings.bridge_cells
    if k > 0 and hole.any():
        closed = ndimage.binary_closing(np.pad(hole, k), structure=np.ones((2 * k + 1,) * 2, bool))[k:-k, k:-k]
        region = hole | (closed & (values == OCCLUDED))
    labels, n = ndimage.label(region)
    return hole, labels, n


def refine_bounds(rect: tuple[int, int, int, int], wall_st: np.ndarray | None, s0: float, t0: float, cell: float,
                  params: "FacadeParams") -> tuple[float, float, float, float]:
    """Sub-cell sides of a fitted rectangle (cells) from the wall points around it: (s_lo, s_hi, t_lo, t_hi).

    Each side lies between the last wall sample before the opening and the next sample the scanner would have
    taken: last + spacing / 2, with "last" the median over the bands (one cell wide) along the side of the wall
    sample nearest the opening, and "spacing" the median gap between consecutive samples across the side. Without
    enough points (``refine_min_points``) a side is its cell edge moved out by ``edge_bias_cells`` (a cell
    straddling the edge holds wall samples, so the hole is on average half a cell short). A side moves at most
    ``refine_max_cells`` from its cell edge outwards and ``refine_inward_cells`` into the opening.
    """
    r0, r1, c0, c1 = rect
    b = params.openings.edge_bias_cells * cell
    cell_sides = [s0 + c0 * cell, s0 + c1 * cell, t0 + r0 * cell, t0 + r1 * cell]
    out = [cell_sides[0] - b, cell_sides[1] + b, cell_sides[2] - b, cell_sides[3] + b]
    if wall_st is None or len(wall_st) == 0 or params.openings.refine_max_cells <= 0:
        return tuple(out)  # type: ignore[return-value]
    st = np.asarray(wall_st, dtype=np.float64)
    lim = params.openings.refine_max_cells * cell
    inward = min(params.openings.refine_inward_cells * cell, lim)
    reach = lim + 2 * cell
    for k in range(4):
        axis = 0 if k < 2 else 1  # the coordinate across this side
        other = 1 - axis
        lo_o, hi_o = (cell_sides[2], cell_sides[3]) if axis == 0 else (cell_sides[0], cell_sides[1])
        if hi_o - lo_o <= 2 * cell:
            continue
        edge = cell_sides[k]
        sign = -1.0 if k in (0, 2) else 1.0  # the wall lies on this side of the edge
        across = sign * (st[:, axis] - edge)  # > 0: in the wall, < 0: inside the opening
        sel = (across > -lim) & (across < reach) & (st[:, other] > lo_o + cell) & (st[:, other] < hi_o - cell)
        if np.count_nonzero(sel) < params.openings.refine_min_points:
            continue
        a = across[sel]
        bands = np.floor((st[sel, other] - lo_o) / cell).astype(np.int64)
        order = np.lexsort((a, bands))
        a, bands = a[order], bands[order]
        first = np.r_[True, bands[1:] != bands[:-1]]
        nearest = a[first]  # per band: the wall sample closest to the opening
        gaps = np.diff(a)[~first[1:]]
        gaps = gaps[gaps > 0.25 * cell]  # samples of one scan line (noise apart) are not the spacing
        if len(nearest) < 3:
            continue
        spacing = min(float(np.median(gaps)), 3 * cell) if len(gaps) else 0.0
        pos = float(np.clip(np.median(nearest) - spacing / 2, -inward, lim))
        out[k] = edge + sign * pos
    return tuple(out)  # type: ignore[return-value]


def detect_openings(values: np.ndarray, cell: float, params: "FacadeParams",
                    ground_t: np.ndarray | None = None, t0: float = 0.0, s0: float = 0.0,
                    wall_st: np.ndarray | None = None, opaque: np.ndarray | None = None,
                    front: np.ndarray | None = None) -> list[Opening]:
    """Classify every hole region of a value grid (see :func:`hole_regions` and the module doc).

    * fewer hole cells than ``min_hole_area``: ignored (sampling gaps);
    * touching the left, right or top border of the grid (unless wall closes the three other sides of a hole the
      left or right border cuts, :func:`_cut_side`, or its sides and bottom when the top border cuts it,
      :func:`top_cut`), larger than ``max_opening_area``, more than
      ``occlusion_touch_max`` of its border occluded (unless wall encloses it: :func:`enclosed_by_wall`), fill
      ratio below ``Ta``, rectangle ε_w above
      ``max_window_uncertainty``, a side below ``min_opening_size`` or cells spanning less than it both ways:
      UNKNOWN (uncertainty inf);
    * door-sized and reaching the ground (:func:`door_or_window`; ``ground_t``: ground height per grid column in
      façade t, default: the grid's bottom edge ``t0``; ``opaque``: share of passing pulses back from just behind):
      DOOR, unless the border cuts it (wall was required below it);
    * otherwise WINDOW with the fitted rectangle and its eq. (3) ε_w (bridged occluded cells count as 0).

    With ``front`` (cells of a layer in front of the wall: balconies) a hole whose rows below are occluded down to
    such a structure reaches down to its top (:func:`structure_below`); its seen part then needs wall on its other
    three sides only (the occluded side is the structure's shadow) and no minimum height of its own.

    The grid's lower-left corner is (``s0``, ``t0``); ``wall_st`` (the main layer's points, (s, t)) places the
    rectangles' sides below the cell size (:func:`refine_bounds`); sizes and the door test use those sides,
    stored in ``Opening.bounds``.
    """
    values = np.asarray(values)
    hole, labels, n = hole_regions(values, params)
    if n == 0:
        return []
    rows, cols = values.shape
    ground = np.full(cols, t0) if ground_t is None else np.asarray(ground_t, dtype=np.float64)
    min_cells = params.openings.min_hole_area / (cell * cell)
    # cells cut off by the opening: unexplained, neither hole nor wall
    work = np.where((values == HOLE) & ~hole, OCCLUDED, values)
    out: list[Opening] = []
    # each region once; one that bridged occluded cells and failed as a whole is tried again as its hole parts
    candidates: collections.deque = collections.deque((lab, True) for lab in range(1, n + 1))
    while candidates:
        item, splittable = candidates.popleft()
        region = labels == item if isinstance(item, int) else item
        mask = region & hole
        n_cells = int(mask.sum())
        if n_cells < min_cells:
            continue
        rows_any, cols_any = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
        r0, r1, c0, c1 = int(rows_any[0]), int(rows_any[-1]) + 1, int(cols_any[0]), int(cols_any[-1]) + 1
        n_region = int(region.sum())
        fill = n_region / float((r1 - r0) * (c1 - c0))
        # border of the region: 4-neighbours outside it
        win = (slice(max(r0 - 1, 0), min(r1 + 1, rows)), slice(max(c0 - 1, 0), min(c1 + 1, cols)))
        local = region[win]
        ring = ndimage.binary_dilation(local) & ~local
        ring_vals = work[win][ring]
        occ_border = float(np.count_nonzero(ring_vals == OCCLUDED)) / max(1, ring_vals.size)
        cut = _cut_side(work, (r0, r1, c0, c1), params)
        cut_above = cut is None and top_cut(work, (r0, r1, c0, c1), ground, t0, cell, params)
        touches_edge = (c0 == 0 or c1 == cols or r1 == rows) and cut is None and not cut_above
        area = n_region * cell * cell
        unknown = Opening(ElementKind.UNKNOWN, mask, None, math.inf, fill, occ_border, n_cells, region)
        if touches_edge or area > params.openings.max_opening_area or not (
                fill >= params.openings.Ta or fill >= params.openings.Ta_enclosed
                and enclosed_by_wall(work, (r0, r1, c0, c1), params)):
            parts = _hole_parts(region, mask) if splittable and params.openings.split_bridged else []
            if parts:
                candidates.extend((part, False) for part in parts)
            else:
                out.append(unknown)
            continue
        rect, _ = fit_rectangle(region, work, params)
        # eq. (3) on this opening alone: other holes and the bridged cells are neither hole nor object
        local = np.where(mask, HOLE, np.where(region | (work == HOLE), OCCLUDED, work))
        eps = window_uncertainty_eq3(local, rect)
        seen_rect = rect
        low = structure_below(rect, work, front, cell, params) if front is not None else None
        if low is not None:  # the parapet's shadow hides the lower part: the window reaches down to its top
            rect = (low, rect[1], rect[2], rect[3])
        bounds = _not_below_min_size(refine_bounds(rect, wall_st, s0, t0, cell, params),
                                     refine_bounds(rect, None, s0, t0, cell, params), params)
        # sizes count inside the façade only: a sliver under the eave is not a window reaching above the roof
        bounds = (max(bounds[0], s0), min(bounds[1], s0 + cols * cell), max(bounds[2], t0),
                  min(bounds[3], t0 + rows * cell))
        width, height = bounds[1] - bounds[0], bounds[3] - bounds[2]
        if low is not None:  # the shadow explains the occluded side; wall must close the seen part's others
            hidden = not enclosed_by_wall(work, seen_rect, params, sides=(True, True, False, True))
        else:
            sides = _sides(rect, ground, t0, cell, params)
            if cut is not None or cut_above:  # no wall was seen beyond the façade's extent: that side needs none
                sides = tuple(named and k != (3 if cut_above else cut) for k, named in enumerate(sides))
            hidden = occ_border > params.openings.occlusion_touch_max and not enclosed_by_wall(
                work, rect, params, sides=sides)
        # a gap whose cells span less than min_opening_size both ways is no opening, however far the half-cell
        # growth of sides without wall samples (edge_bias_cells) carries its box
        gap = max(rect[1] - rect[0], rect[3] - rect[2]) * cell < params.openings.min_opening_size - 1e-9
        # nor is a hole mostly below the ground line (pulses that crossed the wall plane under the pavement)
        underground = underground_share(mask, ground, t0, cell) > params.openings.underground_max
        if hidden or gap or underground or eps > params.openings.max_window_uncertainty \
                or min(width, height) < params.openings.min_opening_size:
            unknown.rect = seen_rect if hidden else None
            out.append(unknown)
            continue
        ground_here = float(np.mean(ground[rect[2]:rect[3]]))
        width_cut = side_hidden(work, rect, params)
        kind, undecided = door_or_window_verdict(bounds, ground_here, mask, opaque, params, width_cut=width_cut)
        if cut is not None or (kind is ElementKind.DOOR and low is None
                               and lifted_leaf_too_tall(rect, bounds, ground_here, work, t0, cell, params)):
            # wall closes it below: no door, whatever the ground line of a wall seen this little; or its foot is
            # hidden and it would be taller than a door
            kind, undecided = ElementKind.WINDOW, False
        elif kind is ElementKind.WINDOW and low is None and (
                hidden_leaf_door(work, rect, bounds, ground_here, t0, cell, mask, opaque, params, width_cut)
                or hidden_foot_door(work, rect, bounds, ground_here, t0, cell, params, width_cut)):
            kind, undecided = ElementKind.DOOR, False  # a door whose lower part was hidden: it reaches the ground
            rect = (_ground_row(ground_here, t0, cell),) + tuple(rect[1:])
            bounds = (bounds[0], bounds[1], ground_here, bounds[3])
        elif kind is ElementKind.WINDOW and low is None \
                and door_below_hidden(work, rect, bounds, ground_here, t0, cell, params, width_cut):
            unknown.rect = seen_rect  # the top of a door or a window: what hid its lower part decides which
            out.append(unknown)
            continue
        if low is not None:
            eps = window_uncertainty_eq3(local, rect)  # the occluded rows it now covers count
        out.append(Opening(kind, mask, rect, eps, fill, occ_border, n_cells, region, bounds,
                           kind_undecided=undecided))
    below_floor_level(out, ground, params)
    return out


def inside_structures(openings: list[Opening], front: np.ndarray, params: FacadeParams) -> list[Opening]:
    """Windows and doors whose hole cells lie mostly (more than ``inside_structure_max`` of them) where a layer in
    front of the wall was seen (``front``: an oriel, a bay window) become unknown regions without window evidence,
    in place; returns them. The wall plane is open behind an oriel, whose own windows let the pulses cross it,
    so the oriel's floors read as holes of the wall: no window of the wall (issue 18 round 31, independent dev
    scenes: 5 of the 33 false openings after three campaigns). A window behind a balcony is seen over the
    parapet, through cells no layer in front covers."""
    turned = []
    for o in openings:
        if o.kind in (ElementKind.WINDOW, ElementKind.DOOR) and o.mask.any() \
                and float(front[o.mask].mean()) > params.openings.inside_structure_max:
            o.kind, o.rect, o.bounds = ElementKind.UNKNOWN, None, None
            turned.append(o)
    return turned


def _hole_parts(region: np.ndarray, mask: np.ndarray) -> list[np.ndarray]:
    """The hole parts (4-connected) of a ``region`` that joined them across occluded cells or took such cells in
    (none when it holds none). A band of shadow along the ground (parked cars) joined a door with hole fragments up
    to the façade's end, and the whole became one unknown region (issue 18 round 31, independent dev seed 7)."""
    if not (region & ~mask).any():
        return []
    labels, n = ndimage.label(mask)
    return [labels == k for k in range(1, n + 1)]


def _not_below_min_size(refined: tuple[float, float, float, float], cells: tuple[float, float, float, float],
                        params: FacadeParams) -> tuple[float, float, float, float]:
    """A rectangle's sides placed from the wall points (``refined``), except along an axis where they bring it
    below ``min_opening_size`` while its cell edges (``cells``, half a cell out) do not: a narrow window's frame,
    a few cm behind the wall plane, returns "wall" points inside the opening that moved both sides a cell inwards
    (issue 18 round 7, hard dev seeds 117 and 120: open windows 0.63 and 0.69 m wide measured 0.42 and 0.44 m:
    unknown regions)."""
    out = list(refined)
    least = params.openings.min_opening_size
    for lo, hi in ((0, 1), (2, 3)):
        if refined[hi] - refined[lo] < least <= cells[hi] - cells[lo]:
            out[lo], out[hi] = cells[lo], cells[hi]
    return (out[0], out[1], out[2], out[3])


def _sides(rect: tuple[int, int, int, int], ground: np.ndarray, t0: float, cell: float,
           params: FacadeParams) -> tuple[bool, bool, bool, bool]:
    """The sides (left, right, below, above) of a box (r0, r1, c0, c1) that wall must close for
    :func:`enclosed_by_wall`: not the one below when ``ground_encloses`` and the box is door-tall
    (``door_min_height``) and starts within ``door_bottom_tol`` of the ground line (a door has pavement below it,
    no wall; a lower hole there, e.g. under a shop window, still needs wall below)."""
    r0, r1, c0, c1 = rect
    op = params.openings
    at_ground = op.ground_encloses and (r1 - r0) * cell >= op.door_min_height \
        and t0 + r0 * cell <= float(np.mean(ground[c0:c1])) + op.door_bottom_tol
    return (True, True, not at_ground, True)


def underground_share(mask: np.ndarray, ground: np.ndarray, t0: float, cell: float) -> float:
    """The share of a hole's cells (``mask``) whose centre lies more than half a cell below the ground line of
    their column (``ground``, façade t; grid bottom ``t0``). Independent dev seed 2 (issue 18 round 37): a strip
    0.5 m tall under a shop window, 0.4 m of it below the pavement, was a window."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return 0.0
    centres = t0 + (rows + 0.5) * cell
    return float(np.mean(centres < ground[cols] - 0.5 * cell))


def below_floor_level(openings: list[Opening], ground: np.ndarray, params: FacadeParams) -> int:
    """Doors lifted above the ground line (more than ``door_bottom_tol``; typed doors by their leaf within
    ``door_leaf_tol``) that start more than ``door_floor_tol`` above the lowest door-tall opening of the same
    façade become windows, in place; returns how many.

    A door up some steps or on a ground floor raised above the street opens at the floor level; a ground-floor
    window starts a sill above it. Glass with curtains closes a window like a leaf, so on a raised floor a tall
    curtained window on a 0.8 m sill passes the ground test that admits the door beside it (issue 18, dev seed 22
    building 6): the door of the same floor, starting lower, tells them apart."""
    op = params.openings
    tall = [o for o in openings if o.bounds is not None and o.kind in (ElementKind.WINDOW, ElementKind.DOOR)
            and o.bounds[3] - o.bounds[2] >= op.door_min_height]
    if len(tall) < 2:
        return 0
    floor = min(o.bounds[2] for o in tall)
    done = 0
    for o in tall:
        lifted = o.bounds[2] > float(np.mean(ground[o.rect[2]:o.rect[3]])) + op.door_bottom_tol
        if o.kind is ElementKind.DOOR and lifted and o.bounds[2] > floor + op.door_floor_tol:
            o.kind = ElementKind.WINDOW
            done += 1
    return done


def door_below_hidden(values: np.ndarray, rect: tuple[int, int, int, int], bounds: tuple[float, float, float, float],
                      ground: float, t0: float, cell: float, params: FacadeParams, width_cut: bool = False) -> bool:
    """Whether a window's seen part may be the top of a door whose lower part the campaign did not see: with
    ``hidden_bottom_unknown``, the cells between the ground line (``ground``, façade t) and the rectangle's bottom
    (r0, r1, c0, c1 = ``rect``) are mostly not observed, without one row of mostly observed wall among them (a car or
    a van in front), and the rectangle (``bounds``) would have a door's size if it reached the ground: door-wide
    (``door_min_width`` .. ``door_max_width``; no minimum when ``width_cut``) and its top ``door_min_height`` ..
    ``door_max_height`` above the ground line. Its bottom, hence its kind, is then unknown (issue 18 round 26,
    dev seeds 388, 392 and 403: the upper 0.8-1.9 m of doors seen above parked vehicles were stored as windows)."""
    op = params.openings
    if not op.hidden_bottom_unknown or bounds[2] - ground < op.hidden_bottom_min_height:
        return False  # the bottom seen may be a ground-floor window's sill with the wall below it hidden
    return _hidden_to_ground(values, rect, bounds, ground, t0, cell, params, width_cut)


def hidden_leaf_door(values: np.ndarray, rect: tuple[int, int, int, int], bounds: tuple[float, float, float, float],
                     ground: float, t0: float, cell: float, mask: np.ndarray, opaque: np.ndarray | None,
                     params: FacadeParams, width_cut: bool = False) -> bool:
    """Whether a window is the upper part of a door closed by an opaque leaf whose lower part the campaign did not
    see: with ``hidden_leaf_doors``, its core's passing pulses came back from just behind the wall (at least
    ``evidence.opaque_share`` of them, :func:`door_or_window`), its seen part starts within ``door_leaf_tol`` of the
    ground line, and the cells down to the ground line are hidden as :func:`door_below_hidden` asks (mostly not
    observed, no row of mostly observed wall, door-sized if it reached the ground). A window's glass lets most
    pulses through or returns a share of them; a leaf stops them all. The door then reaches the ground line
    (issue 18 round 34, independent dev seed 1: a door in a 0.5 m deep porch, its lower 0.7 m hidden, was a
    window)."""
    op = params.openings
    if not op.hidden_leaf_doors or bounds[2] - ground > op.door_leaf_tol:
        return False
    share = _leaf_share(mask, opaque)
    if len(share) == 0 or float(share.mean()) < params.evidence.opaque_share:
        return False
    return _hidden_to_ground(values, rect, bounds, ground, t0, cell, params, width_cut)


def hidden_foot_door(values: np.ndarray, rect: tuple[int, int, int, int], bounds: tuple[float, float, float, float],
                     ground: float, t0: float, cell: float, params: FacadeParams, width_cut: bool = False) -> bool:
    """Whether a window is a door whose foot the campaign did not see: seen from no higher than
    ``hidden_foot_max`` above the ground line, no wider than ``open_door_max_width``, with its cells down to the
    ground line hidden as :func:`door_below_hidden` asks (mostly not observed, no row of mostly observed wall,
    door-sized if it reached the ground). What hides the lowest half metre of a wall (a car's bonnet, bins,
    bicycles) leaves a door's upper 1.7 m; that a door-tall window sits that low on its sill is taken as the less
    likely case, a prior not measured on real streets (issue 18 round 37, independent dev seeds 2 and 5: doors
    seen from 0.4 m above their threshold were stored as windows)."""
    op = params.openings
    if bounds[2] - ground > op.hidden_foot_max or bounds[1] - bounds[0] > op.open_door_max_width:
        return False
    return _hidden_to_ground(values, rect, bounds, ground, t0, cell, params, width_cut)


def _hidden_to_ground(values: np.ndarray, rect: tuple[int, int, int, int], bounds: tuple[float, float, float, float],
                      ground: float, t0: float, cell: float, params: FacadeParams, width_cut: bool) -> bool:
    """Whether the cells between the ground line and a rectangle's bottom are mostly not observed, with no row of
    mostly observed wall among them, and the rectangle would be door-sized if it reached the ground line (see
    :func:`door_below_hidden`)."""
    op = params.openings
    r0, r1, c0, c1 = rect
    g_row = _ground_row(ground, t0, cell)
    if r0 - g_row < 2:
        return False  # it reaches the ground line: the verdict saw its bottom
    width, top = bounds[1] - bounds[0], bounds[3] - ground
    if top > op.door_max_height or not op.door_sized(max(width, op.door_min_width) if width_cut else width, top):
        return False
    return _band_hidden(values, rect, g_row)


def _band_hidden(values: np.ndarray, rect: tuple[int, int, int, int], g_row: int) -> bool:
    """Whether the cells from row ``g_row`` (the ground line's) up to a rectangle's bottom (r0, r1, c0, c1) are
    mostly not observed, with no row of mostly observed wall among them."""
    r0, _, c0, c1 = rect
    band = values[g_row:r0, c0:c1]
    if band.size == 0 or bool(((band == OBJECT).mean(axis=1) > 0.5).any()):
        return False  # wall seen below it: a sill, whatever hid the rest
    return float(np.mean(band == OCCLUDED)) > 0.5


def lifted_leaf_too_tall(rect: tuple[int, int, int, int], bounds: tuple[float, float, float, float], ground: float,
                         values: np.ndarray, t0: float, cell: float, params: FacadeParams) -> bool:
    """Whether a door typed by its leaf above ``door_bottom_tol`` of the ground line (``ground``) would be taller
    than a door if it reached the ground: its top more than ``door_max_height`` above it and its cells down to the
    ground line hidden (:func:`_band_hidden`: its foot is not seen, so it reaches below its seen bottom). A shop
    window whose room returned the pulses like a leaf, seen above a field of view that ended 1.05 m up, measured
    2.6 m from there: a door (issue 18 round 39, independent dev seed 31)."""
    op = params.openings
    if bounds[2] <= ground + op.door_bottom_tol or bounds[3] - ground <= op.door_max_height:
        return False
    g_row = _ground_row(ground, t0, cell)
    return rect[0] - g_row >= 2 and _band_hidden(values, rect, g_row)


def _ground_row(ground: float, t0: float, cell: float) -> int:
    """The grid row whose lower edge lies nearest the ground line ``ground`` (façade t; grid bottom ``t0``)."""
    return max(int(math.floor((ground - t0) / cell + 0.5)), 0)


def side_hidden(values: np.ndarray, rect: tuple[int, int, int, int], params: FacadeParams) -> bool:
    """Whether the left or right side of a rectangle (r0, r1, c0, c1) ends at cells the campaign did not see: more
    than half of the ``enclosed_reach_cells`` columns beyond it, over its rows, are occluded (a reveal's shadow
    fringe or a door frame is a column or two; an occluder's shadow is wider). The opening may go on behind them."""
    r0, r1, c0, c1 = rect
    k = max(params.openings.enclosed_reach_cells, 1)
    bands = (values[r0:r1, max(c0 - k, 0):c0], values[r0:r1, c1:c1 + k])
    return any(b.shape[1] == k and float(np.mean(b == OCCLUDED)) > 0.5 for b in bands)


def _cut_side(values: np.ndarray, box: tuple[int, int, int, int], params: FacadeParams) -> int | None:
    """The side (0 left, 1 right, as ``enclosed_by_wall`` names them) of a hole's bounding box (r0, r1, c0, c1)
    that the façade's extent cuts, when the hole is a whole opening there all the same, else ``None``.

    The extent ends where the campaigns' wall samples end (the scanner's reach along a wall seen at a grazing
    angle), and it can end at a window's jamb: the hole then touches the grid's left or right border. It is taken
    as whole when wall closes its three other sides (:func:`enclosed_by_wall`): a rectangle of its own, not the
    gap past a building's corner nor a strip of unobserved wall along the border (those have no wall above and
    below). With wall below it such a hole is a window. Without such a side it stays an unknown region. The wall
    above must be the façade's, not its last row: a hole cut by the extent whose top lies within
    ``enclosed_reach_cells`` of the grid's top is the corner under the eave (issue 18 round 20, dev seed 270: a
    jagged 0.6 m hole at the corner of a façade's top, closed above by one row of wall, became a window)."""
    r0, r1, c0, c1 = box
    rows, cols = values.shape
    if r0 == 0 or r1 + max(params.openings.enclosed_reach_cells, 1) > rows or (c0 == 0) == (c1 >= cols):
        return None
    side = 0 if c0 == 0 else 1
    return side if enclosed_by_wall(values, box, params, sides=(side == 1, side == 0, True, True)) else None


def top_cut(values: np.ndarray, box: tuple[int, int, int, int], ground: np.ndarray, t0: float, cell: float,
            params: FacadeParams) -> bool:
    """Whether a hole whose bounding box (r0, r1, c0, c1) the grid's top border cuts, or cells the campaign did not
    observe close above (:func:`_unseen_above`), is the part of an opening seen below them (``top_cut_windows``):
    away from the left and right borders, with wall on its left and right and below
    it (none below a door-tall box from the ground line, :func:`_sides`). A campaign whose view ends low (a
    multibeam scanner's upper beam at 2.1-3.3 m) cuts the grid there, across shop windows and doors: they were
    unknown regions (independent dev seeds 6 and 21, issue 18 round 36). The gap past a building's corner or the
    sky beside a gable's slope touches a side border or lacks wall beside it; a strip under the eave is lower than
    ``top_cut_min_height`` (hard dev seed 416: 0.4 m, a false window)."""
    r0, r1, c0, c1 = box
    rows, cols = values.shape
    op = params.openings
    if not op.top_cut_windows or c0 == 0 or c1 >= cols or (r1 - r0) * cell < op.top_cut_min_height:
        return False
    if r1 != rows and not _unseen_above(values, box, params):
        return False
    return enclosed_by_wall(values, box, params, sides=_sides(box, ground, t0, cell, params)[:3] + (False,))


def _unseen_above(values: np.ndarray, box: tuple[int, int, int, int], params: FacadeParams) -> bool:
    """Whether the cells within ``enclosed_reach_cells`` above a hole's bounding box (r0, r1, c0, c1) are mostly not
    observed: the campaign's view ends there inside the grid (a multibeam scanner's upper beam runs diagonally
    across a side wall seen at a slant, independent dev seed 4: a first-floor window whose top corner it cut was an
    unknown region), or something in front hid it."""
    r0, r1, c0, c1 = box
    band = values[r1:r1 + max(params.openings.enclosed_reach_cells, 1), c0:c1]
    return band.size > 0 and float(np.mean(band == OCCLUDED)) > 0.5


def enclosed_by_wall(values: np.ndarray, rect: tuple[int, int, int, int], params: FacadeParams,
                     sides: tuple[bool, bool, bool, bool] = (True, True, True, True)) -> bool:
    """Whether wall (OBJECT cells) was observed beyond every side of a rectangle (r0, r1, c0, c1) that ``sides``
    (left, right, below, above) names: within ``enclosed_reach_cells`` outside the side, along at least half of
    its length (:func:`side_wall_share`). A hole whose border is mostly occluded (shadow fringes of reveals and
    frames at grazing incidence, the ends of scan lines) but that wall closes on all four sides is a whole opening,
    not the visible part of one that continues behind an occluder."""
    k = params.openings.enclosed_reach_cells
    if k <= 0:
        return False
    wall = values == OBJECT
    # sides named (left, right, below, above); side_wall_share numbers them as rect's lines (below, above, ...)
    return all(side_wall_share(wall, rect, side, k) >= 0.5
               for side, named in zip((2, 3, 0, 1), sides) if named)


def side_wall_share(wall: np.ndarray, rect: tuple[int, int, int, int] | list[int], side: int, reach: int) -> float:
    """Share of the rows (left/right side) or columns (below/above) of a rectangle ``rect`` = (r0, r1, c0, c1) with
    a ``wall`` cell within ``reach`` cells outside one side; ``side`` indexes ``rect``'s line: 0 below, 1 above,
    2 left, 3 right. 0 at the grid's border or for an empty side. Shared by detection and the map's fusion."""
    r0, r1, c0, c1 = rect
    rows, cols = wall.shape
    if (side == 0 and r0 <= 0) or (side == 1 and r1 >= rows) or (side == 2 and c0 <= 0) or (side == 3 and c1 >= cols):
        return 0.0
    if side == 0:
        band = wall[max(r0 - reach, 0):r0, c0:c1].any(axis=0)
    elif side == 1:
        band = wall[r1:r1 + reach, c0:c1].any(axis=0)
    elif side == 2:
        band = wall[r0:r1, max(c0 - reach, 0):c0].any(axis=1)
    else:
        band = wall[r0:r1, c1:c1 + reach].any(axis=1)
    return float(band.mean()) if band.size else 0.0


def structure_below(rect: tuple[int, int, int, int], values: np.ndarray, front: np.ndarray, cell: float,
                    params: FacadeParams) -> int | None:
    """The row a hole's rectangle (r0, r1, c0, c1) reaches down to when a structure in front hides its lower part
    (the parapet of a balcony under a French window, seen from a scanner below it), else ``None``.

    The row below the rectangle must be mostly occluded; going down row by row while a row is not mostly
    observed (OBJECT), at most ``behind_structure_reach`` (and at least the rectangle's own height), the first
    mostly observed row must be the top of a structure in front: in most columns a ``front`` cell (a layer in
    front of the wall: a balcony, not the wall nor a car's shadow reaching the ground) in it or the two rows
    below. The rectangle then starts just above it."""
    op = params.openings
    if not op.complete_behind_structures:
        return None
    r0, r1, c0, c1 = rect
    across = slice(c0, c1)
    if r0 < 1 or c1 - c0 < 2 or np.mean(values[r0 - 1, across] == OCCLUDED) < 0.5:
        return None
    reach = max(r1 - r0, round(op.behind_structure_reach / cell))
    k, stop = r0 - 1, max(r0 - reach, 0)
    while k >= stop and np.mean(values[k, across] == OBJECT) <= 0.5:
        k -= 1
    # the structure's top rows: a sparse campaign's scan lines hit the parapet's top in some cells of a row only
    top = front[max(k - 2, 0):k + 1, across].any(axis=0)
    if k < stop or np.mean(top) < 0.5:
        return None  # nothing observed within reach, or the wall itself: the window may end anywhere above it
    return k + 1 if k + 1 < r0 else None


def door_or_window(bounds: tuple[float, float, float, float], ground: float, mask: np.ndarray,
                   opaque: np.ndarray | None, params: FacadeParams, width_cut: bool = False) -> ElementKind:
    """A door is at least ``door_min_height`` tall, ``door_min_width`` .. ``door_max_width`` wide and starts within
    ``door_bottom_tol`` of the ground line below it, or within ``door_leaf_tol`` when it is closed by a leaf: on
    average over its cells with passing pulses (those 2 cells or more inside its border: reveals catch pulses
    along the border of an open window), at least ``opaque_share`` of them came back from just behind the
    wall (``opaque``: that share per cell, NaN without passing pulses; a door at the top of steps). An opening
    wider than ``open_door_max_width`` is a door only when closed by such a leaf (a garage door): glazed shop
    fronts let most pulses through. Everything else, shop windows and windows with low sills included, is a
    window. ``width_cut``: a side of the opening ends at cells the campaign could not see
    (:func:`side_hidden`), so its width is a lower bound and no minimum width applies (issue 18 round 20, dev seed
    272: a door whose left part a van hid measured 0.64 m wide and was stored as a window)."""
    return door_or_window_verdict(bounds, ground, mask, opaque, params, width_cut)[0]


def door_or_window_verdict(bounds: tuple[float, float, float, float], ground: float, mask: np.ndarray,
                           opaque: np.ndarray | None, params: FacadeParams,
                           width_cut: bool = False) -> tuple[ElementKind, bool]:
    """:func:`door_or_window` and whether its verdict is *undecided*: a window of a door's size that starts above
    ``door_bottom_tol`` but within ``door_leaf_tol`` of the ground line, with no pulse through its core, is a
    window only because nothing said whether a leaf closes it. Another campaign that measured the leaf may
    settle it (issue 18 round 24, dev seed 358: a door 0.59 m above the ground line, found a door by campaign 1,
    seen by campaign 3 without a passing pulse and retyped a window). Undecided, it is a door when no wider than
    ``open_door_max_width`` and starting within ``door_steps_tol`` of the ground line (round 26), else a window."""
    op = params.openings
    width, height = bounds[1] - bounds[0], bounds[3] - bounds[2]
    if not op.door_sized(max(width, op.door_min_width) if width_cut else width, height):
        return ElementKind.WINDOW, False
    if height > op.door_tallest:
        # taller than any door: a shop window 3.2 m tall on a 0.4 m sill, whose dark room or blinds returned the
        # pulses like a leaf (issue 18 round 31, independent dev seeds 5 and 7)
        return ElementKind.WINDOW, False
    share = _leaf_share(mask, opaque)
    leaf = len(share) > 0 and float(share.mean()) >= params.evidence.opaque_share
    if width > op.open_door_max_width and len(share) > 0 and not leaf:
        return ElementKind.WINDOW, False  # wider than a door leaf and the pulses cross it: a glazed shop front
    tol = op.door_leaf_tol if leaf else op.door_bottom_tol
    if bounds[2] <= ground + tol:
        return ElementKind.DOOR, False
    if len(share) == 0 and bounds[2] <= ground + op.door_leaf_tol:
        # no pulse through its core said whether a leaf closes it: door-tall, door-wide and starting a few steps
        # above the street (door_steps_tol) it is a door (issue 18 round 26, dev seeds 398, 402 and 404: doors
        # up 0.4-0.55 m of steps, seen at grazing angles, were stored as windows); higher, or wider than a leaf,
        # a window (tall windows 0.8-1.1 m up became doors)
        door = width <= op.open_door_max_width and bounds[2] <= ground + op.door_steps_tol
        return (ElementKind.DOOR if door else ElementKind.WINDOW), True
    return ElementKind.WINDOW, False


def _leaf_share(mask: np.ndarray, opaque: np.ndarray | None) -> np.ndarray:
    """The opaque share (``opaque``) of an opening's core cells with passing pulses: a leaf closes the whole
    opening, the reveals of an open window catch pulses along its border only."""
    if opaque is None:
        return np.zeros(0)
    core = ndimage.binary_erosion(mask, structure=np.ones((5, 5), dtype=bool))
    core = core if core.sum() >= 0.25 * mask.sum() else mask
    share = opaque[core]
    return share[np.isfinite(share)]


def complete_by_repetition(openings: list[Opening], values: np.ndarray, s0: float, t0: float, cell: float,
                           params: "FacadeParams") -> int:
    """Complete windows cut by an occlusion from their repeated neighbours (paper §2.1), in place.

    A window with part of its border occluded takes the median height of the windows with no occluded border in
    the same column (both sides within ``repetition_tol``) by growing its bottom (or top) side, and likewise the
    median width of those in the same row; a side grows only across occluded or unobserved cells, stopping at the
    first row (column) that is mostly observed wall, and only when it gets at least half-way. Its uncertainty is
    eq. (3) of the completed rectangle: the occluded cells it now covers count. Returns how many windows changed.
    """
    values = np.asarray(values)
    rows, cols = values.shape
    clean = [op for op in openings if op.kind is ElementKind.WINDOW and op.bounds is not None
             and op.occluded_border <= 0.05]
    tol = params.openings.repetition_tol
    done = 0

    def idx(x: float, origin: float, n: int) -> int:
        return int(np.clip(np.floor((x - origin) / cell + 1e-9), 0, n - 1))

    def grow(lo_side: float, target: float, step: int, origin: float, n: int, across: slice, axis: int) -> float:
        """Move a side from ``lo_side`` towards ``target`` cell by cell (step -1: down/left, +1: up/right) while
        the next line of cells (over ``across``) is not mostly observed."""
        pos = lo_side
        k = idx(lo_side - (cell / 2 if step < 0 else -cell / 2), origin, n)
        while (target < pos if step < 0 else target > pos) and 0 <= k < n:
            line = values[k, across] if axis == 0 else values[across, k]
            if line.size == 0 or np.count_nonzero(line == OBJECT) > 0.5 * line.size:
                break
            pos = max(target, pos - cell) if step < 0 else min(target, pos + cell)
            k += step
        return pos

    for op in openings:
        if op.kind is not ElementKind.WINDOW or op.bounds is None or op.occluded_border <= 0.05:
            continue
        new = list(op.bounds)
        column = [o.bounds for o in clean if abs(o.bounds[0] - new[0]) <= tol and abs(o.bounds[1] - new[1]) <= tol]
        if column:
            height = float(np.median([b[3] - b[2] for b in column]))
            deficit = height - (new[3] - new[2])
            if deficit > cell:
                cs = slice(idx(new[0], s0, cols) + 1, idx(new[1], s0, cols))
                down = grow(new[2], new[3] - height, -1, t0, rows, cs, 0)
                if new[2] - down >= deficit / 2:
                    new[2] = down
                else:
                    up = grow(new[3], new[2] + height, 1, t0, rows, cs, 0)
                    if up - new[3] >= deficit / 2:
                        new[3] = up
        row = [o.bounds for o in clean if abs(o.bounds[2] - new[2]) <= tol and abs(o.bounds[3] - new[3]) <= tol]
        if row:
            width = float(np.median([b[1] - b[0] for b in row]))
            deficit = width - (new[1] - new[0])
            if deficit > cell:
                rs = slice(idx(new[2], t0, rows) + 1, idx(new[3], t0, rows))
                left = grow(new[0], new[1] - width, -1, s0, cols, rs, 1)
                if new[0] - left >= deficit / 2:
                    new[0] = left
                else:
                    right = grow(new[1], new[0] + width, 1, s0, cols, rs, 1)
                    if right - new[1] >= deficit / 2:
                        new[1] = right
        if tuple(new) != tuple(op.bounds):
            rect = tuple(int(np.clip(round((x - o) / cell), 0, n)) for x, o, n in
                         ((new[2], t0, rows), (new[3], t0, rows), (new[0], s0, cols), (new[1], s0, cols)))
            local = np.where(op.mask, HOLE, np.where(values == HOLE, OCCLUDED, values))
            op.bounds = (new[0], new[1], new[2], new[3])
            op.rect = rect
            op.uncertainty = window_uncertainty_eq3(local, rect)
            done += 1
    return done


def complete_behind_structures(openings: list[Opening], values: np.ndarray, front: np.ndarray, s0: float, t0: float,
                               cell: float, params: FacadeParams) -> int:
    """Windows whose lower part a structure in front hides (the parapet of a balcony under a French window): the
    bottom side moves down across the occluded rows below it to the top of that structure, in place.

    The rule of :func:`structure_below`, for windows found without ``front`` (:func:`detect_openings` applies it
    when given ``front``, to partly hidden holes too). Its uncertainty is eq. (3) of the grown rectangle. Returns
    how many changed.
    """
    values = np.asarray(values)
    done = 0
    for op in openings:
        if op.kind is not ElementKind.WINDOW or op.bounds is None or op.rect is None:
            continue
        new_r0 = structure_below(op.rect, values, front, cell, params)
        if new_r0 is None:
            continue
        r1, c0, c1 = op.rect[1:]
        local = np.where(op.mask, HOLE, np.where(values == HOLE, OCCLUDED, values))
        op.rect = (new_r0, r1, c0, c1)
        op.bounds = (op.bounds[0], op.bounds[1], t0 + new_r0 * cell, op.bounds[3])
        op.uncertainty = window_uncertainty_eq3(local, op.rect)
        done += 1
    return done



@dataclasses.dataclass(frozen=True)
class WallDepths:
    """Per cell of a façade grid, the mean depth of the returns near the wall relative to the local wall (NaN: none),
    how many returns that mean is over, and the cells of door leaves found flush with it
    (:func:`lidarmap.facade.evidence.door_leaves`)."""

    offset: np.ndarray
    count: np.ndarray
    leaves: np.ndarray | None = None


def glazed_doors(openings: list[Opening], values: np.ndarray, depths: WallDepths, ground: np.ndarray, s0: float,
                 t0: float, cell: float, params: FacadeParams) -> list[tuple[Opening, np.ndarray]]:
    """Windows that are the glazed pane of a door, made doors, in place; returns each such door with the cells it
    gained.

    A glazed door is a leaf with a pane in its upper part: the pulses cross the pane (a hole from 1.0-1.2 m up), but
    the leaf below it returns them from 2-5 cm behind the wall (a flush leaf), so only the pane is a hole and it was
    typed a window (issue 18, independent dev scenes: 9 of the 18 doors missed after one campaign were windows
    over all or part of them, 8 of those glazed doors). A window whose bottom lies ``glazed_sill_min`` .. ``glazed_sill_max`` above the
    ground line and whose top lies a door's height above it (``door_min_height`` less ``glazed_frame_max``, the
    leaf's frame above the pane, .. ``door_max_height``; the grown door must have a door's size), no wider
    than ``open_door_max_width``, becomes a door when the cells below it down to the ground line are mostly observed
    (or ``glazed_seen_rows`` rows' worth, the rest hidden by a parked car) and lie behind the wall beside them at
    the same heights: their median depth at least ``evidence.leaf_offset``
    behind that wall's, and 60 % of them half that (holes and leaf cells count as behind). A window on a sill has
    wall below it, as deep as the wall beside it. The door reaches the ground line and grows sideways and up by the
    leaf around the pane (lines of cells mostly behind the wall, at most ``glazed_frame_max``). Two such doors
    side by side (at most ``glazed_frame_max`` apart, tops as close) are the two panes of one double door. A door
    made is leaf, not wall beside, for the panes tested after it (the other pane of a double door)."""
    if not params.openings.glazed_doors:
        return []
    made: list[tuple[Opening, np.ndarray]] = []
    leaves = np.zeros(values.shape, dtype=bool) if depths.leaves is None else depths.leaves.copy()
    while True:  # a door made is leaf, not wall beside the next pane (the other leaf of a double door)
        found = False
        for o in openings:
            if o.kind is not ElementKind.WINDOW or o.bounds is None or o.rect is None:
                continue
            cells = _glazed_door_cells(o, values, WallDepths(depths.offset, depths.count, leaves), ground, t0,
                                       cell, params)
            if cells is None:
                continue
            r0, r1, c0, c1 = cells
            o.kind, o.kind_undecided, o.rect = ElementKind.DOOR, False, cells
            o.bounds = (min(o.bounds[0], s0 + c0 * cell), max(o.bounds[1], s0 + c1 * cell),
                        float(np.mean(ground[c0:c1])), max(o.bounds[3], t0 + r1 * cell))
            new = np.zeros(values.shape, dtype=bool)
            new[r0:r1, c0:c1] = True
            made.append((o, new & ~o.mask))
            leaves |= new
            found = True
        if not found:
            return _pair_double_doors(openings, made, params.openings.glazed_frame_max)


def _glazed_door_cells(o: Opening, values: np.ndarray, depths: WallDepths, ground: np.ndarray, t0: float,
                       cell: float, params: FacadeParams) -> tuple[int, int, int, int] | None:
    """The cells (r0, r1, c0, c1) of the door whose pane the window ``o`` is, or None (see :func:`glazed_doors`)."""
    op = params.openings
    r0, r1, c0, c1 = o.rect
    g = float(np.mean(ground[c0:c1]))
    sill, top = o.bounds[2] - g, o.bounds[3] - g
    # the leaf's frame above the pane may add up to glazed_frame_max to its top: door_sized decides at the end
    tall = op.door_min_height - op.glazed_frame_max <= top <= op.door_max_height
    if not (op.glazed_sill_min <= sill <= op.glazed_sill_max and tall):
        return None
    if o.bounds[1] - o.bounds[0] > op.open_door_max_width:
        return None  # wider than a leaf: a shop window on a stall riser
    g_row = _ground_row(g, t0, cell)
    if r0 - g_row < 3:
        return None
    reach = max(int(round(op.glazed_frame_max / cell)), 0)
    below = _LeafTest(values, depths, slice(g_row, r0), c0, c1, reach, cell, params)
    if not below.is_leaf():
        return None
    cols, rows = values.shape[1], values.shape[0]
    left = _leaf_lines(below.is_leaf(c, c + 1) for c in range(c0 - 1, max(c0 - reach, 0) - 1, -1))
    right = _leaf_lines(below.is_leaf(c, c + 1) for c in range(c1, min(c1 + reach, cols)))
    up = _leaf_lines(_LeafTest(values, depths, slice(r, r + 1), c0, c1, reach, cell, params).is_leaf(c0, c1)
                     for r in range(r1, min(r1 + reach, rows)))
    new = (g_row, r1 + up, c0 - left, c1 + right)
    if not op.door_sized((new[3] - new[2]) * cell, t0 + new[1] * cell - g):
        return None
    return new


def _leaf_lines(verdicts) -> int:
    """How many lines of cells (beside or above a pane, outwards) are leaf before the first that is not."""
    return sum(1 for _ in itertools.takewhile(bool, verdicts))


class _LeafTest:
    """The cells of ``rows`` against the wall beside a pane's columns ``c0:c1`` at the same heights: the observed
    wall cells from ``reach`` to 1 m beyond either side (their median depth is the reference: a ground floor's
    rustication or plinth, or a biased local wall, moves wall and leaf alike)."""

    def __init__(self, values: np.ndarray, depths: WallDepths, rows: slice, c0: int, c1: int, reach: int,
                 cell: float, params: FacadeParams):
        self.c0, self.c1, self.params = c0, c1, params
        off, n = depths.offset[rows], depths.count[rows]
        hole = values[rows] == HOLE
        leaf = depths.leaves[rows] if depths.leaves is not None else np.zeros_like(hole)
        cols = values.shape[1]
        far = int(round(1.0 / cell))
        side = np.zeros(cols, dtype=bool)
        side[max(c0 - far, 0):max(c0 - reach, 0)] = True
        side[min(c1 + reach, cols):min(c1 + far, cols)] = True
        wall = side[None, :] & (n > 0) & (values[rows] == OBJECT) & ~leaf
        self.ref = float(np.median(off[wall])) if wall.sum() >= 10 else None
        self.seen = hole | leaf | (n > 0)
        self.measured = (n > 0) & ~hole  # cells whose returns give a depth (not a pulse through the plane)
        self.depth = np.where(hole | leaf, -np.inf, np.where(n > 0, off, np.nan))
        half = 0.5 * params.evidence.leaf_offset
        self.deep = self.seen & (self.depth <= (np.inf if self.ref is None else self.ref - half))

    def share(self, c0: int, c1: int) -> float | None:
        """The share of the observed cells of columns ``c0:c1`` that lie behind the wall (None: no wall beside,
        or under half of them observed, unless the cells with returns make ``glazed_seen_rows`` rows' worth: a
        parked car hides most of a leaf below a pane, its lowest rows seen beneath the car's body; holes do not
        count there, the ragged bottom of a hole below its fitted rectangle is no leaf)."""
        seen = self.seen[:, c0:c1]
        if self.ref is None or seen.sum() < 2:
            return None
        rows = self.params.openings.glazed_seen_rows
        if seen.sum() < 0.5 * seen.size and (rows <= 0 or self.measured[:, c0:c1].sum() < rows * (c1 - c0)):
            return None
        return float(self.deep[:, c0:c1][seen].mean())

    def is_leaf(self, c0: int | None = None, c1: int | None = None) -> bool:
        """Whether the cells of columns ``c0:c1`` (default: the pane's) are leaf: mostly observed, 60 % of them
        behind the wall and their median depth ``leaf_offset`` behind it (see :func:`glazed_doors`)."""
        c0, c1 = (self.c0, self.c1) if c0 is None else (c0, c1)
        share = self.share(c0, c1)
        if share is None or share < 0.6:
            return False
        core = self.seen[:, c0:c1]
        return float(np.median(self.depth[:, c0:c1][core])) <= self.ref - self.params.evidence.leaf_offset


def _pair_double_doors(openings: list[Opening], made: list[tuple[Opening, np.ndarray]],
                       gap: float) -> list[tuple[Opening, np.ndarray]]:
    """Doors made from panes (with the cells they gained) that stand side by side, at most ``gap`` apart with tops
    as close: the two panes of a double door, one leaf below both. The left one joins the right one and leaves
    ``openings``; returns the doors that remain."""
    made = sorted(made, key=lambda m: m[0].bounds[0])
    out: list[tuple[Opening, np.ndarray]] = []
    for o, cells in made:
        if out:
            a = out[-1][0]  # its gained cells lie inside the joined rectangle
            if o.bounds[0] - a.bounds[1] <= gap + 1e-9 and abs(o.bounds[3] - a.bounds[3]) <= gap + 1e-9:
                o.bounds = (a.bounds[0], o.bounds[1], min(a.bounds[2], o.bounds[2]), max(a.bounds[3], o.bounds[3]))
                o.rect = (min(a.rect[0], o.rect[0]), max(a.rect[1], o.rect[1]), a.rect[2], o.rect[3])
                joined = np.zeros_like(cells)
                joined[o.rect[0]:o.rect[1], o.rect[2]:o.rect[3]] = True
                o.mask = o.mask | a.mask
                cells = joined & ~o.mask
                openings[:] = [x for x in openings if x is not a]
                out.pop()
        out.append((o, cells))
    return out
