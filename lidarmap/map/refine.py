"""Fusing a new campaign into the stored building map (Zou & Sester, §2.5) and roofs from the air.

Contract used by the CLI (``lidarmap map update``)::

    new_map = refine_map(stored, points, trajectory, footprints, facade_params, refine_params, campaign_id, seed)
    new_map = add_aerial(stored, cloud, footprints, refine_params, campaign_id, seed)

Both return a new :class:`~lidarmap.map.model.BuildingMap` (``stored`` is not modified) without the campaign record;
the caller appends the :class:`~lidarmap.map.model.Campaign` and commits it with :class:`~lidarmap.map.store.MapStore`.
An empty ``stored`` map is built from the campaign alone (façade extraction, §2.2-2.4).

Refinement of one stored façade by one campaign (:func:`refine_facade`), in the stored façade's frame:

1. **Points** of the building within ``association_distance`` (2 m) of the façade's main plane, and along the wall
   within its extent (+ ``extend_margin``, or its footprint edge), belong to it; the rest may form new façades
   (RANSAC, :func:`lidarmap.facade.observe.observe.building_facades`), e.g. a wall seen for the first time.
2. **Layers**: a GMM on the new points' depths (the same depth axis as the stored layers); components are matched to
   stored layers (the main layer first, then the others after removing the main layer's shift, gate
   ``layer_gate`` x the combined σ, at least ``layer_gate_min``) and fused by the Gaussian product of eq. (4)-(7)
   (:func:`fuse_gaussians`); unmatched components become new layers.
3. **Plane**: the new main layer's 3σ inliers give a PCA normal, combined with the stored one weighted by point counts;
   the frame is turned about the façade's middle and moved so that the fused main layer is at d = 0 again. The
   extent grows (whole cells, so the evidence grids stay aligned) where the new wall reaches beyond it.
4. :func:`lidarmap.facade.observe.observe.observe_facade` gives what the campaign saw on the (grown) grid, its depths
   measured from the campaign's own wall (GPS drift puts it cm off the fused plane); the evidence grids add up:
   ``window_votes`` / ``object_votes`` / ``seen`` count campaigns per pixel. A campaign sampling the façade more
   sparsely than ``min_element_density`` (side walls at grazing angles) and more sparsely than the stored façade
   (:func:`stored_density`) refines the plane and layers only, except on the cells no earlier campaign saw, where
   its votes and elements count (:func:`_on_unseen_cells`). A cell it holds no return in, filled only by a coarse
   sampling-gap closing, casts no wall vote (``evidence.fill_vote_max_radius``).
5. **Elements** of the same layer class are matched by polygon IoU (or a piece mostly inside another, so objects an
   old occlusion split merge). Windows/doors: the best rectangle over candidate lines from the edges of all matched
   shapes minimises the weighted eq. (3) on the vote map (:func:`refit_rectangle`, :func:`weighted_window_uncertainty`:
   window votes weigh for, object votes against, occluded pixels nothing); ε is that weighted ratio; sides below the
   cell size are the campaign-weighted mean of the matched shapes' sides on the chosen lines. Cells whose window
   and wall votes tie weigh nothing where the stored shapes hold most of the matched evidence (elsewhere they count
   as wall), and where stored shapes take part ties between rectangles go to the extent the better-evidenced
   shapes claim. A merged window whose
   ε exceeds ``max_window_uncertainty`` on the fused votes is dropped; a stored one the campaign saw but did not
   find is dropped only when the wall evidence over it outweighs its opening evidence, else its sides are refitted
   (inwards over the whole rectangle, so a too-wide one sheds its wall strip). Structures: the
   pixels most campaigns that saw them saw as the object; ε the point-weighted mean. The same vote judges a stored
   structure the new campaign saw but did not find (dropped when outvoted) and a new one earlier campaigns saw no
   sign of, so clutter seen once (reveals, interiors behind glass) does not pile up campaign after campaign. Pixels claimed by objects on
   two layers go to the one with the lower ε.
6. **Unknown regions** lose the pixels any campaign saw as wall (``object_votes`` > 0) or a changed opening covers;
   new ones are added only where the grid grew, so a façade's unknown area never grows. One the campaign saw that
   the fused votes show as a hole enclosed by wall on all four sides becomes a window (``enclosed_wall_share``).

Element and façade ids stay stable: a merged object keeps the id of its oldest stored member; new objects get fresh
ids. A campaign id already listed in a façade's ``campaigns`` is never fused again into it (re-applying is a no-op).

:func:`add_aerial` adds roof planes per building from an aerial scan (the aerial pipeline's plane detector,
:func:`lidarmap.aerial.flatten.detect_planes`) and fuses a later aerial campaign's planes with the stored ones.
See docs/refine.md for the parameters and measured numbers.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from typing import ClassVar

import numpy as np
import shapely
from scipy import ndimage
from scipy.sparse.csgraph import connected_components
from shapely.geometry import Polygon, box

from lidarmap.config import check_params
from lidarmap.core import Footprints, PointCloud
from lidarmap.errors import LidarmapError
from lidarmap.executor import derive_seed
from lidarmap.facade.campaign import CampaignData, check_same_crs
from lidarmap.facade.layers import assign_layers, grid_shape, mask_to_polygons
from lidarmap.facade.model import (
    Element,
    ElementKind,
    Facade,
    FacadeEvidence,
    FacadeFrame,
    Layer,
)
from lidarmap.facade.observe import building_facades, layer_fit, observe_facade
from lidarmap.facade.openings import box_sums, integral_image, side_wall_share
from lidarmap.facade.params import FacadeParams, OpeningParams
from lidarmap.facade.planes import boundary_distance, fit_line_2d, footprint_edges
from lidarmap.map.model import Building, BuildingMap, RoofPlane

__all__ = ["RefineParams", "add_aerial", "refine_facade", "assign_to_facades", "fuse_gaussians",
           "match_layers", "net_votes", "weighted_window_uncertainty", "refit_rectangle", "opening_uncertainty",
           "pad_evidence", "roof_planes", "fuse_roofs", "weighted_kind", "outweighed_by_wall", "evidence_weight"]

OPENINGS = (ElementKind.WINDOW, ElementKind.DOOR)


@dataclasses.dataclass(frozen=True)
class RefineParams:
    """Parameters of refinement (TOML table ``[refine]``). Lengths in metres, angles in degrees.

    Points and façades
        association_distance (2.0): new points within this distance of a stored façade's main plane belong to it
            (paper §2.5: two metres); farther points may form new façades (RANSAC).
        extend_margin (2.0): ... and within this distance beyond the façade's extent along the wall (or anywhere
            along its footprint edge): a campaign that sees more of a wall grows the façade instead of starting a
            new one (façade extraction splits walls at gaps > 2 m, ``facade_max_gap``).
        corner_margin (0.5): ... unless the point lies closer to the footprint's boundary than to the façade's
            plane by more than this: it is on another wall of the building. Near a corner the first metres of a
            wall no campaign has stored yet lie within ``association_distance`` of the stored wall beside it; that
            wall used to take them, so the new façade stopped 2 m short of its end and lost the windows there.
            The margin is what a footprint may be off from the wall (cadastre: a few dm). A façade on no footprint
            edge gets no margin: a room's side wall seen through a window took a strip of the street wall square to
            it, at every height, before a campaign had stored that wall (issue 18 round 22, dev seed 347).
        yield_depth (0.3): a stored façade on a footprint edge that holds no window or door, lies more than this
            behind a wall a new campaign finds on the same edge and is less than half that wall's area is the back
            of a room seen through the windows: it is dropped and the campaign's points are assigned again, so that
            the returns through the windows reach the wall (issue 18 round 27, dev seed 400).
        extend_min (0.2): the extent grows where the new main-layer points reach at least this far beyond it
            (a few cm of misregistration must not add a row of empty cells every campaign) ...
        extend_min_area (1.0): ... and cover at least this many m² of grid cells there (a few stray points of a
            sparse side wall seen at a grazing angle grow nothing).
        extend_column_share (0.1): along the wall the extent grows only as far as the outermost column of cells
            that holds at least this share of the fullest new column's cells (a wall ends in a column over its
            height; a few points past the corner used to drag the end out, and the pulses that passed the plane
            beyond the wall made a strip of false windows there).
        normal_max_angle_deg (5.0): a new PCA normal further than this from the stored one is an outlier (a
            partial view, a different wall) and is not fused; the layers and elements still are.
        min_element_density (20.0): a campaign that samples a façade with fewer points per m² of the cells it saw
            (a side wall at a grazing angle: 1-2 /m², against 100-200 /m² on street façades) refines its plane and
            layers only: at that spacing a 1 m gap is sampling, not an opening, so its elements and evidence are
            left out. Unless it samples the façade at least as densely as the stored façade's campaigns did
            (:func:`stored_density`): then the stored elements came from no better sampling. On the cells no
            earlier campaign saw its evidence and elements are kept all the same (:func:`_on_unseen_cells`):
            there it is the only word (issue 18 round 23, dev seed 352: a 28 m tall façade whose ground floor
            two campaigns could not see; the third saw it whole, 424 window cells, but sampled the upper floors
            sparsely, 18.9 points per m² over the façade, and nothing it saw was stored).

    Layers (eq. 4-7)
        main_layer_gate (0.3): the new component nearest the stored main layer (d = 0) within this distance is
            the main layer seen again; without one the façade is not refined by this campaign.
        wall_retry_inits (5): when the campaign's GMM component matched to the stored main layer is not narrow
            enough to be a surface (σ > FacadeParams.surface_max_sigma), or none matches, the GMM is fitted again
            with this many starts: on the few thousand points of a side wall one random start merges the wall
            into a broad clutter component for ~10-30 % of seeds (σ 10-15 cm), whose 3σ band then drags the
            extent along the clutter; five starts found the wall for every seed tried.
        layer_gate (3.0): another new component matches a stored layer when their means (after removing the main
            layer's shift, i.e. the campaigns' misregistration) differ by at most layer_gate x sqrt(σ0² + σ1²) ...
        layer_gate_min (0.04): ... or this distance (the fused σ0 shrinks with every campaign; layers closer than
            ``min_layer_separation`` are one layer anyway).

    Elements
        iou_threshold (0.3): elements of the same layer class whose polygons overlap with at least this IoU are
            the same object (a window seen whole and one partly hidden by a car overlap by ~0.5-0.9; neighbouring
            windows never overlap).
        contain_fraction (0.6): an element with at least this share of its area inside another of the same class
            is a piece of it (a window split by an old occlusion) and merges into it.
        piece_aligned_share (0.8): two windows/doors that overlap and whose extents along s (or along t) share at
            least this fraction of the longer one are pieces of one opening: the top of a window one campaign saw
            above a car and the rest another saw below (neighbouring windows never overlap).
        piece_overlap_fraction (0.25): ... and two windows/doors of which one lies at least this share of its area
            inside the other are pieces of one opening too: the top of a window one campaign measured wider than
            another (neighbouring windows never overlap; ``contain_fraction`` is for all elements).
        line_offsets (1): each shape's edges give candidate lines at this many cells either side for the
            vote-map rectangle refit.
        window_bottom_margin (0.2): when a fused rectangle of a door's size starts within the detection's
            ``door_bottom_tol`` of the façade's bottom and a shape saw a door there, a shape typed window that
            starts more than this above the fused rectangle does not vote on its kind: it was a window by the
            height of its bottom (a van hid the door's lowest part), which the fused opening no longer has.
        max_window_uncertainty (0.5): a window/door merged from matched shapes whose weighted eq. (3) ε exceeds
            this after fusion (campaigns saw wall across it) is dropped. A stored one the new campaign saw without
            finding it is judged by evidence weight instead (``outweighed_by_wall``): a striped vote map (a door
            leaf read as wall on every other scan line) has a high ε although its opening evidence dominates.
        enclosed_wall_share (0.5): an unknown region the new campaign saw becomes a window when the fused votes
            hold a rectangle in it with ε <= ``max_window_uncertainty`` and at least this share of the cells just
            outside each of its four sides carries net wall weight (enclosed by wall); 1.0 switches it off.
        enclosed_max_grow (1.0): ... a side without wall just outside (a balcony parapet hides the window's lower
            part: cells no campaign voted on) reaches across such cells by at most this many metres to the wall
            that encloses it; 0 switches the growth off.
        seen_fraction (0.5): a stored window is re-scored only when the new campaign saw at least this share of its
            cells; otherwise it is left exactly as stored. Likewise a stored window one campaign saw is split over
            two new shapes by the new campaign's wall votes on the strip between them only when it saw this share
            of the strip (``_split_bridged``). And a new shape matching no stored one keeps the cells where its
            votes tie the earlier campaigns' wall votes when those campaigns saw less than this share of its cells
            (``_partly_seen_before``: their wall votes come from a part view).
        refit_keep_share (0.5): a re-scored stored window/door whose refitted rectangle keeps less than this share
            of its opening evidence keeps its stored rectangle: such a refit found the patch the new campaign did
            not read as wall (a strip of a door leaf), not the opening's sides.
        structure_vote (0.5): a structure keeps the pixels that at least this share of the campaigns that saw them
            saw as the object.
        min_conflict_area (0.02): overlaps between objects on two layers smaller than this (m²; half-cell outline
            buffers) are not conflicts.

    Roofs (aerial)
        roof_min_height (2.0): aerial points at least this far above the ground around the footprint are roof
            candidates ...
        roof_ground_ring (5.0): ... the ground being the 10th percentile height of the ground points (ASPRS 2, or
            the façade stage's height rule) within this distance of the footprint's bounding box ...
        roof_buffer (0.5): ... within this distance of the footprint (eaves).
        roof_min_points (30): planes with fewer inliers are ignored.
        roof_max_slope_deg (75.0): steeper planes are walls, not roofs.
        roof_match_angle_deg (5.0): a new roof plane matches a stored one within this normal angle ...
        roof_match_distance (0.3): ... and this vertical distance between the planes at the middle of the new
            outline, and overlapping outlines.
        roof_outline_cell (0.5): outlines are concave hulls of the inliers snapped to half this size and buffered by
            half of it (aerial point spacing is 0.3-0.5 m) ...
        roof_concave_ratio (0.3): ... with this shapely concave_hull ratio (0 most concave, 1 convex hull).
    """

    section = "refine"
    constraints: ClassVar[dict[str, str]] = {
        "association_distance": ">= 0",
        "extend_margin": ">= 0",
        "corner_margin": ">= 0",
        "yield_depth": ">= 0",
        "window_bottom_margin": ">= 0",
        "extend_min": ">= 0",
        "extend_min_area": ">= 0",
        "extend_column_share": "[0, 1]",
        "normal_max_angle_deg": ">= 0",
        "min_element_density": ">= 0",
        "main_layer_gate": ">= 0",
        "wall_retry_inits": ">= 0",
        "layer_gate": ">= 0",
        "layer_gate_min": ">= 0",
        "iou_threshold": ">= 0",
        "contain_fraction": ">= 0",
        "piece_aligned_share": "(0, 1]",
        "piece_overlap_fraction": "(0, 1]",
        "line_offsets": ">= 0",
        "max_window_uncertainty": ">= 0",
        "enclosed_wall_share": ">= 0",
        "enclosed_max_grow": ">= 0",
        "seen_fraction": ">= 0",
        "refit_keep_share": "[0, 1]",
        "structure_vote": ">= 0",
        "min_conflict_area": ">= 0",
        "roof_min_height": ">= 0",
        "roof_ground_ring": ">= 0",
        "roof_buffer": ">= 0",
        "roof_min_points": ">= 0",
        "roof_max_slope_deg": ">= 0",
        "roof_match_angle_deg": ">= 0",
        "roof_match_distance": ">= 0",
        "roof_outline_cell": ">= 0",
        "roof_concave_ratio": ">= 0",
    }

    association_distance: float = 2.0
    extend_margin: float = 2.0
    corner_margin: float = 0.5
    yield_depth: float = 0.3
    window_bottom_margin: float = 0.2
    extend_min: float = 0.2
    extend_min_area: float = 1.0
    extend_column_share: float = 0.1
    normal_max_angle_deg: float = 5.0
    min_element_density: float = 20.0
    main_layer_gate: float = 0.3
    wall_retry_inits: int = 5
    layer_gate: float = 3.0
    layer_gate_min: float = 0.04
    iou_threshold: float = 0.3
    contain_fraction: float = 0.6
    piece_aligned_share: float = 0.8
    piece_overlap_fraction: float = 0.25
    line_offsets: int = 1
    max_window_uncertainty: float = 0.5
    enclosed_wall_share: float = 0.5
    enclosed_max_grow: float = 1.0
    seen_fraction: float = 0.5
    refit_keep_share: float = 0.5
    structure_vote: float = 0.5
    min_conflict_area: float = 0.02
    roof_min_height: float = 2.0
    roof_ground_ring: float = 5.0
    roof_buffer: float = 0.5
    roof_min_points: int = 30
    roof_max_slope_deg: float = 75.0
    roof_match_angle_deg: float = 5.0
    roof_match_distance: float = 0.3
    roof_outline_cell: float = 0.5
    roof_concave_ratio: float = 0.3

    def __post_init__(self) -> None:
        check_params(self)
        positive = ("association_distance", "main_layer_gate", "layer_gate", "max_window_uncertainty")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("iou_threshold", "contain_fraction", "seen_fraction", "structure_vote", "enclosed_wall_share",
                     "piece_aligned_share", "piece_overlap_fraction"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1]")
        if self.wall_retry_inits < 1:
            raise ValueError("wall_retry_inits must be >= 1")
        if min(self.line_offsets, self.extend_margin, self.extend_min, self.extend_min_area) < 0:
            raise ValueError("line_offsets, extend_margin, extend_min and extend_min_area must be >= 0")


# ----------------------------------------------------------------------------------------------------------------------
# Depth layers: the Gaussian product (eq. 4-7)


def fuse_gaussians(mu0: float, sigma0: float, mu1: float, sigma1: float) -> tuple[float, float]:
    """Paper eq. (4)-(7): N(μ0, σ0) · N(μ1, σ1) ∝ N(μ', σ') with k = σ0² / (σ0² + σ1²), μ' = μ0 + k (μ1 - μ0),
    σ'² = σ0² - k σ0² (a Kalman update of the stored layer by the new measurement)."""
    v0, v1 = float(sigma0) ** 2, float(sigma1) ** 2
    if v0 + v1 <= 0:
        return 0.5 * (float(mu0) + float(mu1)), 0.0
    k = v0 / (v0 + v1)
    mu = float(mu0) + k * (float(mu1) - float(mu0))
    return mu, math.sqrt(max(v0 - k * v0, 0.0))


def _main_match(main: Layer | None, new: list[Layer], params: RefineParams) -> int | None:
    """The new component that is the stored main layer seen again: the heaviest within ``main_layer_gate``."""
    near = [i for i, la in enumerate(new) if main is not None and abs(la.mu - main.mu) <= params.main_layer_gate]
    return max(near, key=lambda i: (new[i].weight, -i)) if near else None


def match_layers(stored: list[Layer], main_id: int | None, new: list[Layer],
                 params: RefineParams) -> tuple[dict[int, int], float]:
    """Match new layers (indices) to stored layer ids: {new index: stored layer id}, and the main layer's shift.

    The stored main layer takes the heaviest new component within ``main_layer_gate`` of it; the other components,
    their depths corrected by the main layer's shift (the campaigns' relative misregistration along the normal),
    take the nearest unmatched stored layer within the gate (closest pairs first). Returns ({}, nan) when the main
    layer was not seen again.
    """
    main = next((la for la in stored if la.layer_id == main_id), None)
    j_main = _main_match(main, new, params)
    if j_main is None:
        return {}, math.nan
    shift = new[j_main].mu - main.mu
    pairs = []
    for i, la in enumerate(new):
        if i == j_main:
            continue
        for old in stored:
            if old.layer_id == main.layer_id:
                continue
            gap = abs(la.mu - shift - old.mu)
            gate = max(params.layer_gate * math.hypot(old.sigma, la.sigma), params.layer_gate_min)
            if gap <= gate:
                pairs.append((gap, i, old.layer_id))
    matches = {j_main: main.layer_id}
    used = {main.layer_id}
    for _, i, lid in sorted(pairs):
        if i not in matches and lid not in used:
            matches[i] = lid
            used.add(lid)
    return matches, shift


def _fused_layers(stored: list[Layer], new: list[Layer], matches: dict[int, int], n_old: int, n_new: int,
                  campaign_id: int) -> tuple[list[Layer], dict[int, int]]:
    """Layers after the fusion (eq. 4-7 for matched pairs, unmatched new components appended with fresh ids) and
    {new index: fused layer id}. Weights are mixtures of both campaigns' weights by point count; ``n_points`` add."""
    total = max(n_old + n_new, 1)
    out = [dataclasses.replace(la, campaigns=list(la.campaigns), weight=la.weight * n_old / total) for la in stored]
    by_id = {la.layer_id: la for la in out}
    next_id = max((la.layer_id for la in stored), default=-1) + 1
    id_map: dict[int, int] = {}
    for i, la in enumerate(new):
        if i in matches:
            old = by_id[matches[i]]
            old.mu, old.sigma = fuse_gaussians(old.mu, old.sigma, la.mu, la.sigma)
            old.weight += la.weight * n_new / total
            old.n_points += int(la.n_points)
            old.campaigns = sorted(set(old.campaigns) | {campaign_id})
            id_map[i] = old.layer_id
        else:
            out.append(Layer(layer_id=next_id, mu=la.mu, sigma=la.sigma, weight=la.weight * n_new / total,
                             n_points=int(la.n_points), campaigns=[campaign_id]))
            id_map[i] = next_id
            next_id += 1
    out.sort(key=lambda la: la.layer_id)  # the store's order: a map reloaded from it is the same map
    return out, id_map


def _fuse_normal(n0: np.ndarray, w0: float, n1: np.ndarray, w1: float, max_angle_deg: float) -> np.ndarray:
    """Horizontal unit normal combining the stored (n0) and new (n1) normals weighted by point counts; n0 when n1 is
    further than ``max_angle_deg`` from it."""
    n0 = np.asarray(n0, dtype=np.float64)[:2]
    n1 = np.asarray(n1, dtype=np.float64)[:2]
    if float(n0 @ n1) < 0:
        n1 = -n1
    if float(n0 @ n1) < math.cos(math.radians(max_angle_deg)) or w1 <= 0:
        return n0 / np.linalg.norm(n0)
    n = max(w0, 0.0) * n0 + w1 * n1
    return n / np.linalg.norm(n)


# ----------------------------------------------------------------------------------------------------------------------
# Evidence grids


@dataclasses.dataclass(frozen=True)
class _Grid:
    """A façade's cell grid: origin (s0, t0), cell size and shape (rows, cols)."""

    s0: float
    t0: float
    cell: float
    shape: tuple[int, int]

    def raster(self, polygon) -> np.ndarray:
        """Cells whose centre lies inside ``polygon``."""
        out = np.zeros(self.shape, dtype=bool)
        if polygon is None or polygon.is_empty:
            return out
        rows, cols = self.shape
        x0, y0, x1, y1 = polygon.bounds
        c0 = max(int(math.floor((x0 - self.s0) / self.cell)), 0)
        c1 = min(int(math.ceil((x1 - self.s0) / self.cell)), cols)
        r0 = max(int(math.floor((y0 - self.t0) / self.cell)), 0)
        r1 = min(int(math.ceil((y1 - self.t0) / self.cell)), rows)
        if c1 <= c0 or r1 <= r0:
            return out
        cs = self.s0 + (np.arange(c0, c1) + 0.5) * self.cell
        ts = self.t0 + (np.arange(r0, r1) + 0.5) * self.cell
        ss, tt = np.meshgrid(cs, ts)
        out[r0:r1, c0:c1] = shapely.contains_xy(polygon, ss, tt)
        return out

    def line(self, x: float, axis: int) -> int:
        """Index of the grid line nearest to coordinate ``x`` (axis 0: s / columns, 1: t / rows)."""
        origin = self.s0 if axis == 0 else self.t0
        return int(round((x - origin) / self.cell))

    def coord(self, index: int, axis: int) -> float:
        return (self.s0 if axis == 0 else self.t0) + index * self.cell


def _extended_extent(extent: tuple[float, float, float, float], st: np.ndarray, cell: float,
                     params: RefineParams) -> tuple[float, float, float, float]:
    """The extent grown towards the new wall samples ``st`` (s, t of the main layer's points) on each side where
    they cover at least ``extend_min_area`` of cells at least ``extend_min`` beyond it (a few stray points of a
    sparse side wall, or a few cm of misregistration, grow nothing); the side moves to the samples' 0.1 % / 99.9 %
    quantile. Lower sides move by whole cells so that the old grid stays aligned inside the new one."""
    s0, s1, t0, t1 = extent
    min_cells = params.extend_min_area / (cell * cell)
    out = [s0, s1, t0, t1]
    for k, (axis, sign) in enumerate(((0, -1), (0, 1), (1, -1), (1, 1))):
        beyond = st[sign * (st[:, axis] - extent[k]) > params.extend_min]
        if len(beyond) == 0:
            continue
        cells = np.unique(np.floor(beyond / cell).astype(np.int64), axis=0)
        if len(cells) < min_cells:
            continue
        if axis == 0:
            beyond = _supported_columns(beyond, cells, sign, cell, params.extend_column_share)
        reach = float(np.quantile(beyond[:, axis], 0.001 if sign < 0 else 0.999))
        if sign < 0:
            out[k] = extent[k] - math.ceil((extent[k] - reach) / cell - 1e-9) * cell
        else:
            out[k] = max(extent[k], reach)
    return out[0], out[1], out[2], out[3]


def _supported_columns(st: np.ndarray, cells: np.ndarray, sign: int, cell: float, share: float) -> np.ndarray:
    """The samples ``st`` up to the outermost column of cells (side ``sign``) holding at least ``share`` of the
    fullest column's cells: a wall ends in a column of samples over its height, a handful of points past its corner
    (the next wall, a neighbour's, misregistration) does not reach that far."""
    columns, counts = np.unique(cells[:, 0], return_counts=True)
    full = columns[counts >= share * counts.max()]
    column = np.floor(st[:, 0] / cell).astype(np.int64)
    return st[column <= full.max()] if sign > 0 else st[column >= full.min()]


def pad_evidence(ev: FacadeEvidence | None, extent: tuple[float, float, float, float],
                 cell: float) -> FacadeEvidence:
    """Evidence grids placed on the grid of a larger ``extent`` (aligned: its origin differs by whole cells);
    zeros where the old grid did not reach. ``None`` gives all-zero grids."""
    shape = grid_shape(extent, cell)
    out = FacadeEvidence(cell=cell, s0=float(extent[0]), t0=float(extent[2]),
                         window_votes=np.zeros(shape, np.int32), object_votes=np.zeros(shape, np.int32),
                         seen=np.zeros(shape, np.int32))
    if ev is None:
        return out
    r_off = int(round((ev.t0 - extent[2]) / cell))
    c_off = int(round((ev.s0 - extent[0]) / cell))
    rows, cols = ev.shape
    if r_off < 0 or c_off < 0 or r_off + rows > shape[0] or c_off + cols > shape[1]:
        raise LidarmapError("internal: the grown façade grid does not contain the stored one")
    for name in ("window_votes", "object_votes", "seen"):
        getattr(out, name)[r_off:r_off + rows, c_off:c_off + cols] = getattr(ev, name)
    return out


def _old_area(ev: FacadeEvidence | None, extent: tuple[float, float, float, float], cell: float) -> np.ndarray:
    """Cells of the grid over ``extent`` that the stored grid ``ev`` covered (before the extent grew)."""
    if ev is None:
        return np.zeros(grid_shape(extent, cell), dtype=bool)
    return pad_evidence(dataclasses.replace(ev, seen=np.ones(ev.shape, np.int32)), extent, cell).seen > 0


def _add_evidence(a: FacadeEvidence, b: FacadeEvidence) -> FacadeEvidence:
    """Vote grids of two observations on one grid added (campaigns per pixel)."""
    def add(name: str) -> np.ndarray:
        return (getattr(a, name) + getattr(b, name)).astype(np.int32)

    return FacadeEvidence(cell=a.cell, s0=a.s0, t0=a.t0, window_votes=add("window_votes"),
                          object_votes=add("object_votes"), seen=add("seen"))


# ----------------------------------------------------------------------------------------------------------------------
# Weighted eq. (3) on the vote map


def net_votes(window_votes: np.ndarray, object_votes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weights of the vote map: (window weight max(W - O, 0), object weight max(O - W, 0)).

    W campaigns saw the pixel as window, O as wall or another object: their votes cancel, so a pixel on a window's
    edge that the campaigns' sampling put on either side carries little weight, a pixel every campaign saw as window
    the most."""
    w = np.asarray(window_votes, dtype=np.int64)
    o = np.asarray(object_votes, dtype=np.int64)
    return np.maximum(w - o, 0), np.maximum(o - w, 0)


def weighted_window_uncertainty(window_votes: np.ndarray, object_votes: np.ndarray,
                                rect: tuple[int, int, int, int]) -> float:
    """Eq. (3) on the vote map for the rectangle (r0, r1, c0, c1) (cells [r0, r1) x [c0, c1)).

    With the pixel weights of :func:`net_votes` (w window, o object): N_hole = Σw, N_diff = Σ_outside w +
    Σ_inside o, N_obj = Σ_inside o (object pixels count twice, as in eq. 3), ε = (N_diff + N_obj) / N_hole.
    Pixels no campaign saw as window or object -- occluded, or holes a campaign could not explain (a window split by
    a pole's shadow) -- weigh nothing (§2.5: "the region detected as other objects instead of the occlusion would
    count as error"). With one campaign this is eq. (3) with occluded pixels left out.
    """
    w, o = net_votes(window_votes, object_votes)
    n_hole = int(w.sum())
    if n_hole == 0:
        return math.inf
    r0, r1, c0, c1 = (max(int(v), 0) for v in rect)
    inside = (slice(r0, r1), slice(c0, c1))
    return (n_hole - int(w[inside].sum()) + 2 * int(o[inside].sum())) / n_hole


def refit_rectangle(window_votes: np.ndarray, object_votes: np.ndarray, col_lines, row_lines,
                    prefer: np.ndarray | None = None,
                    forbidden: np.ndarray | None = None) -> tuple[tuple[int, int, int, int] | None, float]:
    """The rectangle (r0, r1, c0, c1) over candidate grid lines minimising :func:`weighted_window_uncertainty`,
    and its ε. Every pair of column lines and every pair of row lines is a candidate; all are scored at once with
    integral images. ``(None, inf)`` without window weight, or when every candidate holds a ``forbidden`` cell.

    Ties -- cells whose window and wall votes cancel weigh nothing either way, so several rectangles can score the
    same -- go to the candidate holding most of ``prefer`` (a per-cell share in [0, 1] of the matched shapes'
    evidence claiming the cell: Σ over the rectangle of 2·prefer − 1), i.e. the extent the better-evidenced shapes
    gave; without ``prefer``, the first candidate in line order."""
    w, o = net_votes(window_votes, object_votes)
    n_hole = int(w.sum())
    if n_hole == 0:
        return None, math.inf
    rows, cols = w.shape
    cl = np.unique(np.clip(np.asarray(list(col_lines), dtype=np.int64), 0, cols))
    rl = np.unique(np.clip(np.asarray(list(row_lines), dtype=np.int64), 0, rows))
    ci, cj = np.triu_indices(len(cl), k=1)
    ri, rj = np.triu_indices(len(rl), k=1)
    if len(ci) == 0 or len(ri) == 0:
        rr, cc = np.nonzero(w)
        rect = (int(rr.min()), int(rr.max()) + 1, int(cc.min()), int(cc.max()) + 1)
        return rect, weighted_window_uncertainty(window_votes, object_votes, rect)
    iw, io = integral_image(w), integral_image(o)
    R0, C0 = np.meshgrid(rl[ri], cl[ci], indexing="ij")
    R1, C1 = np.meshgrid(rl[rj], cl[cj], indexing="ij")
    err = n_hole - box_sums(iw, R0, R1, C0, C1) + 2 * box_sums(io, R0, R1, C0, C1)
    if forbidden is not None and forbidden.any():
        err = np.where(box_sums(integral_image(forbidden), R0, R1, C0, C1) > 0, np.inf, err)
        if not np.isfinite(err).any():
            return None, math.inf
    if prefer is None:
        best = np.unravel_index(int(np.argmin(err)), err.shape)
    else:  # among the tied minima, the candidate closest to the preferred extent, then the smallest
        share = box_sums(integral_image(2.0 * np.asarray(prefer, dtype=np.float64) - 1.0, np.float64), R0, R1, C0, C1)
        tied = np.flatnonzero(err.ravel() == err.min())
        area = ((R1 - R0) * (C1 - C0)).ravel()[tied]
        order = np.lexsort((area, -np.round(share.ravel()[tied], 9)))
        best = np.unravel_index(int(tied[order[0]]), err.shape)
    rect = (int(R0[best]), int(R1[best]), int(C0[best]), int(C1[best]))
    return rect, float(err[best]) / n_hole


# ----------------------------------------------------------------------------------------------------------------------
# Elements


def _weight(e: Element) -> int:
    return max(1, len(e.campaigns))


def _iou_pairs(a: list, b: list, same: np.ndarray, params: RefineParams,
               aligned: bool = False) -> list[tuple[float, int, int]]:
    """(score, i, j) for polygons a[i], b[j] of the same class (``same[i, j]``) that are one object: IoU >=
    ``iou_threshold``, or one lies ``contain_fraction`` inside the other, or (``aligned``: windows and doors) they
    overlap and are aligned pieces (:func:`_aligned_pieces`) or one lies ``piece_overlap_fraction`` inside the
    other. Score = IoU."""
    if not a or not b:
        return []
    ga, gb = np.array(a, dtype=object), np.array(b, dtype=object)
    ba, bb = shapely.bounds(ga), shapely.bounds(gb)
    touch = (ba[:, None, 0] < bb[None, :, 2]) & (bb[None, :, 0] < ba[:, None, 2]) \
        & (ba[:, None, 1] < bb[None, :, 3]) & (bb[None, :, 1] < ba[:, None, 3]) & same
    ii, jj = np.nonzero(touch)
    if len(ii) == 0:
        return []
    inter = shapely.area(shapely.intersection(ga[ii], gb[jj]))
    area_a, area_b = shapely.area(ga[ii]), shapely.area(gb[jj])
    union = area_a + area_b - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    piece = inter / np.maximum(np.minimum(area_a, area_b), 1e-12)
    ok = (iou >= params.iou_threshold) | (piece >= params.contain_fraction)
    if aligned:
        ok |= (inter > 0) & (_aligned_pieces(ba[ii], bb[jj], params.piece_aligned_share)
                             | (piece >= params.piece_overlap_fraction))
    return [(float(max(iou[k], 0.0)), int(ii[k]), int(jj[k])) for k in np.flatnonzero(ok)]


def _aligned_pieces(ba: np.ndarray, bb: np.ndarray, share: float) -> np.ndarray:
    """Per row of bounds (minx, miny, maxx, maxy) pairs: whether their extents along s, or along t, overlap by at
    least ``share`` of the longer one (one window seen in two parts, stacked or side by side)."""
    def along(lo: int, hi: int) -> np.ndarray:
        common = np.minimum(ba[:, hi], bb[:, hi]) - np.maximum(ba[:, lo], bb[:, lo])
        longer = np.maximum(ba[:, hi] - ba[:, lo], bb[:, hi] - bb[:, lo])
        return common >= share * np.maximum(longer, 1e-12)
    return along(0, 2) | along(1, 3)


def _clusters(old: list[Element], new: list[Element], key, params: RefineParams,
              aligned: bool = False) -> list[tuple[list[int], list[int]]]:
    """Groups (old indices, new indices) of elements that are one object (connected by :func:`_iou_pairs`)."""
    same = np.array([[key(o) == key(n) for n in new] for o in old], dtype=bool).reshape(len(old), len(new))
    pairs = _iou_pairs([e.polygon for e in old], [e.polygon for e in new], same, params, aligned)
    parent = list(range(len(old) + len(new)))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for _, i, j in pairs:
        a, b = find(i), find(len(old) + j)
        if a != b:
            parent[max(a, b)] = min(a, b)
    groups: dict[int, tuple[list[int], list[int]]] = {}
    for k in range(len(old) + len(new)):
        g = groups.setdefault(find(k), ([], []))
        (g[0] if k < len(old) else g[1]).append(k if k < len(old) else k - len(old))
    return [groups[r] for r in sorted(groups)]


def _keeper(olds: list[Element]) -> Element:
    """The stored member whose id a merged object keeps: seen by the most campaigns, then the oldest id."""
    return min(olds, key=lambda e: (-_weight(e), e.element_id))


class _Ids:
    """Fresh element ids for one façade (never an id in use or freed in this update)."""

    def __init__(self, elements: list[Element]):
        self.next = max((e.element_id for e in elements), default=-1) + 1

    def __call__(self) -> int:
        self.next += 1
        return self.next - 1


@dataclasses.dataclass
class _Votes:
    """Fused evidence of one façade on its grid, plus what the new campaign alone saw."""

    grid: _Grid
    window: np.ndarray
    objects: np.ndarray
    seen: np.ndarray
    seen_new: np.ndarray
    old_area: np.ndarray  # cells the façade's grid covered before this campaign grew it
    window_new: np.ndarray | None = None  # the new campaign's own window votes (None: all votes count as old)

    def window_old(self) -> np.ndarray:
        """Window votes of the campaigns before this one."""
        return self.window if self.window_new is None else self.window - self.window_new


def evidence_weight(window_votes: np.ndarray, cells: np.ndarray) -> float:
    """The opening evidence behind one shape: the sum of the window votes (per-cell weights 1-4 from
    :func:`lidarmap.facade.evidence.vote_weights`) over its cells."""
    return float(np.asarray(window_votes, dtype=np.float64)[cells].sum())


def weighted_kind(kinds: list[ElementKind], weights: list[float], tie: ElementKind) -> ElementKind:
    """Window or door by weighted vote: the kind whose shapes carry the most opening evidence (``tie`` on a tie).
    A door seen well by one campaign outweighs a window seen at a grazing angle by two."""
    total: dict[ElementKind, float] = {}
    for k, w in zip(kinds, weights):
        total[k] = total.get(k, 0.0) + float(w)
    return max(total, key=lambda k: (total[k], k is tie))


def outweighed_by_wall(window_votes: np.ndarray, object_votes: np.ndarray, cells: np.ndarray) -> bool:
    """Whether the accumulated wall/object evidence over an opening's cells exceeds its opening evidence (the
    weighted votes of all campaigns so far): such an element does not exist."""
    if not cells.any():
        return False
    o = float(np.asarray(object_votes, dtype=np.float64)[cells].sum())
    return o > float(np.asarray(window_votes, dtype=np.float64)[cells].sum())


def _member_weights(members: list[Element], n_old: int, votes: _Votes, within: np.ndarray | None = None) -> list[float]:
    """Evidence weight of each member: stored shapes (the first ``n_old``) by the earlier campaigns' window votes
    over their cells, the new campaign's shapes by its own; at least the campaign count, so that a shape whose
    votes a neighbour's claimed still counts. ``within`` (cells): only the votes there count."""
    old_w = votes.window_old()
    new_w = votes.window if votes.window_new is None else votes.window_new
    out = []
    for k, m in enumerate(members):
        cells = votes.grid.raster(m.polygon)
        if within is not None:
            cells = cells & within
        out.append(max(evidence_weight(old_w if k < n_old else new_w, cells), float(_weight(m))))
    return out


def _lines_near(g: _Grid, values, axis: int, lo: int, off: int) -> list[int]:
    """Grid line indices (relative to ``lo``) within ``off`` lines of each coordinate in ``values`` (axis 0: s, 1: t):
    the candidate sides a refit may take from a shape's or a region's bounds."""
    return [g.line(float(x), axis) - lo + k for x in values for k in range(-off, off + 1)]


def _merge_opening(members: list[Element], keep_id: int, votes: _Votes, params: RefineParams,
                   extent: tuple[float, float, float, float], n_old: int = 0,
                   extra_bounds: np.ndarray | None = None, min_size: float = 0.0,
                   doors: OpeningParams | None = None, foreign: np.ndarray | None = None) -> Element | None:
    """One window/door from matched shapes: vote-map refit over their edge lines, sub-cell sides averaged over the
    shapes that proposed the chosen line (weighted by campaigns), kind by evidence-weighted vote
    (:func:`weighted_kind`; the first ``n_old`` members are stored shapes), a window when the fused rectangle has
    no door's size by ``doors``. ``None`` when the fused ε exceeds
    ``max_window_uncertainty`` or the wall evidence over it outweighs its opening evidence
    (:func:`outweighed_by_wall`). ``extra_bounds`` (rows of s_lo, t_lo, s_hi, t_hi): more candidate sides, from
    stored unknown regions the shapes lie in. ``None`` too when a side of the fused rectangle, cut to the extent,
    is shorter than ``min_size``. ``doors``: the detection's door sizes (see
    :func:`_kind_voters`). ``foreign``: the façade's cells inside stored openings that are not members; their
    votes are not this opening's, and the fused rectangle may not reach into their interior (see
    :func:`_foreign_cells`)."""
    g = votes.grid
    off = params.line_offsets
    bounds = np.array([[*m.polygon.bounds] for m in members])  # minx (s_lo), miny (t_lo), maxx (s_hi), maxy (t_hi)
    lines = bounds if extra_bounds is None or len(extra_bounds) == 0 else np.vstack([bounds, extra_bounds])
    pad = off + 2
    c_lo = max(g.line(lines[:, 0].min(), 0) - pad, 0)
    c_hi = min(g.line(lines[:, 2].max(), 0) + pad, g.shape[1])
    r_lo = max(g.line(lines[:, 1].min(), 1) - pad, 0)
    r_hi = min(g.line(lines[:, 3].max(), 1) + pad, g.shape[0])
    if c_hi <= c_lo or r_hi <= r_lo:
        return None
    patch = (slice(r_lo, r_hi), slice(c_lo, c_hi))
    evidence = _member_weights(members, n_old, votes)
    claimed = np.zeros((r_hi - r_lo, c_hi - c_lo), dtype=bool)
    share = np.zeros(claimed.shape)  # of the members' evidence claiming each cell ...
    share_old = np.zeros(claimed.shape)  # ... and of the stored members' alone
    for k, (m, weight) in enumerate(zip(members, evidence)):
        cells = g.raster(m.polygon)[patch]
        claimed |= cells
        share += weight * cells
        if k < n_old:
            share_old += weight * cells
    total = max(sum(evidence), 1e-12)
    others = np.zeros(claimed.shape, dtype=bool) if foreign is None else foreign[patch]
    kept_ties = share_old / total > 0.5
    if n_old == 0 and _partly_seen_before(votes, patch, claimed, params.seen_fraction):
        kept_ties = kept_ties | claimed
    w = np.where(others, 0, _own_votes(votes.window[patch], votes.objects[patch], claimed & ~others, kept_ties))
    cols = _lines_near(g, np.r_[lines[:, 0], lines[:, 2]], 0, c_lo, off)
    rows = _lines_near(g, np.r_[lines[:, 1], lines[:, 3]], 1, r_lo, off)
    # ties go to the extent the stored shapes' evidence claims; a new shape alone keeps the plain line order, except
    # against the sides of a stored unknown region: cells no campaign voted on tie, and the first line in order (the
    # region's far side) stretched the shape over them (issue 18 round 11, dev seed 157: a window 0.94 m wide grew
    # 2.25 m to the left side of the region campaign 1 could not see -- a tree and a van stood in front -- across a
    # pier and the next window)
    tie_to_shapes = n_old > 0 or (extra_bounds is not None and len(extra_bounds) > 0)
    rect, eps = refit_rectangle(w, votes.objects[patch], cols, rows, share / total if tie_to_shapes else None,
                                ndimage.binary_erosion(others) if others.any() else None)
    if rect is None or eps > params.max_window_uncertainty:
        return None
    weights = np.array([_weight(m) for m in members], dtype=np.float64)

    def side(k: int, line: int, axis: int) -> float:
        near = np.abs(np.array([g.line(x, axis) for x in bounds[:, k]]) - line) <= off
        if not near.any():
            return g.coord(line, axis)
        return float(np.average(bounds[near, k], weights=weights[near]))

    r0, r1, c0, c1 = rect
    s_lo, s_hi = side(0, c0 + c_lo, 0), side(2, c1 + c_lo, 0)
    t_lo, t_hi = side(1, r0 + r_lo, 1), side(3, r1 + r_lo, 1)
    s0, s1, t0, t1 = extent
    poly = box(max(s_lo, s0), max(t_lo, t0), min(s_hi, s1), min(t_hi, t1))
    if poly.is_empty or poly.area <= 0:
        return None
    b = poly.bounds
    if min(b[2] - b[0], b[3] - b[1]) < min_size:
        return None  # a sliver (under the eave, beyond the façade's extent): not an opening of this façade
    if outweighed_by_wall(votes.window, votes.objects, g.raster(poly)):
        return None
    keeper = next((m for m in members if m.element_id == keep_id), members[0])
    # the kind of the fused rectangle goes by the evidence each shape holds over it: the part of a shape the refit
    # rejected (a door shape twice the window's width, its other half wall) has no say in what the opening is
    evidence_over = _member_weights(members, n_old, votes, g.raster(poly))
    voters = _kind_voters(members, poly, doors, n_old, bottom=(extent[2], params.window_bottom_margin))
    voting = [m for m, v in zip(members, voters) if v]
    votes_on_kind = [(m.kind, w) for m, w, v in zip(members, evidence_over, voters) if v]
    kind = weighted_kind([k for k, _ in votes_on_kind], [w for _, w in votes_on_kind], keeper.kind)
    if kind is ElementKind.DOOR and doors is not None and not _door_sized(poly, doors) \
            and not _door_verdict_stands(voting, poly):
        # the detection types an opening without a door's size a window whatever else it sees, and so does the
        # fusion (issue 18 round 13, dev seed 178: a glazed window 1.82 m tall that one campaign saw 2.2 m tall
        # and typed a door stayed a door after the refit cut it to 1.69 m)
        kind = ElementKind.WINDOW
    layered = [m for m in members if m.layer_id is not None]
    layer_id = max(layered, key=_weight).layer_id if layered else None
    campaigns = sorted({c for m in members for c in m.campaigns})
    return Element(element_id=keep_id, kind=kind, polygon=poly, layer_id=layer_id, uncertainty=float(eps),
                   n_points=int(sum(m.n_points for m in members)), campaigns=campaigns)


def _partly_seen_before(votes: _Votes, patch, claimed: np.ndarray, seen_fraction: float) -> bool:
    """Whether the campaigns before this one saw less than ``seen_fraction`` of the cells a new shape claims. Their
    wall votes there come from a part view of the opening -- a van hid the rest, so no detection could close its
    border -- and a tie with the campaign that saw all of it is no evidence against the shape (issue 18 round 29,
    dev seed 410: a van hid the lower 1.8 m of a flush door from campaign 1, whose weight-1 wall votes on the top
    of the leaf tied campaign 2's door votes; the fused door was cut to a 1.6 m window)."""
    seen_old = (votes.seen[patch] - votes.seen_new[patch])[claimed] > 0  # the patch only: called per opening
    return bool(seen_old.size) and float(seen_old.mean()) < seen_fraction


def _door_verdict_stands(voting: list[Element], fused) -> bool:
    """Whether a fused rectangle without a door's size stays a door: every shape voting on its kind is a door and
    either two campaigns or more saw it (issue 18 round 20, dev seed 273: a flush door two campaigns measured
    0.98 m wide became a 0.67 m window after a third saw the edge of its leaf as wall), or the refit made it no
    smaller than one of them: the detection typed a door of that size for reasons the fusion does not see, such
    as a side ending at cells a van hid (dev seed 272: a new door 0.63 m wide was stored a window)."""
    if not voting or any(m.kind is not ElementKind.DOOR for m in voting):
        return False
    if len({c for m in voting for c in m.campaigns}) >= 2:
        return True
    w, h = _size(fused)
    return any(w >= mw - 0.01 and h >= mh - 0.01 for mw, mh in map(_size, (m.polygon for m in voting)))


def _size(polygon) -> tuple[float, float]:
    """A rectangle's width (s) and height (t)."""
    s0, t0, s1, t1 = polygon.bounds
    return s1 - s0, t1 - t0


def _door_sized(polygon, doors: OpeningParams) -> bool:
    """Whether a rectangle has a door's size by the detection's limits (:meth:`OpeningParams.door_sized`; 1e-9 m of
    slack: fused sides are sums of sub-cell offsets)."""
    s0, t0, s1, t1 = polygon.bounds
    return doors.door_sized(s1 - s0, t1 - t0, 1e-9)


def _kind_voters(members: list[Element], fused, doors: OpeningParams | None, n_old: int = 0,
                 bottom: tuple[float, float] | None = None) -> list[bool]:
    """Which matched shapes vote on the kind of the fused rectangle ``fused`` (the first ``n_old`` members are
    stored shapes). A shape typed window whose own rectangle has no door's size was a window by its size alone
    (the detection types such shapes windows before it looks at the ground): once the fused rectangle has a
    door's size and another shape saw a door there, that verdict no longer applies and it does not vote (issue 18
    round 7, dev seed 104: a flush door 2.03 m tall that one campaign measured 1.94 m, 1 cm below
    ``door_min_height``, became a window). Likewise a window wider than ``open_door_max_width`` may be a window by
    its width alone (the detection types an opening that wide a window unless a leaf closes it): it does not vote
    on a fused rectangle no wider than that (issue 18 round 17, dev seeds 175 and 225: doors 1.46-1.47 m wide that
    an earlier campaign measured 1.85-1.94 m wide stayed windows against the door a later campaign saw). And a
    new shape the detection left undecided (``Element.kind_undecided``: a window for want of leaf evidence) does
    not vote against a door either (issue 18 round 24, dev seed 358); stored shapes carry no such flag. Since
    round 26 that holds for either kind: when the voting shapes disagree on the kind and one of them is decided,
    the undecided new shapes do not vote. ``bottom`` (the façade's bottom line, a margin): see
    :func:`_size_voters`."""
    voters = _size_voters(members, fused, doors, n_old, bottom)
    decided = [k < n_old or not m.kind_undecided for k, m in enumerate(members)]
    if len({m.kind for m, v in zip(members, voters) if v}) > 1 and any(d and v for d, v in zip(decided, voters)):
        # a verdict the detection reached for want of leaf evidence does not vote against one it measured
        voters = [d and v for d, v in zip(decided, voters)]
    return voters


def _size_voters(members: list[Element], fused, doors: OpeningParams | None, n_old: int,
                 bottom: tuple[float, float] | None = None) -> list[bool]:
    """The size part of :func:`_kind_voters`: which shapes' kinds still apply to the fused rectangle's size and
    place. With ``bottom`` = (the façade's bottom line, a margin): when the fused rectangle starts within
    ``door_bottom_tol`` of that line, a window whose own rectangle starts more than the margin higher was a window
    by the height of its bottom, which the fused one no longer has, and does not vote (issue 18 round 27, dev seed
    408: a van hid the lowest 0.3 m of a recessed door from campaigns 1 and 2, which stored a window starting
    0.55 m up; campaign 3 saw the door reach the ground and the fused rectangle did, but the window outvoted it)."""
    if doors is None or not _door_sized(fused, doors) \
            or not any(m.kind is ElementKind.DOOR for m in members):
        return [True] * len(members)
    narrow = _width(fused) <= doors.open_door_max_width + 1e-9
    t0 = fused.bounds[1]
    lowered = bottom is not None and t0 <= bottom[0] + doors.door_bottom_tol

    def applies(k: int, m: Element) -> bool:
        if m.kind is not ElementKind.WINDOW:
            return True
        if lowered and m.polygon.bounds[1] > t0 + bottom[1]:
            return False
        return _door_sized(m.polygon, doors) and not (narrow and _width(m.polygon) > doors.open_door_max_width) \
            and not (k >= n_old and m.kind_undecided)

    return [applies(k, m) for k, m in enumerate(members)]


def _width(polygon) -> float:
    """A rectangle's extent along the façade (s)."""
    s0, _, s1, _ = polygon.bounds
    return s1 - s0


def _own_votes(w: np.ndarray, o: np.ndarray, claimed: np.ndarray, kept_ties: np.ndarray | None = None) -> np.ndarray:
    """Window votes of a patch restricted to the connected parts (of positive net window weight) that touch the
    ``claimed`` cells: this opening's votes, not a neighbour's. Cells whose window votes are cancelled by as much
    wall weight lose them too -- they count as wall -- except the ``kept_ties``: cells the stored,
    better-evidenced opening claims, where a tie must not turn into evidence against it (a door leaf one campaign
    saw open and another as wall, scan line by scan line)."""
    labels, _ = ndimage.label(net_votes(w, o)[0] > 0)
    touching = np.unique(labels[claimed & (labels > 0)])
    own = np.isin(labels, touching) & (labels > 0)
    if kept_ties is not None:
        own |= (labels == 0) & kept_ties
    return np.where(own, w, 0)


def opening_uncertainty(polygon, evidence: FacadeEvidence, line_offsets: int = 1) -> float:
    """The weighted eq. (3) ε of a window/door ``polygon`` on a façade's vote map: the best rectangle whose sides
    lie on the grid lines around the polygon's sides (+- ``line_offsets``), counting only its own opening's votes
    (the refit a window seen by one campaign gets; for a refined window its stored ε)."""
    g = _Grid(evidence.s0, evidence.t0, evidence.cell, evidence.shape)
    s_lo, t_lo, s_hi, t_hi = polygon.bounds
    pad = line_offsets + 2
    r_lo, c_lo = max(g.line(t_lo, 1) - pad, 0), max(g.line(s_lo, 0) - pad, 0)
    r_hi, c_hi = min(g.line(t_hi, 1) + pad, g.shape[0]), min(g.line(s_hi, 0) + pad, g.shape[1])
    if r_hi <= r_lo or c_hi <= c_lo:
        return math.inf
    patch = (slice(r_lo, r_hi), slice(c_lo, c_hi))
    o = evidence.object_votes[patch]
    w = _own_votes(evidence.window_votes[patch], o, g.raster(polygon)[patch])

    def lines(values, origin: float, lo: int) -> list[int]:
        out = []
        for x in values:
            f = math.floor((x - origin) / g.cell)
            out += [f + k - lo for k in range(-line_offsets, line_offsets + 2)]
        return out

    _, eps = refit_rectangle(w, o, lines((s_lo, s_hi), g.s0, c_lo), lines((t_lo, t_hi), g.t0, r_lo))
    return eps


def _refit_stored(e: Element, votes: _Votes, params: RefineParams,
                  extra_bounds: np.ndarray | None = None) -> tuple[Polygon, float] | None:
    """A stored opening's rectangle refitted on the fused votes: each side on the grid lines from
    ``line_offsets`` cells outside it to anywhere inside (so a wall strip a too-wide rectangle holds is shed, not the
    opening), or on a side of ``extra_bounds`` (rows of s_lo, t_lo, s_hi, t_hi: the new campaign's unknown regions
    over it, :func:`_unknown_bounds`; ± ``line_offsets``), ties going to the stored extent; a side left on
    (± ``line_offsets`` of) its stored line keeps its stored sub-cell position. ``None`` without window weight
    around it."""
    g = votes.grid
    s_lo, t_lo, s_hi, t_hi = e.polygon.bounds
    off, pad = params.line_offsets, params.line_offsets + 2
    reach = np.array([[s_lo, t_lo, s_hi, t_hi]]) if extra_bounds is None or len(extra_bounds) == 0 else \
        np.vstack([[s_lo, t_lo, s_hi, t_hi], extra_bounds])
    r_lo, c_lo = max(g.line(reach[:, 1].min(), 1) - pad, 0), max(g.line(reach[:, 0].min(), 0) - pad, 0)
    r_hi = min(g.line(reach[:, 3].max(), 1) + pad, g.shape[0])
    c_hi = min(g.line(reach[:, 2].max(), 0) + pad, g.shape[1])
    if r_hi <= r_lo or c_hi <= c_lo:
        return None
    patch = (slice(r_lo, r_hi), slice(c_lo, c_hi))
    stored = g.raster(e.polygon)[patch]
    o = votes.objects[patch]
    w = _own_votes(votes.window[patch], o, stored, stored)
    side_lines = [g.line(s_lo, 0) - c_lo, g.line(s_hi, 0) - c_lo, g.line(t_lo, 1) - r_lo, g.line(t_hi, 1) - r_lo]
    cols = list(range(side_lines[0] - off, side_lines[1] + off + 1))
    rows = list(range(side_lines[2] - off, side_lines[3] + off + 1))
    cols += _lines_near(g, np.r_[reach[1:, 0], reach[1:, 2]], 0, c_lo, off)
    rows += _lines_near(g, np.r_[reach[1:, 1], reach[1:, 3]], 1, r_lo, off)
    rect, eps = refit_rectangle(w, o, cols, rows, stored.astype(np.float64))
    if rect is None:
        return None
    r0, r1, c0, c1 = rect
    chosen = (c0, c1, r0, r1)
    sides = [x if abs(chosen[k] - side_lines[k]) <= off else
             g.coord(chosen[k] + (c_lo if k < 2 else r_lo), 0 if k < 2 else 1)
             for k, x in enumerate((s_lo, s_hi, t_lo, t_hi))]
    return box(sides[0], sides[2], sides[1], sides[3]), float(eps)


def _holds_an_opening(support: np.ndarray, cells: np.ndarray, cell: float, min_size: float, min_fill: float) -> bool:
    """Whether an opening's support (the cells some campaign saw as opening) is an opening by the detection's own
    measures: at least the smallest opening (``min_size`` squared) and filling at least ``min_fill`` (``Ta``) of
    the stored rectangle's ``cells``. A tie between the campaigns that found such an opening and one that read it
    as wall keeps it -- a later campaign does not undo a found window on no more evidence than it had -- while a
    small or patchy support is no evidence of an opening by itself and goes (dev seeds 102, 112: a hole in a
    cornice band, a patchy stripe on a narrow side wall)."""
    n = float(support.sum())
    return n * cell * cell >= min_size * min_size - 1e-9 and n >= min_fill * float(cells.sum()) - 1e-9


def _rescored_opening(e: Element, votes: _Votes, params: RefineParams, min_size: float = 0.0,
                      min_fill: float = 0.0, extra_bounds: np.ndarray | None = None) -> Element | None:
    """A stored window/door the new campaign saw but did not find: ``None`` when the wall evidence (all campaigns so
    far) over its support -- the cells of it some campaign saw as opening -- exceeds its opening evidence there,
    or equals it on a support smaller than an opening (:func:`_holds_an_opening`; no support:
    :func:`outweighed_by_wall` over all of it); otherwise kept, its sides refitted on the fused
    votes (:func:`_refit_stored`) and its ε recomputed there. A large ε alone does not drop it: a door leaf one
    campaign reads as wall scan line by scan line leaves a striped vote map whose ε is high while the opening
    evidence still outweighs the wall's. A refit that keeps less than ``refit_keep_share`` of the opening evidence is
    not used: the stored rectangle stays; so does one keeping more that leaves a side shorter than ``min_size``,
    unless the stored rectangle is such a sliver itself (then ``None``: a sliver is no opening). ``extra_bounds``:
    more candidate sides for the refit (:func:`_refit_stored`)."""
    g = votes.grid
    cells = g.raster(e.polygon)
    if not cells.any() or votes.seen_new[cells].astype(bool).mean() < params.seen_fraction:
        return e
    # existence is judged on the opening's support, the cells some campaign saw as opening: wall strips a stored
    # rectangle too wide holds (a shutter, a reveal, the frame) say its sides are off, not that it is not there --
    # every later campaign adds wall votes to them, and they alone used to outweigh a well-observed opening.
    support = cells & (votes.window > 0)
    if not support.any():
        return None if outweighed_by_wall(votes.window, votes.objects, cells) else e
    opening = float(votes.window[support].sum())
    wall = float(votes.objects[support].sum())
    if wall > opening or (wall == opening and not _holds_an_opening(support, cells, g.cell, min_size, min_fill)):
        return None
    refit = _refit_stored(e, votes, params, extra_bounds)
    if refit is None:
        return e
    poly, eps = refit
    b = poly.bounds
    # a refit that keeps less than half of the opening evidence has not found the opening's sides but the patch
    # the new campaign happened not to read as wall (a door leaf seen as wall but a strip): the stored rectangle
    # stays. One that keeps most of it but narrows it below an opening's size has not shown that the opening is
    # smaller than one: the stored rectangle stays too (issue 18 round 7, dev seed 110: a curtain window 0.58 m
    # wide that three campaigns saw, refitted 0.42 m wide, was dropped as a sliver); a stored sliver goes
    if float(votes.window[support & g.raster(poly)].sum()) < params.refit_keep_share * opening:
        return e
    if min(b[2] - b[0], b[3] - b[1]) < min_size:
        sb = e.polygon.bounds
        return e if min(sb[2] - sb[0], sb[3] - sb[1]) >= min_size else None
    return dataclasses.replace(e, polygon=poly, uncertainty=eps)


def _unknown_bounds(shapes: list[Element], unknown: list[Element]) -> np.ndarray:
    """Bounds (s_lo, t_lo, s_hi, t_hi) of the stored unknown regions that hold most of one of ``shapes``: an
    irregular hole an earlier campaign saw where a later one finds (part of) a window; its sides are candidates
    for the window's (the votes decide)."""
    out = [u.polygon.bounds for u in unknown for e in shapes
           if e.polygon.area > 0 and u.polygon.intersection(e.polygon).area >= 0.5 * e.polygon.area]
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def _band_between(a, b):
    """The strip of façade between two disjoint rectangles side by side or one above the other (over the span they
    share); ``None`` when they overlap or lie diagonally apart."""
    a0, a1, a2, a3 = a.bounds
    b0, b1, b2, b3 = b.bounds
    s_lo, s_hi, t_lo, t_hi = max(a0, b0), min(a2, b2), max(a1, b1), min(a3, b3)
    if t_hi > t_lo and s_lo >= s_hi:  # side by side: the gap runs from the left one's right side to the other's left
        return box(s_hi, t_lo, s_lo, t_hi)
    if s_hi > s_lo and t_lo >= t_hi:
        return box(s_lo, t_hi, s_hi, t_lo)
    return None


def _separated_by_wall(a: Element, b: Element, votes: _Votes, new_view: float | None = None) -> bool:
    """Whether two openings are two objects by the fused votes: the strip between them holds more wall than
    opening evidence (diagonal neighbours are always two). Overlapping ones, or a strip of no cells or no wall
    weight (a pole hid it), are one object. ``new_view`` (a share): ``a`` and ``b`` are the new campaign's shapes
    over an opening one earlier campaign stored; they are two also when the new campaign saw this share of the
    strip, cast wall votes on it and not one window vote: a view of the pier against one view that missed it."""
    if a.polygon.intersects(b.polygon):
        return False
    band = _band_between(a.polygon, b.polygon)
    if band is None:
        return True
    cells = votes.grid.raster(band)
    if not cells.any():
        return False
    if outweighed_by_wall(votes.window, votes.objects, cells):
        return True
    return new_view is not None and votes.window_new is not None and not votes.window_new[cells].any() \
        and bool(votes.objects[cells].any()) and votes.seen_new[cells].astype(bool).mean() >= new_view


def _clip_to(e: Element, region) -> Element | None:
    """``e`` cut to the rectangle ``region`` (points scaled by the area kept); ``None`` when nothing is left."""
    piece = e.polygon.intersection(region)
    if piece.is_empty or piece.area <= 0:
        return None
    piece = box(*piece.bounds)
    return dataclasses.replace(e, polygon=piece, n_points=int(round(e.n_points * piece.area / e.polygon.area)))


def _split_bridged(olds: list[Element], news: list[Element], votes: _Votes,
                   seen_fraction: float = 0.5) -> list[tuple[list[Element], list[Element]]]:
    """A matched group cut into the objects it holds. A new shape over two stored openings with wall between them
    (:func:`_separated_by_wall`) saw them as one -- a pier it read as glass, a reveal that hid it -- and must not
    merge them into one rectangle (issue 18 round 11, dev seed 154: two windows 0.57 m apart, the pier wall by 54
    votes to 26, fused into one 2.7 m wide). The stored openings are grouped by that test; each group takes the part
    of the new shapes within half the gap to the nearest other group. Likewise a stored opening over two new shapes
    with wall between them: an earlier campaign saw two windows as one, the new one saw the pier (issue 18 round
    25, dev seed 368: two windows 0.27 m apart that campaign 1 saw at a grazing angle and stored as one 4.1 m wide;
    campaign 3 saw them apart, and the stored one swallowed both). There the fused votes on the pier were 26 window
    (campaign 1) against 13 wall (campaign 3, not one window vote), so a stored opening only one campaign saw is
    split also where the new campaign saw ``seen_fraction`` of the strip, voted wall on it and never window
    (``new_view`` of :func:`_separated_by_wall`). The stored opening's id goes with the part holding most of it
    (see :func:`_fuse_openings`)."""
    if len(olds) >= 2 and news:
        parts = _split_by_wall(olds, news, votes)
        if parts is not None:
            return parts
    if len(news) >= 2 and olds:
        parts = _split_by_wall(news, olds, votes, seen_fraction if all(_weight(o) == 1 for o in olds) else None)
        if parts is not None:
            swapped = [(pieces, members) for members, pieces in parts]
            return sorted(swapped, key=lambda p: -sum(e.polygon.area for e in p[0]))
    return [(olds, news)]


def _split_by_wall(anchors: list[Element], others: list[Element], votes: _Votes,
                   new_view: float | None = None) -> list[tuple[list[Element], list[Element]]] | None:
    """``anchors`` grouped into objects by :func:`_separated_by_wall`, each group with the part of the ``others``
    within half the gap to the nearest other group (:func:`_clip_to`); ``None`` when they are one object."""
    one = np.array([[i == j or not _separated_by_wall(a, b, votes, new_view) for j, b in enumerate(anchors)]
                    for i, a in enumerate(anchors)])
    _, label = connected_components(one, directed=False)
    groups: dict[int, list[Element]] = {}
    for k, e in enumerate(anchors):
        groups.setdefault(int(label[k]), []).append(e)
    if len(groups) == 1:
        return None
    hulls = {g: box(*shapely.union_all([e.polygon for e in members]).bounds) for g, members in groups.items()}
    out = []
    for g, members in groups.items():
        reach = min(hulls[g].distance(h) for k, h in hulls.items() if k != g) / 2.0
        region = hulls[g].buffer(reach, join_style="mitre")
        pieces = [p for p in (_clip_to(e, region) for e in others) if p is not None]
        out.append((members, pieces))
    return out


def _stored_index(old: list[Element], g: _Grid) -> np.ndarray:
    """Per cell of the façade's grid, 1 + the index (in ``old``) of the stored opening over it, 0 for none."""
    at = np.zeros(g.shape, dtype=np.int32)
    for k, e in enumerate(old):
        at[g.raster(e.polygon)] = k + 1
    return at


def _foreign_cells(stored_at: np.ndarray, old: list[Element], olds: list[Element], g: _Grid) -> np.ndarray | None:
    """The cells of the stored openings other than ``olds`` (:func:`_stored_index`), ``None`` for none. A new
    shape that spans one stored opening and its neighbour across the wall between them (a campaign that saw
    neither well) must not stretch the first over the second: the neighbour stays a separate opening, so its votes
    are not the first's, and two stored openings would overlap (issue 18 round 12, dev seed 162: a window
    stretched 2.3 m down over the window below it, 0.8 m of wall between them). Only for groups with a stored
    member: a new shape alone over a stored sliver it was not matched with is a new, fuller view (dev seed 152: a
    campaign saw whole windows whose top 0.45 m campaign 1 had stored as slivers; barring the slivers' cells
    dropped the windows)."""
    members = {id(o) for o in olds}
    mine = [k + 1 for k, e in enumerate(old) if id(e) in members]
    cells = (stored_at > 0) & ~np.isin(stored_at, mine)
    for e in olds:  # where stored openings overlap, a member's own cells are never another's
        cells &= ~g.raster(e.polygon)
    return cells if cells.any() else None


def _fuse_openings(old: list[Element], new: list[Element], votes: _Votes, ids: _Ids, params: RefineParams,
                   extent: tuple[float, float, float, float],
                   unknown: list[Element] | None = None, min_size: float = 0.0,
                   doors: OpeningParams | None = None,
                   min_fill: float = 0.0, new_unknown: list[Element] | None = None) -> tuple[list[Element], set[int]]:
    """Windows and doors after the fusion, and the ids of those that changed (merged, added or re-scored). A new
    shape without a stored match may take the sides of a stored ``unknown`` region it lies in
    (:func:`_unknown_bounds`); a fused shape with a side below ``min_size`` is dropped. ``doors``: the
    detection's door size limits (:func:`_kind_voters`; ``None``: every matched shape votes on the kind);
    ``min_fill``: the detection's ``Ta`` (:func:`_holds_an_opening`). A stored opening the new campaign saw without
    finding a shape there, but lying in one of its ``new_unknown`` regions (a hole whose border it could not
    close), is refitted with that region's sides among the candidates: the campaign may have seen more of it (issue
    18 round 11, dev seed 155: campaign 1 saw only the top 0.5 m of a window, the rest lay in a region it could not
    see; campaign 2 saw all of it but not the 1.5 m strip beside it, and stored it as an unknown region; the window
    stayed 0.5 m tall)."""
    out: list[Element] = []
    changed: set[int] = set()
    # a stored piece and a new piece of one window (its top seen above a car, the rest below by another campaign)
    # overlap little but line up: one object (issue 18 round 24, dev seed 365: two windows stored, one false)
    groups = [part for oi, ni in _clusters(old, new, lambda e: "opening", params, aligned=True)
              for part in _split_bridged([old[i] for i in oi], [new[j] for j in ni], votes, params.seen_fraction)]
    stored_at = _stored_index(old, votes.grid) if any(o and n for o, n in groups) else None
    kept_ids: set[int] = set()
    for olds, news in groups:
        if not news:
            for e in olds:
                extra = _unknown_bounds([e], new_unknown) if new_unknown else None
                rescored = _rescored_opening(e, votes, params, min_size, min_fill, extra)
                if rescored is not None:
                    out.append(rescored)
                    if rescored is not e:
                        changed.add(e.element_id)
            continue
        keep_id = _keeper(olds).element_id if olds else ids()
        if keep_id in kept_ids:  # the second part of a stored opening split by wall (_split_bridged) is a new one
            keep_id = ids()
        kept_ids.add(keep_id)
        extra = None if olds or not unknown else _unknown_bounds(news, unknown)
        merged = _merge_opening(olds + news, keep_id, votes, params, extent, n_old=len(olds), extra_bounds=extra,
                                min_size=min_size, doors=doors,
                                foreign=_foreign_cells(stored_at, old, olds, votes.grid) if olds else None)
        if merged is not None:
            out.append(merged)
            changed.add(keep_id)
            continue
        for e in olds:  # the new shape is voted down: the stored ones stay unless the fused votes now drop them
            rescored = _rescored_opening(e, votes, params, min_size, min_fill)
            if rescored is not None and all(o.element_id != rescored.element_id for o in out):
                out.append(rescored)
                if rescored is not e:
                    changed.add(e.element_id)
    return _one_per_object(out, params), changed


def _one_per_object(openings: list[Element], params: RefineParams) -> list[Element]:
    """The fused openings less those that overlap an older one (lower id) by ``iou_threshold`` or more: one
    object, stored once. New shapes that match no stored opening but lie in one stored unknown region each take
    its sides (:func:`_unknown_bounds`); several strips of one flush door a later campaign saw half crossed became
    three identical windows (issue 18 round 21, dev seed 327)."""
    polygons = [e.polygon for e in openings]
    pairs = _iou_pairs(polygons, polygons, np.ones((len(openings),) * 2, dtype=bool), params)
    same = {(i, j) for iou, i, j in pairs if i != j and iou >= params.iou_threshold}
    kept: list[int] = []
    for i in sorted(range(len(openings)), key=lambda k: openings[k].element_id):
        if not any((i, k) in same for k in kept):
            kept.append(i)
    return [openings[i] for i in sorted(kept)]


def _merge_structure(members: list[Element], keep_id: int, votes: _Votes, params: RefineParams,
                     min_area: float) -> Element | None:
    """One irregular object from matched shapes of one layer: the pixels that at least ``structure_vote`` of the
    campaigns that saw them saw as the object; ε the point-weighted mean of the members' eq. (1)-(2) ε."""
    g = votes.grid
    count = np.zeros(g.shape, dtype=np.float64)
    for m in members:
        count += _weight(m) * g.raster(m.polygon)
    keep = (count > 0) & (count >= params.structure_vote * np.maximum(votes.seen, 1))
    parts = [p for p in mask_to_polygons(keep, g.s0, g.t0, g.cell) if p.area >= min_area]
    if not parts:
        return None
    poly = max(parts, key=lambda p: p.area)
    n = np.array([max(m.n_points, 1) for m in members], dtype=np.float64)
    eps = float(np.average([m.uncertainty for m in members], weights=n))
    return Element(element_id=keep_id, kind=ElementKind.STRUCTURE, polygon=poly,
                   layer_id=max(members, key=_weight).layer_id, uncertainty=eps,
                   n_points=int(sum(m.n_points for m in members)),
                   campaigns=sorted({c for m in members for c in m.campaigns}))


def _fuse_structures(old: list[Element], new: list[Element], votes: _Votes, ids: _Ids, params: RefineParams,
                     min_area: float) -> tuple[list[Element], set[int]]:
    out: list[Element] = []
    changed: set[int] = set()

    def outvoted(e: Element) -> bool:
        """Found by fewer than ``structure_vote`` of the campaigns that saw its place (median over its cells)."""
        cells = votes.grid.raster(e.polygon)
        return bool(cells.any()) and _weight(e) < params.structure_vote * float(np.median(votes.seen[cells]))

    for oi, ni in _clusters(old, new, lambda e: e.layer_id, params):
        olds, news = [old[i] for i in oi], [new[j] for j in ni]
        if not news:  # not found again: kept unchanged unless the campaigns that saw its place outvote it
            out.extend(o for o in olds if not votes.seen_new[votes.grid.raster(o.polygon)].any()
                       or not outvoted(o))
            continue
        if not olds:  # new: kept as found unless earlier campaigns saw its place without it
            if not outvoted(news[0]):
                e = dataclasses.replace(news[0], element_id=ids())
                out.append(e)
                changed.add(e.element_id)
            continue
        keep_id = _keeper(olds).element_id
        merged = _merge_structure(olds + news, keep_id, votes, params, min_area)
        out.append(merged if merged is not None else _keeper(olds))
        changed.add(keep_id)
    return out, changed


def _resolve_layer_conflicts(elements: list[Element], changed: set[int], params: RefineParams,
                             min_area: float) -> list[Element]:
    """Pixels claimed by objects on two layers go to the one with the lower ε (only pairs where one of them
    changed in this update: the others were resolved before). Losers shrinking below ``min_area`` are dropped."""
    layered = [e for e in elements if e.layer_id is not None and not e.is_unknown]
    polys = {e.element_id: e.polygon for e in layered}
    for a in layered:
        for b in layered:
            if a.element_id >= b.element_id or a.layer_id == b.layer_id:
                continue
            if a.element_id not in changed and b.element_id not in changed:
                continue
            pa, pb = polys[a.element_id], polys[b.element_id]
            if pa.is_empty or pb.is_empty or pa.intersection(pb).area < params.min_conflict_area:
                continue
            loser, winner = (a, b) if (a.uncertainty, a.element_id) > (b.uncertainty, b.element_id) else (b, a)
            rest = polys[loser.element_id].difference(polys[winner.element_id])
            parts = [p for p in getattr(rest, "geoms", [rest]) if isinstance(p, Polygon) and not p.is_empty]
            polys[loser.element_id] = max(parts, key=lambda p: p.area) if parts else Polygon()
            changed.add(loser.element_id)
    out = []
    for e in elements:
        poly = polys.get(e.element_id)
        if poly is None or poly is e.polygon:
            out.append(e)
        elif not poly.is_empty and poly.area >= min_area:
            out.append(dataclasses.replace(e, polygon=poly))
    return out


def _fuse_unknown(old: list[Element], new: list[Element], openings: list[Element], changed: set[int], votes: _Votes,
                  ids: _Ids, campaign_id: int, min_cells: int) -> list[Element]:
    """Unknown regions after the fusion. Stored regions lose the pixels any campaign saw as wall or object
    (``object_votes`` > 0) and those of openings this update changed; a stored region keeps its id (its largest
    remaining piece) and stays exactly as stored when nothing of it was resolved. The new campaign's regions add
    only where the façade's grid grew (inside the old grid a pixel the old campaigns did not flag was known, or
    not part of the wall): a later campaign adds knowledge, so the unknown area of a façade can only shrink. They
    get fresh ids."""
    g = votes.grid
    covered = np.zeros(g.shape, dtype=bool)
    covered_now = np.zeros(g.shape, dtype=bool)
    for e in openings:
        cells = g.raster(e.polygon)
        covered |= cells
        if e.element_id in changed:
            covered_now |= cells
    resolved = (votes.objects > 0) | covered_now
    out: list[Element] = []
    for e in old:
        cells = g.raster(e.polygon)
        if not (cells & resolved).any():
            out.append(e)
            continue
        parts = [p for p in mask_to_polygons(cells & ~resolved, g.s0, g.t0, g.cell)
                 if p.area >= min_cells * g.cell ** 2 - 1e-9]
        parts.sort(key=lambda p: -p.area)
        for k, poly in enumerate(parts):
            out.append(Element(element_id=e.element_id if k == 0 else ids(), kind=ElementKind.UNKNOWN, polygon=poly,
                               layer_id=None, uncertainty=math.inf, n_points=0,
                               campaigns=sorted(set(e.campaigns) | {campaign_id})))
    fresh = np.zeros(g.shape, dtype=bool)
    for e in new:
        fresh |= g.raster(e.polygon)
    fresh &= ~votes.old_area & ~resolved & ~covered
    labels, n = ndimage.label(fresh)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    for lab in range(1, n + 1):
        if sizes[lab] < min_cells:
            continue
        for poly in mask_to_polygons(labels == lab, g.s0, g.t0, g.cell):
            out.append(Element(element_id=ids(), kind=ElementKind.UNKNOWN, polygon=poly, layer_id=None,
                               uncertainty=math.inf, n_points=0, campaigns=[campaign_id]))
    return out


def _fuse_elements(stored: Facade, obs: Facade, layer_map: dict[int, int], votes: _Votes, fparams: FacadeParams,
                   params: RefineParams, campaign_id: int) -> list[Element]:
    """All elements of a façade after fusing the campaign's observation ``obs`` (its layer ids mapped to the fused
    ones by ``layer_map``)."""
    ids = _Ids(stored.elements)
    new = [dataclasses.replace(e, layer_id=None if e.layer_id is None else layer_map[e.layer_id])
           for e in obs.elements]

    def of(elements, *kinds):
        return [e for e in elements if e.kind in kinds and not e.is_unknown]

    openings, changed = _fuse_openings(of(stored.elements, *OPENINGS), of(new, *OPENINGS), votes, ids, params,
                                       obs.extent, [e for e in stored.elements if e.is_unknown],
                                       fparams.openings.min_opening_size, fparams.openings, fparams.openings.Ta,
                                       [e for e in new if e.is_unknown])
    min_area = fparams.objects.min_object_area
    structures, changed_s = _fuse_structures(of(stored.elements, ElementKind.STRUCTURE),
                                             of(new, ElementKind.STRUCTURE), votes, ids, params, min_area)
    changed |= changed_s
    objects = _resolve_layer_conflicts(openings + structures, changed, params, min_area)
    min_cells = max(1, int(math.ceil(fparams.openings.min_unknown_area / (fparams.layers.cell ** 2) - 1e-9)))
    unknown = _fuse_unknown([e for e in stored.elements if e.is_unknown], [e for e in new if e.is_unknown],
                            [e for e in objects if e.kind in OPENINGS], changed, votes, ids, campaign_id, min_cells)
    if params.enclosed_wall_share < 1.0:
        objects, unknown = _promote_enclosed(objects, unknown, votes, ids, fparams, params, campaign_id)
    return sorted(objects + unknown, key=lambda e: e.element_id)


_FRINGE_CELLS = 3  # wall within this many cells outside a side encloses it (a reveal's shadow fringe between)


def _vote_extent(u: Element, votes: _Votes, max_area: float) -> tuple[tuple[int, int], tuple[int, int]]:
    """Grid rows and columns [lo, hi) spanned by an unknown region and the window votes connected to it: a region
    an earlier campaign stored over part of a hole (the strip its sampling missed) is often narrower than the
    window a later campaign saw whole there, so its own bounds alone cannot hold the window's sides. The search
    reaches as far as a window of ``max_area`` could (its side at most that many m² over the cell)."""
    g = votes.grid
    s_lo, t_lo, s_hi, t_hi = u.polygon.bounds
    c0, c1, r0, r1 = g.line(s_lo, 0), g.line(s_hi, 0), g.line(t_lo, 1), g.line(t_hi, 1)
    reach = math.ceil(math.sqrt(max_area) / g.cell)
    pr0, pr1 = max(r0 - reach, 0), min(r1 + reach, g.shape[0])
    pc0, pc1 = max(c0 - reach, 0), min(c1 + reach, g.shape[1])
    patch = (slice(pr0, pr1), slice(pc0, pc1))
    labels, _ = ndimage.label(net_votes(votes.window[patch], votes.objects[patch])[0] > 0)
    touching = np.unique(labels[g.raster(u.polygon)[patch] & (labels > 0)])
    rr, cc = np.nonzero(np.isin(labels, touching[touching > 0]))
    if len(rr) == 0:
        return (r0, r1), (c0, c1)
    return ((min(r0, pr0 + int(rr.min())), max(r1, pr0 + int(rr.max()) + 1)),
            (min(c0, pc0 + int(cc.min())), max(c1, pc0 + int(cc.max()) + 1)))


def _enclosed_window(u: Element, votes: _Votes, fparams: FacadeParams,
                     params: RefineParams) -> tuple[Polygon, float] | None:
    """The window an unknown region holds on the fused votes, or ``None``: the rectangle over every grid line
    within the bounds of the region and of the window votes connected to it (± ``line_offsets``; :func:`_vote_extent`)
    minimising the weighted eq. (3) (ties: the smallest), kept when ε <= ``max_window_uncertainty``, its sides >=
    ``min_opening_size``, its area <= ``max_opening_area``, and when on each of its four sides at least
    ``enclosed_wall_share`` of the cells just outside carry net wall weight (a window enclosed by wall; a door
    reaching the ground or a hole running off the façade is not). A side failing that first grows across cells no
    campaign voted on by at most ``enclosed_max_grow`` (a parapet hides the window's lower part) and is judged
    there."""
    g = votes.grid
    off = params.line_offsets
    s_lo, t_lo, s_hi, t_hi = u.polygon.bounds
    if (s_hi - s_lo) * (t_hi - t_lo) > 2 * fparams.openings.max_opening_area:
        return None  # too wide to be mostly one window; and every line pair there would be costly
    rows_, cols_ = _vote_extent(u, votes, fparams.openings.max_opening_area)
    if (rows_[1] - rows_[0]) * (cols_[1] - cols_[0]) * g.cell ** 2 > 2 * fparams.openings.max_opening_area:
        # the votes run into a neighbour or a larger hole: the region's own bounds
        rows_, cols_ = (g.line(t_lo, 1), g.line(t_hi, 1)), (g.line(s_lo, 0), g.line(s_hi, 0))
    c_lo, c_hi = max(cols_[0] - off - 1, 0), min(cols_[1] + off + 1, g.shape[1])
    r_lo, r_hi = max(rows_[0] - off - 1, 0), min(rows_[1] + off + 1, g.shape[0])
    patch = (slice(r_lo, r_hi), slice(c_lo, c_hi))
    o = votes.objects[patch]
    w = _own_votes(votes.window[patch], o, g.raster(u.polygon)[patch])
    # ties (cells without votes weigh nothing) go to the smallest rectangle: the sides the votes support; a side
    # hidden beyond the fringe grows below, up to the wall
    rect, eps = refit_rectangle(w, o, range(1, c_hi - c_lo), range(1, r_hi - r_lo), np.zeros(w.shape))
    if rect is None or eps > params.max_window_uncertainty:
        return None
    r0, r1, c0, c1 = rect
    wall = net_votes(votes.window, votes.objects)[1] > 0
    unvoted = (votes.window == 0) & (votes.objects == 0)
    rect = [r0 + r_lo, r1 + r_lo, c0 + c_lo, c1 + c_lo]  # R0, R1, C0, C1 on the façade's grid
    for side in range(4):
        if side_wall_share(wall, rect, side, _FRINGE_CELLS) < params.enclosed_wall_share:
            # a side hidden beyond the fringe (a balcony parapet in front of the window's lower part): it reaches
            # across the cells no campaign voted on, up to the wall that encloses it
            grown = _grown_side(unvoted, rect, side, round(params.enclosed_max_grow / g.cell))
            trial = list(rect)
            trial[side] = grown
            if side_wall_share(wall, trial, side, _FRINGE_CELLS) < params.enclosed_wall_share:
                return None
            rect = trial
    R0, R1, C0, C1 = rect
    size = (C1 - C0) * g.cell, (R1 - R0) * g.cell
    if min(size) < fparams.openings.min_opening_size or size[0] * size[1] > fparams.openings.max_opening_area:
        return None
    poly = box(g.coord(C0, 0), g.coord(R0, 1), g.coord(C1, 0), g.coord(R1, 1))
    return poly, float(eps)


def _grown_side(unvoted: np.ndarray, rect: list[int], side: int, max_cells: int) -> int:
    """The side's grid line moved outwards across lines of which at least 90 % of the cells (over the rectangle's
    span) carry no vote at all, by at most ``max_cells``."""
    R0, R1, C0, C1 = rect
    rows, cols = unvoted.shape
    line = rect[side]
    step = -1 if side in (0, 2) else 1
    for _ in range(max_cells):
        k = line - 1 if step < 0 else line  # the grid line just outside
        if k < 0 or k >= (rows if side < 2 else cols):
            break
        cells = unvoted[k, C0:C1] if side < 2 else unvoted[R0:R1, k]
        if cells.size == 0 or cells.mean() < 0.9:
            break
        line += step
    return line


def _enclosed_kind(rect, bottom: float, fparams: FacadeParams) -> ElementKind:
    """Door or window for an enclosed opening the fused votes found: a door when it has a door's size
    (:func:`_door_sized`) and starts within ``door_bottom_tol`` of the façade's bottom ``bottom`` (the extent's
    lowest line: the ground the wall stands on; the map keeps no ground profile). A threshold or the pavement's
    edge seen as wall below a door encloses it like a sill (issue 18 round 7, dev seed 108: a door 2.4 m tall
    starting 0.17 m above the façade's bottom was promoted a window)."""
    op = fparams.openings
    tall = _door_sized(rect, op)
    return ElementKind.DOOR if tall and rect.bounds[1] <= bottom + op.door_bottom_tol else ElementKind.WINDOW


def _promote_enclosed(objects: list[Element], unknown: list[Element], votes: _Votes, ids: _Ids,
                      fparams: FacadeParams, params: RefineParams,
                      campaign_id: int) -> tuple[list[Element], list[Element]]:
    """Unknown regions the new campaign saw (>= ``seen_fraction`` of their cells) that the fused votes show as a
    window enclosed by wall (:func:`_enclosed_window`) become windows: each campaign alone saw part of the border
    hidden or unobserved (a side wall at a slant), together they saw it whole. Not where the window would overlap
    an opening, or hold less than half of the region. One of a door's size that starts at the façade's bottom is a
    door (:func:`_enclosed_kind`)."""
    g = votes.grid
    openings = [e.polygon for e in objects if e.kind in OPENINGS]
    kept: list[Element] = []
    for u in unknown:
        cells = g.raster(u.polygon)
        found = None
        if cells.any() and votes.seen_new[cells].astype(bool).mean() >= params.seen_fraction:
            found = _enclosed_window(u, votes, fparams, params)
        if found is not None and (any(found[0].intersects(p) and found[0].intersection(p).area > 0 for p in openings)
                                  or found[0].intersection(u.polygon).area < 0.5 * u.polygon.area
                                  or outweighed_by_wall(votes.window, votes.objects, g.raster(found[0]))):
            found = None
        if found is None:
            kept.append(u)
            continue
        objects.append(Element(element_id=ids(), kind=_enclosed_kind(found[0], g.t0, fparams), polygon=found[0],
                               layer_id=None, uncertainty=found[1], n_points=0,
                               campaigns=sorted(set(u.campaigns) | {campaign_id})))
        openings.append(found[0])
    return objects, kept


# ----------------------------------------------------------------------------------------------------------------------
# One façade


def _main_inlier_normal(xyz: np.ndarray, depth: np.ndarray, layer: Layer, sigma_k: float,
                        outward: np.ndarray) -> tuple[np.ndarray | None, int]:
    """PCA normal (2D, oriented like ``outward``) of the points within sigma_k σ of the layer, and their count."""
    inl = np.abs(depth - layer.mu) <= sigma_k * max(layer.sigma, 1e-4)
    if inl.sum() < 3:
        return None, 0
    normal2, _ = fit_line_2d(xyz[inl, :2])
    if float(normal2 @ outward[:2]) < 0:
        normal2 = -normal2
    return normal2, int(inl.sum())


def _wall_component(layers: list[Layer], stored: Facade, fparams: FacadeParams, params: RefineParams) -> bool:
    """Whether the component of a campaign's layers matched to the stored main layer is narrow enough to be a
    surface (σ <= ``surface_max_sigma``)."""
    j = _main_match(stored.layer(stored.main_layer), layers, params)
    return j is not None and layers[j].sigma <= fparams.layers.surface_max_sigma


def refine_facade(stored: Facade, camp: CampaignData, member_ids: np.ndarray, polygon, fparams: FacadeParams,
                  params: RefineParams, campaign_id: int, seed: int = 0, tm: dict | None = None) -> Facade | None:
    """The stored façade refined by one campaign's points ``member_ids`` (indices into ``camp``), or ``None`` when
    the campaign does not see its main layer again (the caller keeps the stored façade). See the module doc."""
    tm = tm if tm is not None else {}
    clock = time.perf_counter()
    rng = np.random.default_rng(seed)
    if stored.evidence is not None and stored.evidence.cell != fparams.layers.cell:
        fparams = fparams.updated(cell=stored.evidence.cell)  # the grids must stay aligned
    cell = fparams.layers.cell
    frame0 = stored.frame
    xyz = camp.xyz[member_ids]
    sdt = frame0.to_facade(xyz)
    keep = (sdt[:, 2] >= -fparams.layers.layer_back) & (sdt[:, 2] <= fparams.layers.layer_front)
    if keep.sum() < fparams.planes.min_facade_points:
        return None
    new_layers = layer_fit(sdt[keep], cell, fparams, rng, seed)  # the campaign's own Gaussians, stored depth axis
    if not _wall_component(new_layers, stored, fparams, params):
        # one random start can merge the wall into a broad clutter component (a few thousand points of a side
        # wall): the same sample again, with more starts
        retry = fparams.updated(gmm_n_init=max(fparams.layers.gmm_n_init, params.wall_retry_inits))
        new_layers = layer_fit(sdt[keep], cell, retry, np.random.default_rng(seed), seed)
    new_layers = [dataclasses.replace(la, sigma=la.sigma * camp.noise_factor) for la in new_layers]
    matches, _ = match_layers(stored.layers, stored.main_layer, new_layers, params)
    if not matches:
        return None
    j_main = next(i for i, lid in matches.items() if lid == stored.main_layer)
    main_old = stored.layer(stored.main_layer)
    # the plane: PCA normal of the new main layer's 3σ inliers, fused with the stored one by point counts
    normal1, n_inl = _main_inlier_normal(xyz[keep], sdt[keep, 2], new_layers[j_main], fparams.layers.sigma_k, frame0.normal)
    normal2 = frame0.normal[:2] if normal1 is None else _fuse_normal(
        frame0.normal, main_old.n_points, normal1, n_inl, params.normal_max_angle_deg)
    mu_main, _ = fuse_gaussians(main_old.mu, main_old.sigma, new_layers[j_main].mu, new_layers[j_main].sigma)
    s0, s1, _, _ = stored.extent
    s_mid = 0.5 * (s0 + s1)
    centre = frame0.to_crs(np.array([[s_mid, 0.0, 0.0]]))[0]
    normal3 = np.array([normal2[0], normal2[1], 0.0])
    u1 = np.array([-normal2[1], normal2[0], 0.0])

    def frame_at(mu: float) -> FacadeFrame:  # the new plane at depth mu of the stored axis; s and t the same
        return FacadeFrame(origin=centre + mu * normal3 - s_mid * u1, u=u1)

    frame1 = frame_at(mu_main)
    # the campaign is observed against its own wall (s, t stay the fused frame's): GPS drift puts it cm off the
    # fused plane, and a wall 8-10 cm behind that plane was cut at the edge of the band the local wall depth is
    # measured in (hard dev seed 147)
    mu_own = new_layers[j_main].mu
    frame_obs = frame_at(mu_own)
    # the extent grows where the campaign's wall reaches beyond it
    std1 = frame_obs.to_facade(xyz)
    obs_layers = [dataclasses.replace(la, mu=la.mu - mu_own) for la in new_layers]
    labels = np.full(len(std1), -1, dtype=np.int64)
    labels[keep] = assign_layers(std1[keep, 2], obs_layers, fparams.layers.sigma_k)
    on_main = labels == j_main
    extent1 = _extended_extent(stored.extent, std1[on_main, :2], cell, params)
    tm["layers"] = tm.get("layers", 0.0) + time.perf_counter() - clock
    obs = observe_facade(camp, frame_obs, extent1, fparams, campaign_id, seed=seed, polygon=polygon,
                         member_ids=member_ids, layers=obs_layers, tm=tm)
    if obs is None:
        return None
    clock = time.perf_counter()
    counted = [dataclasses.replace(la, n_points=o.n_points) for la, o in zip(new_layers, obs.layers)]
    layers, layer_map = _fused_layers(stored.layers, counted, matches, stored.n_points, obs.n_points, campaign_id)
    for la in layers:
        la.mu = 0.0 if la.layer_id == stored.main_layer else la.mu - mu_main
    old_ev = pad_evidence(stored.evidence, obs.extent, cell)
    old_area = _old_area(stored.evidence, obs.extent, cell)
    seen_area = float(obs.evidence.seen.sum()) * cell * cell
    voting: Facade | None = obs
    if obs.n_points < min(params.min_element_density, stored_density(stored)) * seen_area:
        voting = _on_unseen_cells(obs, old_ev)
    if voting is not None:
        fused_ev = _add_evidence(old_ev, voting.evidence)
        votes = _Votes(_Grid(fused_ev.s0, fused_ev.t0, cell, fused_ev.shape), fused_ev.window_votes,
                       fused_ev.object_votes, fused_ev.seen, voting.evidence.seen, old_area,
                       window_new=voting.evidence.window_votes)
        elements = _fuse_elements(stored, voting, layer_map, votes, fparams, params, campaign_id)
    else:  # too sparse to tell openings from sampling gaps, and nothing new seen: the plane and layers only
        fused_ev, elements = old_ev, list(stored.elements)
    main = next(la for la in layers if la.layer_id == stored.main_layer)
    tm["fusion"] = tm.get("fusion", 0.0) + time.perf_counter() - clock
    return Facade(facade_id=stored.facade_id, frame=frame1, sigma=float(main.sigma), extent=obs.extent, layers=layers,
                  elements=elements, main_layer=stored.main_layer, n_points=stored.n_points + obs.n_points,
                  footprint_edge=stored.footprint_edge if stored.footprint_edge is not None else obs.footprint_edge,
                  campaigns=sorted(set(stored.campaigns) | {campaign_id}), evidence=fused_ev)


# ----------------------------------------------------------------------------------------------------------------------
# Buildings and the map


def _on_unseen_cells(obs: Facade, old_ev: FacadeEvidence) -> Facade | None:
    """A sparse observation cut to the cells no earlier campaign saw or voted on (``old_ev.seen`` == 0, or no window
    and no wall vote: a wall guessed between sparse scan lines counts as seen but casts no vote, on the
    observation's grid): its votes there, and its elements lying mostly there. ``None`` when it saw none of them.
    Issue 18 round 24, dev seed 352: two campaigns had "seen" two thirds of a door at a grazing angle without one
    vote on it; the third saw the door whole, and the door was dropped with the rest of its evidence."""
    fresh = (old_ev.seen == 0) | ((old_ev.window_votes == 0) & (old_ev.object_votes == 0))
    ev = obs.evidence
    if not (fresh & (ev.seen > 0)).any():
        return None
    g = _Grid(ev.s0, ev.t0, ev.cell, ev.shape)

    def mostly_fresh(e: Element) -> bool:
        cells = g.raster(e.polygon)
        return bool(cells.any()) and float(fresh[cells].mean()) > 0.5

    cut = FacadeEvidence(cell=ev.cell, s0=ev.s0, t0=ev.t0, window_votes=np.where(fresh, ev.window_votes, 0),
                         object_votes=np.where(fresh, ev.object_votes, 0), seen=np.where(fresh, ev.seen, 0))
    return dataclasses.replace(obs, evidence=cut, elements=[e for e in obs.elements if mostly_fresh(e)])


def stored_density(f: Facade) -> float:
    """Points per m² the stored façade holds over the cells its campaigns saw (inf without evidence): a campaign
    sampling it at least that densely knows it no worse than the campaigns it was built from."""
    ev = f.evidence
    if ev is None:
        return math.inf
    area = float(np.count_nonzero(ev.seen)) * ev.cell * ev.cell
    return f.n_points / area if area > 0 else math.inf


def _s_range(f: Facade, polygon, params: RefineParams) -> tuple[float, float]:
    """Where along the wall new points may still belong to façade ``f``: its extent +- ``extend_margin``, widened to
    its footprint edge but not beyond the edge's ends by more than ``corner_margin`` (past a corner lie the next
    wall and the neighbours), unless the façade already reaches farther."""
    lo, hi = f.extent[0] - params.extend_margin, f.extent[1] + params.extend_margin
    if f.footprint_edge is not None and polygon is not None:
        edges = footprint_edges(polygon)
        if 0 <= f.footprint_edge < len(edges):
            ends = f.frame.to_facade(np.column_stack([edges[f.footprint_edge], np.zeros(2)]))[:, 0]
            lo, hi = min(lo, float(ends.min())), max(hi, float(ends.max()))
            lo = max(lo, min(float(ends.min()) - params.corner_margin, f.extent[0]))
            hi = min(hi, max(float(ends.max()) + params.corner_margin, f.extent[1]))
    return lo, hi


def assign_to_facades(facades: list[Facade], xyz: np.ndarray, polygon, params: RefineParams) -> np.ndarray:
    """Index (into ``facades``) of the façade each point belongs to: within ``association_distance`` of its main
    plane and within its range along the wall (:func:`_s_range`), not on another wall of the footprint
    (``corner_margin``), the nearest plane winning; -1 for none."""
    best = np.full(len(xyz), -1, dtype=np.int64)
    best_d = np.full(len(xyz), np.inf)
    to_boundary = boundary_distance(xyz[:, :2], polygon) if polygon is not None and len(facades) else None
    for k, f in enumerate(facades):
        sdt = f.frame.to_facade(xyz)
        lo, hi = _s_range(f, polygon, params)
        dist = np.abs(sdt[:, 2])
        ok = (dist <= params.association_distance) & (sdt[:, 0] >= lo) & (sdt[:, 0] <= hi) & (dist < best_d)
        if to_boundary is not None:
            # a plane on no edge of the footprint (a room's side wall seen through an open window) has no recesses
            # or balconies of the wall on that edge to keep: a point nearer the footprint's boundary lies on a wall
            # there, maybe one no campaign has stored yet
            margin = params.corner_margin if f.footprint_edge is not None else 0.0
            ok &= to_boundary >= dist - margin
        best[ok] = k
        best_d[ok] = dist[ok]
    return best


def _extent_area(f: Facade) -> float:
    return (f.extent[1] - f.extent[0]) * (f.extent[3] - f.extent[2])


def _behind_new_wall(f: Facade, g: Facade, params: RefineParams) -> bool:
    """Whether stored façade ``f`` is a plane inside the building that new wall ``g`` hides: on the same footprint
    edge, parallel, more than ``yield_depth`` behind ``g``, over ``g`` along the wall and smaller, holding no
    window or door."""
    if f.footprint_edge is None or f.footprint_edge != g.footprint_edge:
        return False
    if any(e.kind in OPENINGS for e in f.elements) or _extent_area(g) < 2.0 * _extent_area(f):
        return False
    if abs(float(f.frame.normal @ g.frame.normal)) < math.cos(math.radians(params.normal_max_angle_deg)):
        return False
    s0, s1, t0, t1 = f.extent
    centre = f.frame.to_crs(np.array([0.5 * (s0 + s1), 0.5 * (t0 + t1), 0.0]))
    if g.frame.to_facade(centre)[2] > -params.yield_depth:
        return False
    ends = np.sort(g.frame.to_facade(f.frame.to_crs(np.array([[s0, t0, 0.0], [s1, t0, 0.0]])))[:, 0])
    over = min(ends[1], g.extent[1]) - max(ends[0], g.extent[0])
    return over >= 0.5 * (s1 - s0)


def _new_facades(stored: Building, camp: CampaignData, ids: np.ndarray, owner: np.ndarray, fparams: FacadeParams,
                 campaign_id: int, seed: int, rng: np.random.Generator, tm: dict) -> list[Facade]:
    """Façades of the points no stored façade took (``owner`` < 0), once per campaign."""
    rest = ids[owner < 0]
    if len(rest) < fparams.planes.min_facade_points or any(campaign_id in f.campaigns for f in stored.facades):
        return []
    clock = time.perf_counter()
    found = building_facades(camp, rest, stored.footprint, fparams, campaign_id, seed, rng, tm)
    tm["new_facades"] = tm.get("new_facades", 0.0) + time.perf_counter() - clock
    return found


def refine_building(stored: Building, camp: CampaignData, ids: np.ndarray, fparams: FacadeParams,
                     params: RefineParams, campaign_id: int, seed: int, rng: np.random.Generator,
                     tm: dict) -> Building:
    """A stored building after one campaign: its façades refined, new façades from the points none of them took.

    A stored façade that a new wall hides (:func:`_behind_new_wall`: a campaign that saw only the inside of a room
    through the windows stored its back wall on the street edge) is dropped and the campaign's points are assigned
    again: that plane took the returns through the wall's windows, and the wall found without them held no opening
    (issue 18 round 27, dev seed 400)."""
    polygon = stored.footprint
    next_id = max((f.facade_id for f in stored.facades), default=-1) + 1  # a dropped façade's id is not reused
    owner = assign_to_facades(stored.facades, camp.xyz[ids], polygon, params)
    found = _new_facades(stored, camp, ids, owner, fparams, campaign_id, seed, rng, tm)
    hidden = {f.facade_id for f in stored.facades if any(_behind_new_wall(f, g, params) for g in found)}
    if hidden:
        stored = dataclasses.replace(stored, facades=[f for f in stored.facades if f.facade_id not in hidden])
        owner = assign_to_facades(stored.facades, camp.xyz[ids], polygon, params)
        found = _new_facades(stored, camp, ids, owner, fparams, campaign_id, seed, rng, tm)
    facades: list[Facade] = []
    for k, f in enumerate(stored.facades):
        members = ids[owner == k]
        refined = None
        if campaign_id not in f.campaigns and len(members) >= fparams.planes.min_facade_points:
            refined = refine_facade(f, camp, members, polygon, fparams, params, campaign_id,
                                    derive_seed(seed, int(f.facade_id)), tm)
        facades.append(refined if refined is not None else f)
    for f in found:
        f.facade_id = next_id
        next_id += 1
        facades.append(f)
    return dataclasses.replace(stored, facades=facades)


def _campaign_applied(stored: BuildingMap, campaign_id: int) -> bool:
    return any(c.campaign_id == campaign_id for c in stored.campaigns)


# ----------------------------------------------------------------------------------------------------------------------
# Roofs from aerial data


def _roof_candidates(xyz: np.ndarray, x_order: np.ndarray, classification: np.ndarray | None, ground: np.ndarray,
                     polygon, params: RefineParams) -> np.ndarray:
    """Indices of aerial points that may lie on a building's roof: inside the footprint (+ ``roof_buffer``), not
    ground or vegetation (ASPRS 2-5), at least ``roof_min_height`` above the ground around the footprint (10th
    percentile of the ground points within ``roof_ground_ring``). ``x_order`` sorts the points by x."""
    area = polygon.buffer(params.roof_buffer)
    ring = params.roof_ground_ring
    x0, y0, x1, y1 = area.bounds
    lo, hi = np.searchsorted(xyz[x_order, 0], [x0 - ring, x1 + ring])
    near = x_order[lo:hi]
    near = near[(xyz[near, 1] >= y0 - ring) & (xyz[near, 1] <= y1 + ring)]
    inside = near[shapely.contains_xy(area, xyz[near, 0], xyz[near, 1])]
    if classification is not None:
        inside = inside[(classification[inside] < 2) | (classification[inside] > 5)]
    around = near[ground[near]]
    base = float(np.quantile(xyz[around, 2], 0.1)) if len(around) else (
        float(xyz[inside, 2].min()) if len(inside) else 0.0)
    return np.sort(inside[xyz[inside, 2] - base >= params.roof_min_height])


def roof_planes(xyz: np.ndarray, polygon, params: RefineParams, campaign_id: int, seed: int = 0) -> list[RoofPlane]:
    """Roof planes of one building from its aerial roof points (CRS): the aerial pipeline's plane detector
    (:func:`lidarmap.aerial.flatten.detect_planes`), planes steeper than ``roof_max_slope_deg`` (walls) or with fewer than
    ``roof_min_points`` inliers dropped; normals point up; outline = concave hull of the inliers (xy) within the
    footprint (+ ``roof_buffer``); σ = the inliers' RMS distance to the plane."""
    from lidarmap.aerial.flatten import FlattenParams, detect_planes
    from lidarmap.facade.layers import outline_polygon

    if len(xyz) < params.roof_min_points:
        return []
    area = polygon.buffer(params.roof_buffer)
    roofs: list[RoofPlane] = []
    for plane in detect_planes(xyz, FlattenParams(), seed):
        normal = np.asarray(plane.normal, dtype=np.float64)
        offset = float(plane.offset)
        if normal[2] < 0:
            normal, offset = -normal, -offset
        if len(plane.inliers) < params.roof_min_points or \
                math.degrees(math.acos(min(1.0, normal[2]))) > params.roof_max_slope_deg:
            continue
        outline = outline_polygon(xyz[plane.inliers, :2], params.roof_outline_cell, params.roof_concave_ratio)
        outline = outline.intersection(area) if outline is not None else None
        if outline is None or outline.is_empty:
            continue
        if outline.geom_type != "Polygon":
            outline = max(getattr(outline, "geoms", [outline]), key=lambda g: g.area)
            if outline.geom_type != "Polygon":
                continue
        roofs.append(RoofPlane(plane_id=len(roofs), normal=normal, offset=offset, outline=outline,
                               sigma=float(plane.rms), n_points=int(len(plane.inliers)), campaigns=[campaign_id]))
    return roofs


def _height_at(roof: RoofPlane, xy: np.ndarray) -> float:
    n = np.asarray(roof.normal, dtype=np.float64)
    return float(-(n[0] * xy[0] + n[1] * xy[1] + roof.offset) / n[2])


def _roof_matches(a: RoofPlane, b: RoofPlane, params: RefineParams) -> bool:
    """Same roof plane: normals within ``roof_match_angle_deg``, planes within ``roof_match_distance`` (vertically,
    at the middle of the new outline) and overlapping outlines."""
    cos = float(np.dot(a.normal, b.normal)) / (np.linalg.norm(a.normal) * np.linalg.norm(b.normal))
    if cos < math.cos(math.radians(params.roof_match_angle_deg)) or not a.outline.intersects(b.outline):
        return False
    c = np.asarray(b.outline.representative_point().coords[0])
    return abs(_height_at(a, c) - _height_at(b, c)) <= params.roof_match_distance


def _fused_roof(old: RoofPlane, new: RoofPlane, campaign_id: int) -> RoofPlane:
    """Two observations of one roof plane: normal weighted by point counts, height at the outline's middle fused by
    eq. (4)-(7) (σ = the planes' RMS), outlines united, counts added."""
    c = np.asarray(old.outline.union(new.outline).representative_point().coords[0])
    z, sigma = fuse_gaussians(_height_at(old, c), old.sigma, _height_at(new, c), new.sigma)
    n = old.n_points * np.asarray(old.normal, dtype=np.float64) + new.n_points * np.asarray(new.normal)
    n /= np.linalg.norm(n)
    outline = old.outline.union(new.outline)
    if outline.geom_type != "Polygon":
        outline = max(getattr(outline, "geoms", [outline]), key=lambda g: g.area)
    return RoofPlane(plane_id=old.plane_id, normal=n, offset=float(-(n[0] * c[0] + n[1] * c[1] + n[2] * z)),
                     outline=outline, sigma=sigma, n_points=old.n_points + new.n_points,
                     campaigns=sorted(set(old.campaigns) | {campaign_id}))


def fuse_roofs(stored: list[RoofPlane], new: list[RoofPlane], params: RefineParams,
               campaign_id: int) -> list[RoofPlane]:
    """A building's roof planes after an aerial campaign: each new plane fuses with the first matching stored one
    (:func:`_roof_matches`, most points first) or is added with a fresh ``plane_id``."""
    out = list(stored)
    next_id = max((r.plane_id for r in stored), default=-1) + 1
    used: set[int] = set()
    for r in sorted(new, key=lambda r: -r.n_points):
        k = next((i for i, old in enumerate(out) if i not in used and old.plane_id in {o.plane_id for o in stored}
                  and _roof_matches(old, r, params)), None)
        if k is None:
            out.append(dataclasses.replace(r, plane_id=next_id))
            used.add(len(out) - 1)
            next_id += 1
        else:
            out[k] = _fused_roof(out[k], r, campaign_id)
            used.add(k)
    return sorted(out, key=lambda r: r.plane_id)


def add_aerial(stored: BuildingMap, cloud: PointCloud, footprints: Footprints, params: RefineParams,
               campaign_id: int, seed: int = 0) -> BuildingMap:
    """The map with roof planes from an aerial scan added to its buildings (a new copy; ``stored`` untouched).

    Per footprint: the aerial points inside it and above the ground (:func:`_roof_candidates`), roof planes by the
    aerial pipeline's detector (:func:`roof_planes`), fused with the building's stored roofs (:func:`fuse_roofs`).
    Buildings the map does not hold yet are added with roofs only. Re-applying a campaign id the map (or a
    building's roofs) already lists changes nothing.
    """
    from lidarmap.facade.planes import ground_mask

    new_map = copy.deepcopy(stored)
    if _campaign_applied(stored, campaign_id):
        return new_map
    check_same_crs(cloud, footprints)
    xyz = cloud.xyz
    classification = cloud.attrs.get("classification")
    ground = ground_mask(xyz, classification, FacadeParams())
    x_order = np.argsort(xyz[:, 0], kind="stable")
    for b, (fid, polygon) in enumerate(zip(footprints.ids, footprints.polygons)):
        bid = str(fid)
        building = new_map.buildings.get(bid)
        if building is not None and any(campaign_id in r.campaigns for r in building.roofs):
            continue
        ids = _roof_candidates(xyz, x_order, classification, ground, polygon, params)
        roofs = roof_planes(xyz[ids], polygon, params, campaign_id, derive_seed(seed, b))
        if not roofs:
            continue
        if building is None:
            new_map.buildings[bid] = Building(building_id=bid, footprint=polygon,
                                              attributes=dict(footprints.properties[b]), roofs=roofs)
        else:
            building.roofs = fuse_roofs(building.roofs, roofs, params, campaign_id)
    return new_map
