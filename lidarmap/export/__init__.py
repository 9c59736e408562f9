"""Exports of the building map: CityJSON 2.0 (:mod:`.cityjson`, checked by :mod:`.validate`), façade images
(:mod:`.render`) and counts (:mod:`.summary`).

All take a :class:`lidarmap.map.model.BuildingMap` (``MapStore.load()``) and never touch the store. The renderer
(matplotlib) is imported only by ``lidarmap.export.render``.
"""

from lidarmap.export.cityjson import map_to_cityjson, write_cityjson
from lidarmap.export.summary import count_buildings, count_map
from lidarmap.export.validate import validate_cityjson

__all__ = ["map_to_cityjson", "write_cityjson", "count_buildings", "count_map", "validate_cityjson"]
