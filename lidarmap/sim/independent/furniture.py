"""Street furniture (static) and the things that change between campaigns (parked vehicles, people, bicycles).

Static: trees (trunk, a few branches, a crown of small leaf triangles that pass part of each pulse), lamp posts,
sign posts, bollards and a bus shelter with glass walls. Per campaign: cars and vans (2.2-2.8 m tall) parked
along both curbs, pedestrians (box people) on the sidewalks and parked bicycles. Positions along a sidewalk's
curb strip are kept apart through a list of occupied x intervals.
"""

from __future__ import annotations

import numpy as np

from .geometry import (CAR, GLASS, LEAF, PERSON, STREET, TRUNK, VAN, Materials, MeshBuilder, cylinder,
                       random_leaves, world_box)
from .terrain import Terrain


class Strip:
    """Occupied x intervals along the curb strip of each side."""

    def __init__(self):
        self.used = {1: [], -1: []}
        self.shelter = {1: [], -1: []}

    def free(self, side: int, a: float, b: float) -> bool:
        return all(b <= u0 or a >= u1 for u0, u1 in self.used[side])

    def take(self, side: int, a: float, b: float) -> None:
        self.used[side].append((a, b))


def _blocked_x(terrain: Terrain, side: int, a: float, b: float) -> bool:
    """True where [a, b] runs into the cross street on that side."""
    if terrain.cross is None or terrain.cross[0] != side:
        return False
    _, x0, x1 = terrain.cross
    return b > x0 - 1.0 and a < x1 + 1.0


def static_furniture(rng, terrain: Terrain, mats: Materials, front_y: dict) -> tuple[MeshBuilder, Strip]:
    """front_y: side -> smallest |y| of a façade structure line on that side (crowns stay clear of it)."""
    mb, strip = MeshBuilder(), Strip()
    L, rh = terrain.length, terrain.road_half
    shelter_side = max((1, -1), key=lambda s: terrain.sidewalk[s])
    if terrain.sidewalk[shelter_side] >= 3.0 and rng.random() < 0.5:
        for _ in range(20):
            x = rng.uniform(15.0, max(16.0, L - 15.0))
            if not _blocked_x(terrain, shelter_side, x - 3, x + 3):
                _bus_shelter(rng, mb, mats, terrain, shelter_side, x)
                strip.take(shelter_side, x - 3.0, x + 3.0)
                strip.shelter[shelter_side].append((x - 6.0, x + 6.0))
                break
    for side in (1, -1):
        if rng.random() < 0.6:
            _trees(rng, mb, mats, terrain, strip, side, front_y.get(side, rh + terrain.sidewalk[side]))
    lamp_sides = [1, -1] if rng.random() < 0.7 else [int(rng.choice([1, -1]))]
    for side in lamp_sides:
        for x in np.arange(rng.uniform(3, 15), L, rng.uniform(20, 30)):
            _place(strip, terrain, side, x, 0.4, lambda p: _lamp(rng, mb, mats, p, side))
    for _ in range(int(rng.integers(3, 7))):
        side = int(rng.choice([1, -1]))
        _place(strip, terrain, side, rng.uniform(2, L - 2), 0.2,
               lambda p: _signpost(rng, mb, mats, p))
    for _ in range(int(rng.integers(1, 3))):
        side, x = int(rng.choice([1, -1])), rng.uniform(5, L - 5)
        r = rng.uniform(0.08, 0.12)
        mat = mats.add(STREET, refl=float(rng.uniform(0.1, 0.6)))
        for j in range(int(rng.integers(3, 7))):
            _place(strip, terrain, side, x + 1.5 * j, 0.15,
                   lambda p: mb.add(cylinder(p, rng.uniform(0.8, 1.0), r), mat))
    return mb, strip


def _place(strip: Strip, terrain: Terrain, side: int, x: float, half: float, build, offset: float = 0.4) -> bool:
    if not strip.free(side, x - half, x + half) or _blocked_x(terrain, side, x - half, x + half):
        return False
    y = side * (terrain.road_half + offset)
    build(np.array([x, y, float(terrain.z(x, y))]))
    strip.take(side, x - half, x + half)
    return True


