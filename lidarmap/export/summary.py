"""What a building map holds, in numbers (the CLI's summaries, ``map history``, CityJSON attributes).

Unknown regions are counted as ``unknown`` whatever their kind says (``Element.is_unknown``: UNKNOWN or ε = ∞),
the same rule the CityJSON export and the renders use.
"""

from __future__ import annotations

from collections.abc import Iterable

from lidarmap.facade.model import Element, ElementKind
from lidarmap.map.model import Building, BuildingMap

__all__ = ["COUNT_KEYS", "element_class", "count_buildings", "count_map"]

#: Keys of :func:`count_map` / :func:`count_buildings`, in display order.
COUNT_KEYS = ("buildings", "facades", "layers", "windows", "doors", "structures", "unknown", "roofs")

_PLURAL = {ElementKind.WINDOW: "windows", ElementKind.DOOR: "doors", ElementKind.STRUCTURE: "structures"}


def element_class(element: Element) -> str:
    """``"windows"``, ``"doors"``, ``"structures"`` or ``"unknown"`` (the count an element adds to)."""
    if element.is_unknown:
        return "unknown"
    return _PLURAL.get(ElementKind(element.kind), "unknown")


def count_buildings(buildings: Iterable[Building]) -> dict[str, int]:
    """Buildings, façades, layers, windows, doors, structures, unknown regions and roof planes."""
    counts = dict.fromkeys(COUNT_KEYS, 0)
    for building in buildings:
        counts["buildings"] += 1
        counts["roofs"] += len(building.roofs)
        for facade in building.facades:
            counts["facades"] += 1
            counts["layers"] += len(facade.layers)
            for element in facade.elements:
                counts[element_class(element)] += 1
    return counts


def count_map(building_map: BuildingMap) -> dict[str, int]:
    """:func:`count_buildings` over the whole map."""
    return count_buildings(building_map.buildings.values())
