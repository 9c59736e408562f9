"""lidarmap: LiDAR point clouds of cities to building models that improve with every new scan.

The main jobs are a few lines of Python (:mod:`lidarmap.api`)::

    import lidarmap
    cloud = lidarmap.read("tile.laz", crs="EPSG:28992")
    result = lidarmap.run(["tile.laz"], lidarmap.read_footprints("bag.geojson"), "out/", crs="EPSG:28992")

The names are loaded on first use, so ``import lidarmap`` (and ``lidarmap --help``) stays fast.
"""

from lidarmap._version import __version__

_API = ("read", "write", "read_footprints", "segment_buildings", "run", "update_map", "open_map", "export_cityjson",
        "PointCloud", "Footprints", "BuildingMap", "PipelineConfig", "RunResult", "UpdateResult")

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from lidarmap import api

        return getattr(api, name)
    raise AttributeError(f"module 'lidarmap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
