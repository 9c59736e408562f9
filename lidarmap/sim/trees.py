"""Trees that touch buildings, and bare (leaf-off) crowns.

Real crowns stand against walls and hang over roof edges: the hardest case for a building segmenter, and for the
reconstruction after it (a crown called building grows the building's voxels and mesh). ``SimParams.trees_touching``
places that many trees beside the walls of existing buildings, each crown reaching over the roof edge by
:data:`OVERHANG` metres at about eave height; the trunk stays outside the footprint. ``SimParams.leaf_off`` makes
every crown bare: fewer and smaller scatterers (twigs and branches), so more of each pulse reaches the ground.

Crowns stay porous either way (:func:`lidarmap.sim.city.trees_soup`: leaf triangles pulses pass between and
through, several returns per pulse).
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: How far (m) a touching tree's crown reaches over the roof edge (uniform in this range).
OVERHANG = (1.0, 2.0)
#: Crown radius (m) of touching trees (uniform in this range).
CROWN_RADIUS = (2.5, 3.5)
#: Leaf size (m) and leaf area density (m²/m³) of crowns: leaf-on (the city's default) and leaf-off (twigs).
LEAF_ON = {"leaf_size": 0.35, "leaf_area_density": 0.8}
LEAF_OFF = {"leaf_size": 0.2, "leaf_area_density": 0.2}


@dataclasses.dataclass(frozen=True)
class TreeSpot:
    """Where a touching tree stands (local frame) and its crown: the city turns it into a ``Tree``."""

    x: float
    y: float
    crown_radius: float
    crown_half_height: float
    crown_centre_z: float  # absolute height of the crown's centre
    building_id: int


def crown_leaves(leaf_off: bool) -> dict[str, float]:
    """Keyword arguments of ``trees_soup`` for leaf-on or leaf-off crowns."""
    return dict(LEAF_OFF if leaf_off else LEAF_ON)


def touching_spots(rng: np.random.Generator, rings: list[np.ndarray], eaves: list[float], ids: list[int],
                   count: int) -> list[TreeSpot]:
    """``count`` trees beside the walls of the buildings (footprint rings CCW, eave heights, ids), one per
    building in a random order (cycling when there are more trees than buildings): each at a random point of a
    random wall, outside, its crown centred at the eave and reaching over the wall by :data:`OVERHANG`."""
    if count <= 0 or not rings:
        return []
    order = rng.permutation(len(rings))
    spots = []
    for k in range(count):
        b = int(order[k % len(rings)])
        ring = rings[b]
        edge = int(rng.integers(len(ring)))
        a, c = ring[edge], ring[(edge + 1) % len(ring)]
        along = c - a
        length = float(np.hypot(*along))
        outward = np.array([along[1], -along[0]]) / length  # a CCW ring's outside is to the right
        at = a + along * rng.uniform(0.25, 0.75)
        radius = rng.uniform(*CROWN_RADIUS)
        trunk = at + outward * (radius - rng.uniform(*OVERHANG))
        spots.append(TreeSpot(x=float(trunk[0]), y=float(trunk[1]), crown_radius=float(radius),
                              crown_half_height=float(rng.uniform(2.0, 3.0)), crown_centre_z=float(eaves[b]),
                              building_id=int(ids[b])))
    return spots
