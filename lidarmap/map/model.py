"""The persistent building map: Map -> Building -> Facade -> Layer / Element, with uncertainty and evidence.

Small typed dataclasses only; extraction (``facade.py``), refinement (``refine.py``) and the store (``store.py``)
create, update and persist them. Façade-plane coordinates follow CONTRIBUTING.md: (s, t, d) with s along the wall,
t up, d along the outward normal.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from shapely.geometry import Polygon

from lidarmap.facade.model import Facade

#: Building attribute marking a footprint derived from the points (lidarmap.facade.discover): a polygon of grid
#: cells whose edges do not follow the walls.
DERIVED = "derived_footprint"


@dataclasses.dataclass
class RoofPlane:
    """A roof plane from aerial data: n . x + offset = 0 (CRS), its outline in xy and fit σ."""

    plane_id: int
    normal: np.ndarray
    offset: float
    outline: Polygon
    sigma: float
    n_points: int
    campaigns: list[int] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Building:
    """A building of the map: footprint (CRS), attributes, façades from the street, roofs from the air."""

    building_id: str
    footprint: Polygon
    attributes: dict = dataclasses.field(default_factory=dict)
    facades: list[Facade] = dataclasses.field(default_factory=list)
    roofs: list[RoofPlane] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Campaign:
    """One update of the map: which data, when, and a fingerprint that detects re-applying it."""

    campaign_id: int
    kind: str  # "mobile" | "aerial"
    source: str
    fingerprint: str
    n_points: int
    created: str
    summary: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class BuildingMap:
    """The whole map: CRS (WKT), buildings by id and the campaigns applied so far."""

    crs_wkt: str
    buildings: dict[str, Building] = dataclasses.field(default_factory=dict)
    campaigns: list[Campaign] = dataclasses.field(default_factory=list)
