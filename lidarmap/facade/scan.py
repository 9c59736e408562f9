"""What façade work needs to know about a whole mobile campaign, gathered in two passes over its points.

Façade work looks at one building's surroundings (:mod:`lidarmap.map.update`), but some of its inputs belong to the
whole campaign and must not change with the part of it a building sees, the chunk size or the worker:

* which points are ground and which are building candidates (:class:`PointClasses`): the ASPRS classes when the
  campaign holds them anywhere (one chunk or one street without class 2 must not switch rules), else the height
  rule over the lowest point of every ``ground_cell`` cell of a lattice anchored at the campaign's origin
  (:class:`~lidarmap.facade.observe.observe.planes.LowestCells`);
* the GPS time span of the non-ground points (the trajectory must cover it; the reach track is sampled over it);
* the scanner's reach limits (:func:`~lidarmap.facade.observe.observe.occlusion.reach_limits`), measured on every k-th non-ground
  point of the file (k = points // ``REACH_SAMPLE``): a stride sample depends on the file alone, where a random one
  would depend on how the points arrive.

Pass 1 (:class:`CampaignScan`, chunk by chunk in file order) numbers the points and gathers the classes present and
the lowest cells; pass 2 (:class:`StatsPass`, any batching, every point once) needs pass 1's classes to tell ground
from the rest.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lidarmap.core import PointCloud, Trajectory
from lidarmap.errors import InputError
from lidarmap.facade.occlusion import reach_limits
from lidarmap.facade.params import FacadeParams
from lidarmap.facade.planes import LowestCells

__all__ = ["REACH_SAMPLE", "PointClasses", "CampaignScan", "CampaignStats", "StatsPass"]

#: The reach limits are measured on about this many points (at most twice as many) spread evenly over the file.
REACH_SAMPLE = 200_000


@dataclasses.dataclass
class PointClasses:
    """The campaign's rule for ground and building points (see the module doc); ``None`` classes: not present."""

    ground_class: int | None
    building_class: int | None
    lowest: LowestCells | None  # the height rule's table when the campaign has no ground class
    ground_height: float

    def masks(self, xyz: np.ndarray, classification: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(ground, building) masks of some of the campaign's points; building points are never ground."""
        if self.ground_class is not None:
            ground = classification == self.ground_class
        else:
            ground = self.lowest.ground(xyz, self.ground_height)
        building = classification == self.building_class if self.building_class is not None else ~ground
        return ground, building & ~ground


class CampaignScan:
    """Pass 1: point count and bounds, the classes present, the lowest cells (until a ground class shows up)."""

    def __init__(self, origin: np.ndarray, params: FacadeParams, source: str | None = None):
        self.params = params
        self.source = source
        self.n_points = 0
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.seen = np.zeros(256, dtype=bool)
        self.lowest: LowestCells | None = LowestCells(origin, params.join.ground_cell)

    def _seen(self, code: int) -> bool:
        return 0 <= code < 256 and bool(self.seen[code])

    def add(self, cloud: PointCloud) -> np.ndarray:
        """Take one chunk (file order); returns its points' numbers in the campaign."""
        if "gps_time" not in cloud.attrs:
            raise InputError("the points have no gps_time: façade occlusion needs each point's sensor position",
                             self.source)
        classification = cloud.attrs.get("classification")
        if classification is not None and len(classification):
            self.seen[np.unique(classification).astype(np.int64)] = True
        if self._seen(self.params.join.ground_class):
            self.lowest = None  # the classes decide: the height rule's table is not needed
        elif self.lowest is not None:
            self.lowest.add(cloud.xyz)
        if len(cloud):
            self.lo = np.minimum(self.lo, cloud.xyz.min(axis=0))
            self.hi = np.maximum(self.hi, cloud.xyz.max(axis=0))
        index = np.arange(self.n_points, self.n_points + len(cloud), dtype=np.int64)
        self.n_points += len(cloud)
        return index

    def classes(self) -> PointClasses:
        """The campaign's ground/building rule, once every chunk went through :meth:`add`."""
        p = self.params.join
        by_class = self._seen(p.ground_class)
        return PointClasses(ground_class=p.ground_class if by_class else None,
                            building_class=p.building_class if self._seen(p.building_class) else None,
                            lowest=None if by_class else self.lowest.finish(), ground_height=p.ground_height)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """xy bounding box of the points seen."""
        return float(self.lo[0]), float(self.lo[1]), float(self.hi[0]), float(self.hi[1])


@dataclasses.dataclass(frozen=True)
class CampaignStats:
    """The campaign-wide numbers every building's task shares."""

    n_points: int
    n_nonground: int
    n_building: int
    t_span: tuple[float, float]  # GPS time of the first and last non-ground point
    limits: tuple[float, float, float]  # max range, min and max elevation angle (radians)
    bounds: tuple[float, float, float, float]  # xy box of all points
    source: str | None = None  # the point file


class StatsPass:
    """Pass 2: non-ground time span (checked against the trajectory), counts, and the stride sample for the reach
    limits. Batches may come in any order; each point exactly once."""

    def __init__(self, classes: PointClasses, scan: CampaignScan, trajectory: Trajectory):
        self.classes, self.scan, self.trajectory = classes, scan, trajectory
        self.stride = max(1, scan.n_points // REACH_SAMPLE)
        self.n_nonground = self.n_building = self.outside = 0
        self.t_lo, self.t_hi = np.inf, -np.inf
        self.sample: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, xyz: np.ndarray, gps: np.ndarray, classification: np.ndarray | None,
            index: np.ndarray) -> np.ndarray:
        """Take a batch; returns its building mask."""
        ground, building = self.classes.masks(xyz, classification)
        nonground = ~ground
        self.n_nonground += int(nonground.sum())
        self.n_building += int(building.sum())
        if nonground.any():
            t = gps[nonground]
            self.t_lo, self.t_hi = min(self.t_lo, float(t.min())), max(self.t_hi, float(t.max()))
            self.outside += self.trajectory.count_outside(t)
        pick = nonground & (index % self.stride == 0)
        self.sample.append((index[pick], xyz[pick], gps[pick]))
        return building

    def finish(self, reach_quantile: float) -> CampaignStats:
        """The stats; InputError when every point is ground or the trajectory misses some non-ground times."""
        if self.n_nonground == 0:
            raise InputError("every point is ground: no façade can be extracted", self.scan.source)
        self.trajectory.check_covers(self.t_lo, self.t_hi, self.outside)
        index = np.concatenate([s[0] for s in self.sample])
        order = np.argsort(index)  # file order: the value does not depend on the batching
        xyz = np.concatenate([s[1] for s in self.sample])[order]
        sensors = self.trajectory.position_at(np.concatenate([s[2] for s in self.sample])[order])
        return CampaignStats(n_points=self.scan.n_points, n_nonground=self.n_nonground, n_building=self.n_building,
                             t_span=(self.t_lo, self.t_hi), limits=reach_limits(xyz, sensors, reach_quantile),
                             bounds=self.scan.bounds, source=self.scan.source)
