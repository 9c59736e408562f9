"""Façades, depth layers, elements and occlusions of buildings from ONE mobile-mapping campaign.

Zou & Sester, *Incremental map refinement of building information using LiDAR point clouds*, §2.2-2.4:

1. ground removed (class 2, or a height rule), building points (class 6, or every non-ground point) joined to the
   nearest footprint, points farther than ``max_footprint_distance`` ignored (§2.2);
2. per building, vertical planes (efficient RANSAC or region growing, :mod:`lidarmap.facade_planes`) grouped into
   façades, matched to footprint edges and oriented outwards;
3. per façade, a GMM over depth (BIC picks the number of layers), main layer = heaviest component, its 3σ inliers give
   a PCA normal, points re-projected and the GMM fitted again; d = 0 sits on the main layer (§2.3);
4. objects per layer by region growing on the 2.5D grid, outlines by concave hull, uncertainty eq. (1)-(2);
5. occlusion by ray tracing from the trajectory, windows/doors from holes by Hough rectangles and eq. (3), unknown
   regions (occlusions, irregular holes) with uncertainty = inf (§2.4).

:func:`extract_buildings` is the entry point; the pieces are importable for tests and the refinement stage.
See docs/facade.md for the parameters and their defaults.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
from scipy import ndimage
from shapely.geometry import box

from lidarmap.errors import CRSError, InputError
from lidarmap.facade_layers import (DepthGrid, assign_layers, close_sampling_gaps, depth_grid, fit_layers,
                                    grid_shape, grow_regions, mask_to_polygons, outline_polygon, square,
                                    uncertainty_eq1)
from lidarmap.facade_occlusion import occlusion_mask, project_rays, reach_mask, sample_spacing, through_cells
from lidarmap.facade_planes import (PlaneGroup, boundary_distance, check_points, estimate_normals, fit_facade_frame,
                                    fit_line_2d, footprint_edges, group_planes, join_footprints, match_footprint_edge,
                                    ransac_vertical_planes, region_growing_vertical_planes, voxel_subsample)
from lidarmap.facade_windows import (HOLE, OBJECT, OCCLUDED, Opening, complete_by_repetition, detect_openings,
                                     fit_rectangle, refine_bounds, window_uncertainty_eq3)
from lidarmap.io.footprints import Footprints
from lidarmap.io.pointcloud import PointCloud
from lidarmap.io.trajectory import Trajectory
from lidarmap.model import Building, Element, ElementKind, Facade, FacadeEvidence, FacadeFrame, Layer

__all__ = [
    "FacadeParams", "CampaignData", "prepare_campaign", "extract_buildings", "building_facades", "extract_facade",
    "observe_facade", "detect_facade_groups", "fit_facade_frame", "depth_grid", "DepthGrid", "fit_layers",
    "assign_layers", "occlusion_mask", "through_cells", "reach_mask", "project_rays", "detect_openings",
    "fit_rectangle", "refine_bounds", "complete_by_repetition", "uncertainty_eq1", "window_uncertainty_eq3",
    "value_grid", "footprint_edges", "Opening", "HOLE", "OCCLUDED", "OBJECT", "check_same_crs", "join_campaign",
    "campaign_data", "campaign_track", "no_join_error",
]


@dataclasses.dataclass(frozen=True)
class FacadeParams:
    """Parameters of façade extraction (TOML table ``[facade]``). Lengths in metres, angles in degrees.

    Points and buildings (§2.2)
        ground_class (2): ASPRS class of ground points, used when the classification contains it.
        building_class (6): class of building points; when absent every non-ground point is a building candidate.
        ground_cell (2.0): xy cell of the height rule used without a ground class (lowest point per cell, then the
            minimum over the 3x3 cells around).
        ground_height (0.25): points less than this above the local lowest point are ground (height rule).
        max_footprint_distance (2.0): points farther than this from every footprint are ignored (paper: 2 m); also
            the band around a footprint's boundary where façades are searched and the edge-matching distance.
        join_quantum (0.02): xy snapping before the footprint join (≤ 1.4 cm error, one query per distinct spot).

    Vertical planes
        plane_method ("ransac"): "ransac" (efficient RANSAC, Schnabel 2007) or "region" (k-NN region growing).
        detect_voxel (0.1): detection runs on one point per voxel of this size (uniform density).
        detect_max_points (150000): at most this many voxel points per building for detection.
        normal_k (12): neighbours for the PCA normals.
        vertical_tolerance_deg (15.0): normals within this of horizontal belong to vertical surfaces.
        ransac_threshold (0.05): inlier distance to a plane (MLS noise is mm-cm; wall roughness a few cm).
        ransac_normal_deg (15.0): inlier normal deviation.
        ransac_hypotheses (256): candidates per extraction round.
        ransac_eval_points (4000): random subset on which candidates are scored.
        region_angle_deg (10.0): region growing: max normal angle between neighbours.
        min_facade_points (150): a façade plane needs this many voxel points (0.1 m voxels: ~1.5 m² of wall).
        min_facade_length (1.0): and this length along the wall.
        facade_max_gap (2.0): collinear inliers further apart than this along the wall are separate planes.
        merge_angle_deg (20.0): near-parallel planes (angle below this) ...
        merge_depth (1.5): ... whose ends both lie within this depth of a bigger plane, overlapping it along the
            wall, are one façade (its layers, or a short spurious fit through pilasters, reveals and door leaves;
            a genuinely different wall 20° off is longer than merge_depth / tan 20° = 4 m and stays apart).
        edge_angle_deg (10.0): a footprint edge matches a façade within this angle (and max_footprint_distance).
        facade_margin (0.3): points up to this beyond a façade's ends still belong to it.

    Depth layers (§2.3)
        cell (0.1): size of the 2.5D grid cells (windows ≥ 0.5 m span ≥ 5 cells; MLS spacing is 1-10 cm).
        layer_front (1.5): points up to this in front of the main plane form layers (balconies, bay windows).
        layer_back (0.6): and up to this behind it (door leaves, recessed panels); deeper points were seen through
            openings.
        gmm_max_components (4): the GMM tries 1..K components and keeps the lowest BIC.
        gmm_max_samples (8000): points per GMM fit (density-equalised sample).
        gmm_points_per_cell (3): the sample keeps at most this many points per grid cell.
        gmm_n_init (1): GMM restarts per K.
        gmm_reg_var (1e-6): variance floor added by the GMM (m²), i.e. σ ≥ 1 mm.
        gmm_min_weight (0.002): lighter components are dropped.
        min_layer_separation (0.04): components with closer means are merged.
        sigma_k (3.0): points within sigma_k σ of the main layer give the PCA normal (paper: 3σ, 99.7 %); points
            beyond sigma_k σ of every layer belong to none.
        refine_iterations (1): rounds of GMM -> 3σ inliers -> PCA normal -> re-projection (then the final GMM).
        structure_min_offset (0.05): layers further than this from the main one carry objects (proud: STRUCTURE;
            recessed: DOOR, WINDOW or STRUCTURE).
        surface_max_sigma (0.05): a recessed object whose depths spread more than this (robust σ) is clutter
            (reveals, mixed cells, interiors seen through glass), not a surface: it is dropped (neither a door leaf,
            a recessed window nor a structure).
        layer_cell_share (0.2): a cell shows the front-most layer holding at least this share (and 2) of its
            points (the main layer: 2 points): the wall hides interior surfaces seen through a window behind it, a
            balcony hides the wall.

    Objects
        close_cells (1): gaps of up to 2*close_cells cells are closed before region growing, and at least this
            radius closes sampling gaps when deciding which cells were observed ...
        max_close_cells (3): ... raised up to this where the local point spacing is coarser (radius = spacing /
            cell); windows wider than 2*max_close_cells+1 cells are never closed.
        min_object_area (0.1): smaller objects are dropped.
        min_object_width (0.2): parts of an object thinner than this are cut (opening), e.g. window reveals.
        concave_ratio (0.3): shapely concave_hull ratio for object outlines (0 most concave, 1 convex hull).
        max_outline_points (4000): points used per outline.

    Occlusion (§2.4)
        occluder_min_depth (0.2): points at least this far in front of the main plane are occluders (any class).
        occluder_radius (0.03): radius of a foreground sample (the beam footprint; raised to half the foreground's
            point spacing, the Voronoi radius of a sample); its shadow on the wall has radius λ x that.
        occluder_max_radius_cells (6): cap of a shadow's radius in cells.
        occlusion_close_cells (1): closing of the occlusion mask (joins neighbouring shadows).
        through_max_depth (25.0): points up to this far behind the plane are looked at as seen-through points.
        reach_quantile (0.995): the scanner's max range and elevation limits are this quantile over the campaign.
        reach_margin (1.05): factor on the max range.
        reach_angle_margin_deg (2.0): margin on the elevation limits.
        max_incidence_deg (85.0): rays more grazing than this to the wall return nothing.
        reach_step (0.5): trajectory sampling step for the reach test.
        index_bin (5.0): xy bin of the spatial index used to fetch points around a façade.

    Windows and doors (§2.4)
        Ta (0.7): fill ratio (hole cells / bounding-box cells) above which a hole is a window candidate. A
            rectangle has ~1 (0.8-0.95 with jagged sampled edges), an arched window ~0.9, a circle 0.785; L-shaped or
            diagonal leftovers of shadows score ≤ 0.6-0.75.
        min_hole_area (0.12): smaller holes are sampling gaps.
        max_opening_area (16.0): larger holes are UNKNOWN.
        min_opening_size (0.45): windows/doors narrower or lower than this are UNKNOWN (the visible corner of a
            mostly hidden opening is not a window).
        max_window_uncertainty (0.5): rectangles with a larger eq. (3) ε_w are UNKNOWN.
        occlusion_touch_max (0.6): holes with more of their border occluded are UNKNOWN (mostly hidden: the
            opening may continue behind the occluder); they still vote as window evidence. Below it the visible part
            is fitted (a sill hidden by the balcony below it costs a few cells, not the window).
        canny_sigma (1.0): Canny smoothing (cells).
        hough_lines (6): Hough peaks per orientation.
        hough_max_tilt_deg (2.0), hough_angle_steps (2): near-vertical/horizontal angles tried.
        hough_offsets (1): each line is tried this many cells either side.
        edge_bias_cells (0.5): without wall points next to a side, window/door rectangles grow by this many cells
            on each side: a cell straddling a window edge usually holds wall points, so the hole is on average half
            a cell short on each side.
        refine_max_cells (2.5): with wall points, each side is placed half a sampling spacing beyond the last wall
            sample (sub-cell, and right for sparse far façades whose scan lines are further apart than a cell);
            it moves at most this many cells from its cell edge ...
        refine_min_points (8): ... and needs this many wall points along it.
        door_bottom_tol (1.5): openings (holes or recessed leaves) starting within this of the ground in front
            of them may be doors: the ground floor sits up to ~1 m above the pavement on sloping streets ...
        door_min_height (1.9): ... and doors are at least this tall (windows, even on the ground floor, are
            shorter; their sills are ~1 m above the floor).
        ground_band (4.0): ground points up to this far in front of the wall give the ground line ...
        ground_bin (1.0): ... one low (20th percentile) height per this length along the wall.
        door_max_width (3.5): recessed door leaves are at most this wide.
        recessed_windows (False): a rectangular region of a recessed layer (fill >= Ta, opening-sized) that is not a
            door is a WINDOW (glass with blinds or curtains returns the laser a few cm to dm behind the wall);
            False keeps it a STRUCTURE.
        complete_by_repetition (True): a window cut by an occlusion (e.g. the sill hidden by the balcony below it)
            takes the height/width of the unoccluded windows in its column/row, across occluded cells only
            (paper §2.1: façade elements repeat); eq. (3) then counts the occluded cells it covers ...
        repetition_tol (0.2): ... the windows of a column (row) have both sides within this of each other.
        hole_open_cells (1): holes are opened by a square of this radius (removes 1-2 cell fringes of unobserved
            wall along shadow edges).
        bridge_cells (2): hole parts separated by up to 2*bridge_cells occluded cells (a pole or trunk in front
            of a window) are one opening candidate.
        occlusion_grow_cells (1): the occlusion mask grows by this many cells into unobserved cells (the last
            unobserved cells at a shadow's edge are ambiguous, not holes).
        min_unknown_area (0.1): smaller occluded regions are not reported as UNKNOWN elements.
    """

    section = "facade"

    ground_class: int = 2
    building_class: int = 6
    ground_cell: float = 2.0
    ground_height: float = 0.25
    max_footprint_distance: float = 2.0
    join_quantum: float = 0.02

    plane_method: str = "ransac"
    detect_voxel: float = 0.1
    detect_max_points: int = 150_000
    normal_k: int = 12
    vertical_tolerance_deg: float = 15.0
    ransac_threshold: float = 0.05
    ransac_normal_deg: float = 15.0
    ransac_hypotheses: int = 256
    ransac_eval_points: int = 4000
    region_angle_deg: float = 10.0
    min_facade_points: int = 150
    min_facade_length: float = 1.0
    facade_max_gap: float = 2.0
    merge_angle_deg: float = 20.0
    merge_depth: float = 1.5
    edge_angle_deg: float = 10.0
    facade_margin: float = 0.3

    cell: float = 0.1
    layer_front: float = 1.5
    layer_back: float = 0.6
    gmm_max_components: int = 4
    gmm_max_samples: int = 8000
    gmm_points_per_cell: int = 3
    gmm_n_init: int = 1
    gmm_reg_var: float = 1e-6
    gmm_min_weight: float = 0.002
    min_layer_separation: float = 0.04
    sigma_k: float = 3.0
    refine_iterations: int = 1
    structure_min_offset: float = 0.05
    layer_cell_share: float = 0.2
    surface_max_sigma: float = 0.05

    close_cells: int = 1
    max_close_cells: int = 3
    min_object_area: float = 0.1
    min_object_width: float = 0.2
    concave_ratio: float = 0.3
    max_outline_points: int = 4000

    occluder_min_depth: float = 0.2
    occluder_radius: float = 0.03
    occluder_max_radius_cells: int = 6
    occlusion_close_cells: int = 1
    through_max_depth: float = 25.0
    reach_quantile: float = 0.995
    reach_margin: float = 1.05
    reach_angle_margin_deg: float = 2.0
    max_incidence_deg: float = 85.0
    reach_step: float = 0.5
    index_bin: float = 5.0

    Ta: float = 0.7
    min_hole_area: float = 0.12
    max_opening_area: float = 16.0
    min_opening_size: float = 0.45
    max_window_uncertainty: float = 0.5
    occlusion_touch_max: float = 0.6
    canny_sigma: float = 1.0
    hough_lines: int = 6
    hough_max_tilt_deg: float = 2.0
    hough_angle_steps: int = 2
    hough_offsets: int = 1
    edge_bias_cells: float = 0.5
    refine_max_cells: float = 2.5
    refine_min_points: int = 8
    door_bottom_tol: float = 1.5
    ground_band: float = 4.0
    ground_bin: float = 1.0
    door_min_height: float = 1.9
    hole_open_cells: int = 1
    bridge_cells: int = 2
    occlusion_grow_cells: int = 1
    door_max_width: float = 3.5
    recessed_windows: bool = False
    complete_by_repetition: bool = True
    repetition_tol: float = 0.2
    min_unknown_area: float = 0.1

    def __post_init__(self) -> None:
        if self.plane_method not in ("ransac", "region"):
            raise ValueError(f"plane_method must be 'ransac' or 'region', not {self.plane_method!r}")
        positive = ("cell", "max_footprint_distance", "join_quantum", "detect_voxel", "ransac_threshold",
                    "ground_cell", "index_bin", "reach_step")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        if not 0.0 < self.Ta <= 1.0:
            raise ValueError("Ta must be in (0, 1]")
        if self.gmm_max_components < 1:
            raise ValueError("gmm_max_components must be >= 1")


# ----------------------------------------------------------------------------------------------------------------------
# Helpers


class _XYIndex:
    """Points binned on an xy grid (sorted by bin) for fast box queries.

    With a fixed ``origin`` (the campaign's) the bins, and so which points a box query returns and in what order,
    are the same for any part of the campaign that holds the queried bins: a building's context answers like the
    whole campaign.
    """

    def __init__(self, xy: np.ndarray, bin_size: float, origin: np.ndarray | None = None):
        self.bin = float(bin_size)
        if origin is not None:
            self.lo = np.asarray(origin, dtype=np.float64)[:2]
        else:
            self.lo = xy.min(axis=0) if len(xy) else np.zeros(2)
        ij = np.floor((xy - self.lo) / self.bin).astype(np.int64)
        self.shape = (ij.max(axis=0) + 1) if len(xy) else np.array([1, 1])
        keys = ij[:, 0] * self.shape[1] + ij[:, 1]
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]

    def query_box(self, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
        i0, j0 = np.floor((np.array([x0, y0]) - self.lo) / self.bin).astype(np.int64)
        i1, j1 = np.floor((np.array([x1, y1]) - self.lo) / self.bin).astype(np.int64)
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, self.shape[0] - 1), min(j1, self.shape[1] - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, dtype=np.int64)
        rows = np.arange(i0, i1 + 1)
        lo = np.searchsorted(self.keys, rows * self.shape[1] + j0, side="left")
        hi = np.searchsorted(self.keys, rows * self.shape[1] + j1, side="right")
        parts = [self.order[a:b] for a, b in zip(lo, hi) if b > a]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _equalised_sample(flat: np.ndarray, per_cell: int, max_samples: int, rng: np.random.Generator) -> np.ndarray:
    """Indices keeping at most ``per_cell`` random points per cell id, then at most ``max_samples`` of them."""
    if len(flat) == 0:
        return np.zeros(0, dtype=np.int64)
    perm = rng.permutation(len(flat))
    keys = flat[perm]
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    rank = np.arange(len(sk)) - np.searchsorted(sk, sk, side="left")
    chosen = perm[order[rank < per_cell]]
    if len(chosen) > max_samples:
        chosen = rng.choice(chosen, size=max_samples, replace=False)
    return chosen


def layer_fit(std: np.ndarray, cell: float, params: FacadeParams, rng: np.random.Generator,
               seed: int) -> list[Layer]:
    """GMM layers over a density-equalised sample of façade points (at most gmm_points_per_cell per grid cell)."""
    keys = np.floor(std[:, 0] / cell).astype(np.int64) * 1_000_003 + np.floor(std[:, 1] / cell).astype(np.int64)
    sample = _equalised_sample(keys, params.gmm_points_per_cell, params.gmm_max_samples, rng)
    return fit_layers(std[sample, 2], params, seed=seed)


def _main_layer(layers: list[Layer]) -> Layer:
    return max(layers, key=lambda la: la.weight)


def value_grid(observed: np.ndarray, occluded: np.ndarray, through: np.ndarray) -> np.ndarray:
    """The paper's Figure 6 grid: -1 observed wall/object, 0 occluded/unreachable, 1 hole (seen through or empty)."""
    values = np.full(observed.shape, HOLE, dtype=np.int8)
    values[occluded & ~through] = OCCLUDED
    values[observed] = OBJECT
    return values


@dataclasses.dataclass
class CampaignData:
    """One campaign prepared for façade work (:func:`prepare_campaign`): shared by all its façades.

    ``sensors`` holds the sensor position of every non-ground point's pulse (NaN for ground points); the indices
    fetch points around a façade fast; ``limits`` are the scanner's max range and elevation limits measured on the
    campaign; ``track`` samples the trajectory over the campaign's time span every ``reach_step`` metres.
    """

    xyz: np.ndarray
    sensors: np.ndarray
    ground: np.ndarray
    building: np.ndarray
    nonground_index: _XYIndex
    nonground_ids: np.ndarray
    limits: tuple[float, float, float]
    track: np.ndarray
    ground_index: _XYIndex | None = None
    ground_ids: np.ndarray | None = None
    source: str | None = None


def campaign_track(trajectory: Trajectory, t_min: float, t_max: float, step: float) -> np.ndarray:
    """The trajectory over the campaign's time span, sampled every ``step`` metres (the reach test's positions)."""
    inside = (trajectory.time > t_min) & (trajectory.time < t_max)
    times = np.concatenate([[t_min], trajectory.time[inside], [t_max]])
    pos = trajectory.position_at(np.clip(times, trajectory.time[0], trajectory.time[-1]))
    seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return pos[:1]
    samples = np.interp(np.arange(0.0, cum[-1] + step, step), cum, times)
    return trajectory.position_at(np.clip(samples, trajectory.time[0], trajectory.time[-1]))


def campaign_data(xyz: np.ndarray, gps: np.ndarray, ground: np.ndarray, building: np.ndarray,
                  trajectory: Trajectory, limits: tuple[float, float, float], track: np.ndarray, origin: np.ndarray,
                  params: FacadeParams, source: str | None = None) -> CampaignData:
    """:class:`CampaignData` over some of a campaign's points (all of them, or one building's context) with the
    campaign-wide ``limits``, ``track`` and index ``origin`` (:mod:`lidarmap.campaign_scan`)."""
    nonground = np.flatnonzero(~ground)
    sensors = np.full((len(xyz), 3), np.nan)
    sensors[nonground] = trajectory.position_at(gps[nonground])  # InputError when the trajectory misses them
    camp = CampaignData(xyz=xyz, sensors=sensors, ground=ground, building=building,
                        nonground_index=_XYIndex(xyz[nonground, :2], params.index_bin, origin),
                        nonground_ids=nonground, limits=limits, track=track, source=source)
    ground_ids = np.flatnonzero(ground)
    if len(ground_ids):
        camp.ground_index, camp.ground_ids = _XYIndex(xyz[ground_ids, :2], params.index_bin, origin), ground_ids
    return camp


def prepare_campaign(points: PointCloud, trajectory: Trajectory, params: FacadeParams, seed: int = 0,
                     timings: dict | None = None) -> CampaignData:
    """Ground/building masks, the sensor position of every non-ground point, spatial indices, scanner limits, for
    a whole campaign held in memory (the same rules as the streamed update, :mod:`lidarmap.campaign_scan`; ``seed``
    is unused: the reach limits come from a stride sample).

    Raises :class:`~lidarmap.errors.InputError` for an empty cloud, missing ``gps_time`` or GPS times the
    trajectory does not cover (``Trajectory.position_at``).
    """
    from lidarmap.campaign_scan import CampaignScan, StatsPass

    clock = time.perf_counter()
    tm = timings if timings is not None else {}
    check_points(points.xyz, points.source)
    origin = points.xyz[:, :2].min(axis=0)
    scan = CampaignScan(origin, params, points.source)
    index = scan.add(points)
    classes = scan.classes()
    stats_pass = StatsPass(classes, scan, trajectory)
    classification = points.attrs.get("classification")
    gps = np.asarray(points.attrs["gps_time"], dtype=np.float64)
    stats_pass.add(points.xyz, gps, classification, index)
    stats = stats_pass.finish(params.reach_quantile)
    ground, building = classes.masks(points.xyz, classification)
    camp = campaign_data(points.xyz, gps, ground, building, trajectory, stats.limits,
                         campaign_track(trajectory, *stats.t_span, params.reach_step), origin, params, points.source)
    tm["prepare"] = tm.get("prepare", 0.0) + time.perf_counter() - clock
    return camp


# ----------------------------------------------------------------------------------------------------------------------
# Entry points


def extract_buildings(points: PointCloud, trajectory: Trajectory, footprints: Footprints, params: FacadeParams,
                      campaign_id: int, seed: int = 0, timings: dict | None = None) -> list[Building]:
    """Buildings with façades, layers, elements and evidence from one mobile-mapping campaign.

    ``points`` need ``gps_time`` (for the sensor positions of the occlusion ray tracing) and are in the same CRS as
    ``footprints``. Returns the buildings (footprint order) that received at least one façade; ``timings`` (a dict)
    receives seconds per step. Runs building by building exactly like ``lidarmap map update``
    (:func:`lidarmap.map_update.fuse_campaign`): each building draws its random numbers from (seed, its id).
    """
    from lidarmap.map_update import cloud_source, fuse_campaign
    from lidarmap.model import BuildingMap
    from lidarmap.refine import RefineParams

    check_same_crs(points, footprints)
    fused = fuse_campaign(BuildingMap(crs_wkt=""), cloud_source(points), trajectory, footprints, params,
                          RefineParams(), campaign_id, seed, strict=True, timings=timings)
    return list(fused.map.buildings.values())


def check_same_crs(points: PointCloud, footprints: Footprints) -> None:
    """Refuse footprints in another CRS than the points (CRSError naming the footprint file)."""
    if points.crs is not None and footprints.crs is not None:
        from lidarmap.io.crs import same_crs
        if not same_crs(points.crs, footprints.crs):
            raise CRSError(f"footprints are in {footprints.crs.name!r} but the points in {points.crs.name!r}; "
                           "reproject the footprints (Footprints.to_crs) first", footprints.source)


def join_campaign(camp: CampaignData, footprints: Footprints, params: FacadeParams) -> dict[int, np.ndarray]:
    """The campaign's building points joined to their nearest footprint (§2.2): {footprint index: point ids
    (indices into the campaign)} in footprint order, points farther than ``max_footprint_distance`` left out.

    Raises :class:`~lidarmap.errors.InputError` (naming the footprint file) when no building point lies within
    ``max_footprint_distance`` of any footprint.
    """
    xyz = camp.xyz
    cand = np.flatnonzero(camp.building)
    bidx, _ = join_footprints(xyz[cand, :2], footprints, params.max_footprint_distance, params.join_quantum)
    if not np.any(bidx >= 0):
        lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        raise no_join_error(len(cand), (lo[0], lo[1], hi[0], hi[1]), footprints, params)
    order = np.argsort(bidx, kind="stable")
    sorted_b = bidx[order]
    joined: dict[int, np.ndarray] = {}
    for b in np.unique(bidx[bidx >= 0]):
        lo, hi = np.searchsorted(sorted_b, [b, b + 1])
        joined[int(b)] = cand[order[lo:hi]]
    return joined


def no_join_error(n_building: int, points_bounds: tuple[float, float, float, float], footprints: Footprints,
                  params: FacadeParams) -> InputError:
    """The error for a campaign none of whose building points lies near a footprint (naming the footprint file)."""
    px0, py0, px1, py1 = points_bounds
    fx0, fy0, fx1, fy1 = footprints.bounds
    return InputError(
        f"none of the {n_building} building points lies within {params.max_footprint_distance:g} m of a "
        f"footprint (points bbox [{px0:.1f}, {py0:.1f}, {px1:.1f}, {py1:.1f}], footprints bbox "
        f"[{fx0:.1f}, {fy0:.1f}, {fx1:.1f}, {fy1:.1f}]): wrong footprints file or CRS?", footprints.source)


def detect_facade_groups(xyz: np.ndarray, params: FacadeParams, rng: np.random.Generator) -> list[PlaneGroup]:
    """Vertical planes of one building's points (voxel-subsampled), grouped into façades."""
    det = voxel_subsample(xyz, params.detect_voxel, params.detect_max_points, rng)
    det_xyz = xyz[det]
    if len(det_xyz) < params.min_facade_points:
        return []
    normals, nbrs = estimate_normals(det_xyz, params.normal_k)
    if params.plane_method == "region":
        planes = region_growing_vertical_planes(det_xyz, normals, nbrs, params)
    else:
        planes = ransac_vertical_planes(det_xyz, normals, params, rng)
    return group_planes(planes, params)


def building_facades(camp: CampaignData, ids: np.ndarray, polygon, params: FacadeParams, campaign_id: int,
                     seed: int = 0, rng: np.random.Generator | None = None, tm: dict | None = None) -> list[Facade]:
    """The façades of one building from its joined points ``ids`` (indices into the campaign)."""
    tm = tm if tm is not None else {}
    rng = rng if rng is not None else np.random.default_rng(seed)
    clock = time.perf_counter()
    xyz_b = camp.xyz[ids]
    near = boundary_distance(xyz_b[:, :2], polygon, params.join_quantum) <= params.max_footprint_distance
    ids, xyz_b = ids[near], xyz_b[near]
    groups = detect_facade_groups(xyz_b, params, rng)
    tm["planes"] = tm.get("planes", 0.0) + time.perf_counter() - clock
    if not groups:
        return []
    # assign each point to the eligible group with the smallest |d|
    xy = xyz_b[:, :2]
    best = np.full(len(xy), -1, dtype=np.int64)
    best_d = np.full(len(xy), np.inf)
    for g_i, g in enumerate(groups):
        d = g.plane.distance(xy)
        s = g.plane.along(xy)
        ok = (d >= g.d_min - params.layer_back) & (d <= g.d_max + params.layer_front)
        ok &= (s >= g.s_min - params.facade_margin) & (s <= g.s_max + params.facade_margin)
        closer = ok & (np.abs(d) < best_d)
        best[closer] = g_i
        best_d[closer] = np.abs(d[closer])
    facades: list[Facade] = []
    for g_i, g in enumerate(groups):
        members = ids[best == g_i]
        if len(members) < params.min_facade_points:
            continue
        facade = extract_facade(camp, members, g, polygon, params, campaign_id, seed * 31 + g_i, tm)
        if facade is not None:
            facade.facade_id = len(facades)
            facades.append(facade)
    return facades


def _orient(frame: FacadeFrame, polygon, xyz: np.ndarray, sensors: np.ndarray,
            params: FacadeParams) -> FacadeFrame:
    """Orient the frame's normal outwards: the footprint interior behind it, else the sensors in front of it."""
    std = frame.to_facade(xyz)
    s_range = (float(std[:, 0].min()), float(std[:, 0].max()))
    outward = None
    if polygon is not None:
        _, outward = match_footprint_edge(frame, s_range, polygon, params)
    if outward is None:
        toward_sensor = np.nanmean(np.sum((sensors - xyz) * frame.normal, axis=1))
        outward = bool(toward_sensor >= 0)
    return frame if outward else FacadeFrame(origin=frame.origin, u=-frame.u)


def extract_facade(camp: CampaignData, member_ids: np.ndarray, group: PlaneGroup, polygon, params: FacadeParams,
                   campaign_id: int, seed: int = 0, tm: dict | None = None) -> Facade | None:
    """A new façade from its points (indices into the campaign) and their plane group: GMM layers, 3σ PCA normal,
    re-projection and GMM again (§2.3), the frame put on the main layer at the bottom-left of its points, then
    :func:`observe_facade`'s analysis. ``None`` when too few points remain."""
    tm = tm if tm is not None else {}
    clock = time.perf_counter()
    rng = np.random.default_rng(seed)
    xyz = camp.xyz[member_ids]
    sensors = camp.sensors[member_ids]
    cell = params.cell
    n2 = group.plane.normal
    frame = FacadeFrame(origin=np.array([*(-group.plane.c * n2), 0.0]), u=np.array([-n2[1], n2[0], 0.0]))
    frame = _orient(frame, polygon, xyz, sensors, params)
    std = frame.to_facade(xyz)
    lo, hi = group.d_min - params.layer_back, group.d_max + params.layer_front
    if frame.normal[:2] @ n2 < 0:  # flipped: depths of the members flip too
        lo, hi = -group.d_max - params.layer_back, -group.d_min + params.layer_front
    keep = (std[:, 2] >= lo) & (std[:, 2] <= hi)
    for _ in range(max(1, params.refine_iterations)):
        if keep.sum() < params.min_facade_points:
            return None
        main = _main_layer(layer_fit(std[keep], cell, params, rng, seed))
        inl = keep & (np.abs(std[:, 2] - main.mu) <= params.sigma_k * main.sigma)
        if inl.sum() < 3:
            return None
        normal2, c = fit_line_2d(xyz[inl, :2])  # PCA: smallest eigenvector of the inliers, horizontal
        if normal2 @ frame.normal[:2] < 0:
            normal2, c = -normal2, -c
        frame = FacadeFrame(origin=np.array([*(-c * normal2), 0.0]), u=np.array([-normal2[1], normal2[0], 0.0]))
        std = frame.to_facade(xyz)
        keep = (std[:, 2] >= -params.layer_back) & (std[:, 2] <= params.layer_front)
    if keep.sum() < params.min_facade_points:
        return None
    layers = layer_fit(std[keep], cell, params, rng, seed)
    main = _main_layer(layers)
    on_main = keep & (assign_layers(std[:, 2], layers, params.sigma_k) == layers.index(main))
    if on_main.sum() < params.min_facade_points:
        return None
    # the frame: d = 0 on the main layer, origin at the bottom-left of its points (robust quantiles)
    s_lo, s_hi = np.quantile(std[on_main, 0], [0.001, 0.999])
    t_lo = float(np.quantile(std[on_main, 1], 0.001))
    on_any = keep & (assign_layers(std[:, 2], layers, params.sigma_k) >= 0)
    t_hi = float(np.quantile(std[on_any, 1], 0.999))
    frame = FacadeFrame(origin=frame.to_crs(np.array([[s_lo, t_lo, main.mu]]))[0], u=frame.u)
    length, height = float(s_hi - s_lo), float(t_hi - t_lo)
    if length < params.min_facade_length or height <= cell:
        return None
    for la in layers:
        la.mu -= main.mu
    tm["layers"] = tm.get("layers", 0.0) + time.perf_counter() - clock
    return observe_facade(camp, frame, (0.0, length, 0.0, height), params, campaign_id, seed=seed,
                          polygon=polygon, member_ids=member_ids, layers=layers, tm=tm)


def observe_facade(camp: CampaignData, frame: FacadeFrame, extent: tuple[float, float, float, float],
                   params: FacadeParams, campaign_id: int, seed: int = 0, polygon=None,
                   member_ids: np.ndarray | None = None, layers: list[Layer] | None = None,
                   tm: dict | None = None) -> Facade | None:
    """What one campaign says about a façade whose plane is known (a new one, or one of the map for refinement).

    The frame and the extent are kept as given, so the evidence grids align with the map's (cell
    ``params.cell`` from (extent[0], extent[2])). Points: ``member_ids`` or else the campaign's building points
    within [-layer_back, layer_front] of the plane over the extent (+ ``facade_margin``). Layers: ``layers`` (depths
    relative to the frame) or else a GMM (BIC) fitted here. Then the 2.5D grid, occlusion by ray tracing,
    objects per layer (eq. 1-2), holes -> windows/doors (eq. 3) and unknown regions, and the evidence grids.
    Returns ``None`` when the campaign has too few points on the plane.
    """
    tm = tm if tm is not None else {}
    clock = time.perf_counter()
    rng = np.random.default_rng(seed + 7)
    cell = params.cell
    s0, s1, t0, t1 = (float(v) for v in extent)
    margin = params.facade_margin
    if member_ids is None:
        corners = frame.to_crs(np.array([[s0 - margin, 0, -params.layer_back], [s1 + margin, 0, -params.layer_back],
                                         [s0 - margin, 0, params.layer_front], [s1 + margin, 0, params.layer_front]]))
        x0, y0 = corners[:, :2].min(axis=0)
        x1, y1 = corners[:, :2].max(axis=0)
        ids = camp.nonground_ids[camp.nonground_index.query_box(x0, y0, x1, y1)]
        ids = ids[camp.building[ids]]
        std = frame.to_facade(camp.xyz[ids])
        ok = (std[:, 2] >= -params.layer_back) & (std[:, 2] <= params.layer_front)
        ok &= (std[:, 0] >= s0 - margin) & (std[:, 0] <= s1 + margin) & (std[:, 1] >= t0 - 1.0)
        ok &= std[:, 1] <= t1 + 1.0
        member_ids = ids[ok]
    xyz = camp.xyz[member_ids]
    sensors = camp.sensors[member_ids]
    std = frame.to_facade(xyz)
    keep = (std[:, 2] >= -params.layer_back) & (std[:, 2] <= params.layer_front)
    keep &= (std[:, 0] >= s0 - margin) & (std[:, 0] <= s1 + margin)
    if keep.sum() < params.min_facade_points:
        return None
    if layers is None:
        layers = layer_fit(std[keep], cell, params, rng, seed)
    layers = [dataclasses.replace(la, layer_id=i, campaigns=[campaign_id]) for i, la in enumerate(layers)]
    main = _main_layer(layers)
    main_idx = layers.index(main)
    labels = np.full(len(std), -1, dtype=np.int64)
    labels[keep] = assign_layers(std[keep, 2], layers, params.sigma_k)
    tm["layers"] = tm.get("layers", 0.0) + time.perf_counter() - clock

    clock = time.perf_counter()
    shape = grid_shape(extent, cell)
    rows, cols = shape
    grid = depth_grid(std[labels >= 0], cell, extent)
    lab_pts = labels[labels >= 0]
    flat = grid.flat()
    ok = flat >= 0
    per_layer = np.zeros((len(layers), rows * cols), dtype=np.int64)
    np.add.at(per_layer, (lab_pts[ok], flat[ok]), 1)
    count = per_layer.sum(axis=0).reshape(shape)
    if not (count > 0).any():
        return None
    # the cell's surface is its front-most layer with a real share of its points (layers are sorted deepest
    # first): a wall hides what lies behind it in the same cell (room ceilings seen through a window), a balcony
    # hides the wall
    present = (per_layer >= 2) & (per_layer >= params.layer_cell_share * per_layer.sum(axis=0))
    present[main_idx] = per_layer[main_idx] >= 2  # any real wall sample hides what is behind it
    front_most = len(layers) - 1 - np.argmax(present[::-1], axis=0)
    dominant = np.where(present.any(axis=0), front_most, np.where(count.ravel() > 0, np.argmax(per_layer, axis=0),
                                                                   -1)).reshape(shape)
    observed_raw = count > 0
    observed = close_sampling_gaps(count, cell, params.close_cells, params.max_close_cells)

    # points around the façade (any class): occluders in front, seen-through points behind
    front = sensors @ frame.normal - frame.normal @ frame.origin
    front_dist = float(min(np.nanquantile(front, 0.99) + 1.0, camp.limits[0] * params.reach_margin + 1.0))
    corners = frame.to_crs(np.array([[s0, 0, front_dist], [s1, 0, front_dist],
                                     [s0, 0, -params.through_max_depth], [s1, 0, -params.through_max_depth]]))
    x0, y0 = corners[:, :2].min(axis=0) - 1.0
    x1, y1 = corners[:, :2].max(axis=0) + 1.0
    around = camp.nonground_ids[camp.nonground_index.query_box(x0, y0, x1, y1)]
    a_std = frame.to_facade(camp.xyz[around])
    a_sens = frame.to_facade(camp.sensors[around])
    fg = (a_std[:, 2] > params.occluder_min_depth) & (a_std[:, 2] < a_sens[:, 2])
    fg_spacing = sample_spacing(a_std[fg], rng=rng) if fg.any() else 0.0
    occluded = occlusion_mask(a_std[fg], a_sens[fg], shape, s0, t0, cell, params, spacing=fg_spacing)
    behind = a_std[:, 2] < -params.layer_back
    through = through_cells(a_std[behind], a_sens[behind], shape, s0, t0, cell) > 0
    reachable = reach_mask(frame.to_facade(camp.track), shape, s0, t0, cell, camp.limits, params)
    observed &= ~(through & ~observed_raw)
    if params.occlusion_grow_cells > 0:
        grow = square(params.occlusion_grow_cells)
        occluded = occluded | (ndimage.binary_dilation(occluded, structure=grow) & ~observed & ~through)
    ground_t = _ground_line(camp, frame, s0, s1, t0, cols, cell, params)
    # the ground is never above the lowest wall measured in a column
    lowest = np.where(observed_raw.any(axis=0), t0 + np.argmax(observed_raw, axis=0) * cell, np.inf)
    ground_t = np.minimum(ground_t, lowest)
    t_centres = t0 + (np.arange(rows) + 0.5) * cell
    below = (t_centres[:, None] < ground_t[None, :] - 0.5 * cell) & ~observed_raw
    values = value_grid(observed, occluded | ~reachable | below, through)
    tm["occlusion"] = tm.get("occlusion", 0.0) + time.perf_counter() - clock

    clock = time.perf_counter()
    elements: list[Element] = []
    window_votes = np.zeros(shape, dtype=np.int32)
    min_cells = max(1, int(math.ceil(params.min_object_area / (cell * cell))))
    min_width = max(1, int(round(params.min_object_width / cell)))
    g_inside = labels >= 0
    pts_row = np.full(len(std), -1, dtype=np.int64)
    pts_col = np.full(len(std), -1, dtype=np.int64)
    pts_row[g_inside], pts_col[g_inside] = grid.row, grid.col
    door_cells = np.zeros(shape, dtype=bool)

    def add(kind: ElementKind, poly, layer_id, unc: float, n: int = 0) -> None:
        elements.append(Element(element_id=len(elements), kind=kind, polygon=poly, layer_id=layer_id,
                                uncertainty=float(unc), n_points=int(n), campaigns=[campaign_id]))

    for li, layer in enumerate(layers):
        offset = layer.mu - main.mu
        if li == main_idx or abs(offset) <= params.structure_min_offset:
            continue
        comp, n = grow_regions(dominant == li, params.close_cells, min_cells, min_width)
        for k in range(1, n + 1):
            cmask = comp == k
            sel = (labels == li) & (pts_row >= 0)
            sel[sel] = cmask[pts_row[sel], pts_col[sel]]
            if not sel.any():
                continue
            kind, poly = ElementKind.STRUCTURE, None
            unc = uncertainty_eq1(layer.mu, layer.sigma, float(std[sel, 2].mean()))[1]
            if offset < 0:  # recessed and rectangular: a door leaf on the ground, a window (blinds) above it
                rr, cc = np.nonzero(cmask)
                r_lo, r_hi, c_lo, c_hi = rr.min(), rr.max() + 1, cc.min(), cc.max() + 1
                width, h = (c_hi - c_lo) * cell, (r_hi - r_lo) * cell
                fill = cmask.sum() / float((r_hi - r_lo) * (c_hi - c_lo))
                on_ground = t0 + r_lo * cell <= float(np.mean(ground_t[c_lo:c_hi])) + params.door_bottom_tol
                depths = std[sel, 2]
                spread = 1.4826 * float(np.median(np.abs(depths - np.median(depths))))  # robust σ of the object
                opening = fill >= params.Ta and min(width, h) >= params.min_opening_size \
                    and width * h <= params.max_opening_area and spread <= params.surface_max_sigma
                if opening and on_ground and h >= params.door_min_height and width <= params.door_max_width:
                    kind = ElementKind.DOOR
                elif opening and params.recessed_windows and not (on_ground and h >= params.door_min_height):
                    kind = ElementKind.WINDOW
                elif spread > params.surface_max_sigma:
                    continue  # recessed clutter (reveals, mixed cells, interiors seen through glass): no surface
                if kind is not ElementKind.STRUCTURE:
                    vals = np.where(cmask, HOLE, np.where(values == OCCLUDED, OCCLUDED, OBJECT))
                    rect, unc = fit_rectangle(cmask, vals, params)
                    b_s0, b_s1, b_t0, b_t1 = refine_bounds(rect, None, s0, t0, cell, params)
                    poly = box(max(b_s0, s0), max(b_t0, t0), min(b_s1, s1), min(b_t1, t1))
                    door_cells |= cmask
            if poly is None:
                st = std[sel, :2]
                if len(st) > params.max_outline_points:
                    st = st[rng.choice(len(st), size=params.max_outline_points, replace=False)]
                poly = outline_polygon(st, cell, params.concave_ratio)
            if poly is not None:
                add(kind, poly, layer.layer_id, unc, int(sel.sum()))
    window_votes[door_cells] = 1
    values[door_cells] = OBJECT  # a door leaf is not a hole of the wall for the window search

    wall_st = std[labels == main_idx, :2]
    openings = detect_openings(values, cell, params, ground_t=ground_t, t0=t0, s0=s0, wall_st=wall_st)
    if params.complete_by_repetition:
        complete_by_repetition(openings, values, s0, t0, cell, params)
    for op in openings:
        if op.kind in (ElementKind.WINDOW, ElementKind.DOOR) and op.bounds is not None:
            b_s0, b_s1, b_t0, b_t1 = op.bounds
            add(op.kind, box(max(b_s0, s0), max(b_t0, t0), min(b_s1, s1), min(b_t1, t1)), None, op.uncertainty)
            window_votes[op.mask] = 1
            continue
        if op.window_evidence:
            window_votes[op.mask] = 1
        for poly in mask_to_polygons(op.mask, s0, t0, cell):
            add(ElementKind.UNKNOWN, poly, None, math.inf)
    min_unknown = max(1, int(math.ceil(params.min_unknown_area / (cell * cell))))
    occ_comp, n_occ = grow_regions((values == OCCLUDED) & ~below, 0, min_unknown)
    for k in range(1, n_occ + 1):
        for poly in mask_to_polygons(occ_comp == k, s0, t0, cell):
            add(ElementKind.UNKNOWN, poly, None, math.inf)
    tm["elements"] = tm.get("elements", 0.0) + time.perf_counter() - clock

    seen = (values != OCCLUDED).astype(np.int32)
    object_votes = ((values == OBJECT) & ~door_cells).astype(np.int32)
    evidence = FacadeEvidence(cell=cell, s0=s0, t0=t0, window_votes=window_votes, object_votes=object_votes,
                              seen=seen)
    edge = match_footprint_edge(frame, (s0, s1), polygon, params)[0] if polygon is not None else None
    for la, n in zip(layers, np.bincount(labels[labels >= 0], minlength=len(layers))):
        la.n_points = int(n)
    return Facade(facade_id=0, frame=frame, sigma=float(main.sigma), extent=(s0, s1, t0, t1), layers=layers,
                  elements=elements, main_layer=main.layer_id, n_points=int((labels >= 0).sum()),
                  footprint_edge=edge, campaigns=[campaign_id], evidence=evidence)


def _ground_line(camp: CampaignData, frame: FacadeFrame, s0: float, s1: float, t0: float, cols: int, cell: float,
                 params: FacadeParams) -> np.ndarray:
    """Ground height (façade t) in front of every grid column: the 20th percentile height of the ground points in
    a band ``ground_band`` in front of the wall, per ``ground_bin`` along it, median-filtered over 3 bins and
    interpolated; the grid's bottom ``t0`` where no ground point was measured."""
    s_mid = s0 + (np.arange(cols) + 0.5) * cell
    if camp.ground_index is None:
        return np.full(cols, t0)
    band = params.ground_band
    corners = frame.to_crs(np.array([[s0, 0, 0.0], [s1, 0, 0.0], [s0, 0, band], [s1, 0, band]]))
    x0, y0 = corners[:, :2].min(axis=0)
    x1, y1 = corners[:, :2].max(axis=0)
    ids = camp.ground_ids[camp.ground_index.query_box(x0, y0, x1, y1)]
    g = frame.to_facade(camp.xyz[ids])
    g = g[(g[:, 2] > 0.2) & (g[:, 2] < band) & (g[:, 0] >= s0) & (g[:, 0] <= s1)]
    if len(g) < 3:
        return np.full(cols, t0)
    bins = np.floor((g[:, 0] - s0) / params.ground_bin).astype(np.int64)
    order = np.argsort(bins, kind="stable")
    uniq, start = np.unique(bins[order], return_index=True)
    low = np.array([np.quantile(g[order[a:b], 1], 0.2) for a, b in zip(start, np.append(start[1:], len(order)))])
    if len(low) >= 3:  # a bin of mislabelled points (a car hid the street) must not lift the ground
        padded = np.concatenate([low[:1], low, low[-1:]])
        low = np.median(np.stack([padded[:-2], padded[1:-1], padded[2:]]), axis=0)
    return np.interp(s_mid, s0 + (uniq + 0.5) * params.ground_bin, low)