def _trees(rng, mb, mats, terrain, strip, side, front_abs) -> None:
    offset = rng.uniform(0.7, 1.1)
    reach = front_abs - (terrain.road_half + offset) - 0.3
    if reach < 1.0:
        return
    spacing = rng.uniform(8.0, 15.0)
    bark = mats.add(TRUNK, refl=float(rng.uniform(0.2, 0.4)))
    for x in np.arange(rng.uniform(3, 8), terrain.length - 3, spacing):
        x = x + rng.uniform(-1, 1)
        if not strip.free(side, x - 1.0, x + 1.0) or _blocked_x(terrain, side, x - 2, x + 2):
            continue
        strip.take(side, x - 1.0, x + 1.0)
        y = side * (terrain.road_half + offset)
        z = float(terrain.z(x, y))
        trunk_h, r = rng.uniform(2.8, 4.0), rng.uniform(0.12, 0.25)
        rx, rz = min(rng.uniform(1.5, 3.0), reach), rng.uniform(1.5, 3.5)
        centre = np.array([x, y, z + trunk_h + rz * 0.8])
        mb.add(cylinder((x, y, z), trunk_h + rz * 0.6, r, sections=8), bark)
        for a in rng.uniform(0, 2 * np.pi, int(rng.integers(3, 6))):
            mid = np.array([x + 0.35 * rx * np.cos(a), y + 0.35 * rx * np.sin(a), z + trunk_h + 0.4 * rz])
            mb.add(world_box(mid - [0, 0, 0.04], (0.7 * rx, 0.08, 0.08), a), bark)
        count = int(120 * 4 / 3 * np.pi * rx * rx * rz)
        leaves = random_leaves(rng, centre, (rx, rx, rz), count, rng.uniform(0.12, 0.18))
        mb.add(leaves, mats.add(LEAF, refl=float(rng.uniform(0.3, 0.5)), leafq=float(rng.uniform(0.4, 0.7))))


def _lamp(rng, mb, mats, p, side) -> None:
    mat = mats.add(STREET, refl=float(rng.uniform(0.15, 0.5)))
    h = rng.uniform(5.0, 8.0)
    mb.add(cylinder(p, h, 0.08), mat)
    arm = rng.uniform(1.0, 1.5)
    mb.add(world_box(p + [0, -side * arm / 2, h - 0.1], (0.06, arm, 0.06)), mat)
    mb.add(world_box(p + [0, -side * arm, h - 0.25], (0.25, 0.5, 0.15)), mat)


def _signpost(rng, mb, mats, p) -> None:
    mat = mats.add(STREET, refl=float(rng.uniform(0.3, 0.9)))
    h = rng.uniform(2.2, 2.8)
    mb.add(cylinder(p, h, 0.03, sections=6), mat)
    mb.add(world_box(p + [0.03, 0, h - 0.6], (0.02, 0.6, 0.6)), mat)


def _bus_shelter(rng, mb, mats, terrain, side, x) -> None:
    frame = mats.add(STREET, refl=float(rng.uniform(0.2, 0.5)))
    glass = mats.add(GLASS, cls=1, refl=0.03, p0=float(rng.uniform(0.1, 0.3)), k=float(rng.uniform(2, 5)),
                     spec=float(rng.uniform(0.05, 0.2)), pint=1.0)
    length, depth = rng.uniform(3.0, 4.0), rng.uniform(1.3, 1.5)
    y0 = terrain.road_half + 0.6
    yc = side * (y0 + depth / 2)
    z = float(terrain.z(x, yc))
    for dx in (-length / 2, length / 2):
        for dy in (0.0, depth):
            mb.add(world_box((x + dx, side * (y0 + dy), z), (0.06, 0.06, 2.4)), frame)
    mb.add(world_box((x, yc, z + 2.4), (length + 0.2, depth + 0.2, 0.08)), frame)
    mb.add(world_box((x, side * (y0 + depth - 0.3), z), (length * 0.8, 0.4, 0.45)), frame)  # bench
    yb = side * (y0 + depth)
    back = np.array([[x - length / 2, yb, z + 0.1], [x + length / 2, yb, z + 0.1], [x + length / 2, yb, z + 2.3],
                     [x - length / 2, yb, z + 2.3]])
    mb.add(np.stack([back[[0, 1, 2]], back[[0, 2, 3]]]), glass)
    for dx in (-length / 2, length / 2):
        q = np.array([[x + dx, side * (y0 + 0.2), z + 0.1], [x + dx, yb, z + 0.1], [x + dx, yb, z + 2.3],
                      [x + dx, side * (y0 + 0.2), z + 2.3]])
        mb.add(np.stack([q[[0, 1, 2]], q[[0, 2, 3]]]), glass)


# ----------------------------------------------------------------------------------------------------------------------
# Per campaign


