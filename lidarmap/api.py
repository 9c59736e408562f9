"""The main jobs in a few lines of Python (what ``import lidarmap`` exposes).

::

    import lidarmap

    cloud = lidarmap.read("tile.laz", crs="EPSG:28992")               # PointCloud (float64 CRS coordinates)
    probability = lidarmap.segment_buildings(cloud)                   # building probability per point
    footprints = lidarmap.read_footprints("bag.geojson", id_field="bag_pand_id")
    result = lidarmap.run(["tile.laz"], footprints, "out/", crs="EPSG:28992")   # the aerial pipeline
    update = lidarmap.update_map("city.lmap", points="mls.laz", trajectory="traj.csv", footprints="bag.geojson")
    city = lidarmap.open_map("city.lmap")                             # BuildingMap (as_of=N: as after campaign N)
    lidarmap.export_cityjson(city, "city.city.json")

Every function takes the same parameters as the command of the same name (``lidarmap run``, ``lidarmap map update``,
...); stage parameters are the dataclasses of their stages (``lidarmap.aerial.pipeline.PipelineConfig``,
``lidarmap.facade.params.FacadeParams``, ...), defaults documented there and in ``lidarmap config defaults``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pyproj import CRS

from lidarmap.aerial.pipeline import PipelineConfig, RunResult, run_pipeline
from lidarmap.core import Footprints, PointCloud
from lidarmap.export.cityjson import map_to_cityjson, write_cityjson
from lidarmap.facade.params import FacadeParams
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las, write_las
from lidarmap.map.apply import UpdateResult, apply_campaign, campaign_inputs
from lidarmap.map.model import BuildingMap
from lidarmap.map.refine import RefineParams
from lidarmap.map.store import MapStore
from lidarmap.map.update import UpdateParams
from lidarmap.segment.modelfile import load_model
from lidarmap.segment.predict import PredictParams, predict

__all__ = ["read", "write", "read_footprints", "segment_buildings", "run", "update_map", "open_map",
           "export_cityjson", "PointCloud", "Footprints", "BuildingMap", "PipelineConfig", "RunResult", "UpdateResult"]


def read(path: str | Path, crs: str | CRS | None = None) -> PointCloud:
    """A whole LAS/LAZ file as a :class:`PointCloud`; ``crs`` for files without a CRS record."""
    return read_las(path, crs=crs)


def write(path: str | Path, cloud: PointCloud) -> Path:
    """Write a :class:`PointCloud` as LAS/LAZ (by suffix), atomically."""
    return write_las(path, cloud)


def segment_buildings(cloud: PointCloud, params: PredictParams | None = None, model: Any = None) -> Any:
    """Building probability (float32, one per point) from the shipped PointNet++ model (or ``model``)."""
    return predict(cloud, model if model is not None else load_model(), params or PredictParams())


def run(tiles: Sequence[str | Path] | str | Path, footprints: Footprints, out_dir: str | Path,
        config: PipelineConfig | None = None, crs: str | CRS | None = None) -> RunResult:
    """The aerial pipeline (``lidarmap run``): buildings of ``tiles`` segmented, densified, flattened, voxelized and
    meshed into ``out_dir`` (resumable; see docs/pipeline.md)."""
    tiles = [tiles] if isinstance(tiles, (str, Path)) else list(tiles)
    return run_pipeline(tiles, footprints, out_dir, config or PipelineConfig(), crs=crs)


def update_map(map_path: str | Path, points: str | Path | None = None, trajectory: str | Path | None = None,
               footprints: str | Path | None = None, aerial: str | Path | None = None, id_field: str = "id",
               crs: str | None = None, seed: int = 0, facade: FacadeParams | None = None,
               refine: RefineParams | None = None, update: UpdateParams | None = None,
               columns: str | None = None) -> UpdateResult:
    """Fuse one campaign into the map file (``lidarmap map update``): a mobile campaign (``points``: LAS/LAZ, PLY or
    text with ``columns``; ``trajectory`` and ``footprints`` optional, docs/mls.md) or an aerial scan (``aerial``).
    One transaction; the map is created when missing."""
    as_path = (lambda p: None if p is None else Path(p))
    inputs = campaign_inputs(as_path(points), as_path(trajectory), as_path(aerial), as_path(footprints), id_field,
                             crs, columns)
    return apply_campaign(Path(map_path), inputs, (facade or FacadeParams(), refine or RefineParams()), seed,
                          update=update)


def open_map(map_path: str | Path, as_of: int | None = None) -> BuildingMap:
    """The stored map (as it was right after campaign ``as_of`` when given)."""
    with MapStore.open(map_path, readonly=True) as store:
        return store.load(as_of=as_of)


def export_cityjson(building_map: BuildingMap, path: str | Path) -> Path:
    """Write the map as CityJSON 2.0 (atomically)."""
    return write_cityjson(path, map_to_cityjson(building_map))