def vehicle(rng, mb, mats, terrain, x, side, van: bool, length=None, height=None) -> tuple[float, float]:
    """A parked car or van at the curb; returns its x extent."""
    rh = terrain.road_half
    if van:
        L, W, H = length or rng.uniform(4.8, 6.0), rng.uniform(1.9, 2.05), height or rng.uniform(2.2, 2.8)
    else:
        L, W, H = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.85), rng.uniform(1.4, 1.6)
    y = side * (rh - 0.25 - W / 2)
    z = float(terrain.z(x, y))
    yaw = np.radians(rng.uniform(-2, 2))
    body = mats.add(VAN if van else CAR, refl=float(rng.uniform(0.05, 0.8)))
    dark = mats.add(VAN if van else CAR, refl=float(rng.uniform(0.03, 0.1)))
    c, s = np.cos(yaw), np.sin(yaw)
    fwd = np.array([c, s, 0.0])
    if van:
        mb.add(world_box(np.array([x, y, z + 0.35]) - fwd * 0.45, (L - 0.9, W, H - 0.35), yaw), body)
        mb.add(world_box(np.array([x, y, z + 0.35]) + fwd * (L / 2 - 0.45), (0.9, W, 0.8), yaw), body)
    else:
        mb.add(world_box((x, y, z + 0.3), (L, W, 0.7), yaw), body)
        mb.add(world_box(np.array([x, y, z + 1.0]) - fwd * 0.1 * L, (0.55 * L, W - 0.1, H - 1.0), yaw), dark)
    for ax in (-0.33, 0.33):
        for sy in (-1, 1):
            p = np.array([x, y, z]) + fwd * ax * L + np.array([-s, c, 0]) * sy * (W / 2 - 0.1)
            mb.add(world_box(p, (0.62, 0.2, 0.62), yaw), dark)
    return x - L / 2, x + L / 2


def campaign_objects(rng, terrain: Terrain, mats: Materials, strip: Strip, hide: dict | None,
                     populated: bool = True) -> MeshBuilder:
    """Parked vehicles along both curbs, pedestrians and bicycles, different per campaign (only the van of
    ``hide`` when not ``populated``)."""
    mb = MeshBuilder()
    L = terrain.length
    reserved = {1: [], -1: []}
    if hide:
        a, b = vehicle(rng, mb, mats, terrain, hide["x"], hide["side"], True, length=6.5, height=2.8)
        reserved[hide["side"]].append((a - 0.5, b + 0.5))
    if not populated:
        return mb
    for side in (1, -1):
        shelter = strip.shelter[side]  # keep the bus stop free
        x = -15.0 + rng.uniform(0, 5)
        while x < L + 15:
            van = rng.random() < 0.2
            half = 3.0 if van else 2.45
            free = not _blocked_x(terrain, side, x - half, x + half) and all(
                x + half < a or x - half > b for a, b in reserved[side] + shelter)
            if free and rng.random() < 0.7:
                a, b = vehicle(rng, mb, mats, terrain, x, side, van)
                x = b + rng.uniform(0.8, 6.0)
            else:
                x += rng.uniform(2.0, 8.0)
    for _ in range(int(rng.integers(4, 13))):
        side = int(rng.choice([1, -1]))
        off = rng.uniform(0.5, terrain.sidewalk[side] - 0.4)
        x = rng.uniform(0, L)
        _person(rng, mb, mats, terrain, x, side * (terrain.road_half + off))
    for _ in range(int(rng.integers(2, 6))):
        side = int(rng.choice([1, -1]))
        x = rng.uniform(2, L - 2)
        if strip.free(side, x - 1.0, x + 1.0) and not _blocked_x(terrain, side, x - 1, x + 1):
            _bicycle(rng, mb, mats, terrain, x, side * (terrain.road_half + 0.45))
    return mb


def _person(rng, mb, mats, terrain, x, y) -> None:
    z = float(terrain.z(x, y))
    h = rng.uniform(1.6, 1.9)
    yaw = rng.uniform(0, 2 * np.pi)
    cloth = mats.add(PERSON, refl=float(rng.uniform(0.05, 0.6)))
    mb.add(world_box((x, y, z), (0.25, 0.35, 0.47 * h), yaw), cloth)
    mb.add(world_box((x, y, z + 0.47 * h), (0.28, 0.45, 0.4 * h), yaw), cloth)
    mb.add(world_box((x, y, z + 0.87 * h), (0.2, 0.18, 0.13 * h), yaw), mats.add(PERSON, refl=0.35))


def _bicycle(rng, mb, mats, terrain, x, y) -> None:
    z = float(terrain.z(x, y))
    mat = mats.add(STREET, refl=float(rng.uniform(0.1, 0.5)))
    yaw = np.radians(rng.uniform(-10, 10))
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    for ax in (-0.52, 0.52):
        mb.add(world_box(np.array([x, y, z]) + fwd * ax, (0.66, 0.04, 0.66), yaw), mat)
    mb.add(world_box((x, y, z + 0.55), (1.0, 0.04, 0.05), yaw), mat)
    mb.add(world_box(np.array([x, y, z + 0.85]) - fwd * 0.25, (0.25, 0.1, 0.06), yaw), mat)
    mb.add(world_box(np.array([x, y, z + 0.95]) + fwd * 0.45, (0.05, 0.5, 0.04), yaw), mat)
