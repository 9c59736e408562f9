"""Where the houses stand: terraced rows and detached houses along one or both sides of the street.

A side is filled with blocks from its start: a block is a terraced row (2-5 attached houses, each its own
footprint, sharing party walls and the back line) or one detached house; blocks are separated by gaps of
1.5-12 m. One side ends at a cross street, which exposes the side wall of its last house (the corner house).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .terrain import Terrain


@dataclass
class House:
    id: int
    block: int
    side: int  # +1: north of the axis (y > 0, façade faces -y); -1: south (façade faces +y)
    x0: float
    x1: float
    y_front: float  # |y| of the street wall
    y_back: float  # |y| of the back wall
    height: float  # eave above the highest ground along the street wall
    roof: str  # "flat" | "gabled"
    pitch: float  # radians (gabled)
    overhang: float  # eave overhang (m), 0 for none
    ground_floor: float  # storey heights (m)
    storey: float
    shop: bool
    attached_lo: bool = False  # a neighbour shares the wall at x0
    attached_hi: bool = False  # ... at x1
    corner_hi: bool = False  # the wall at x1 faces a cross street
    corner_lo: bool = False
    eave_z: float = 0.0
    floor_z: float = 0.0  # ground floor level
    levels: list = field(default_factory=list)  # absolute z of the upper storeys' floors

    def corners(self) -> np.ndarray:
        """Footprint corners (4, 2), counter-clockwise, first edge = the street wall."""
        s, f, b = self.side, self.y_front, self.y_back
        if s > 0:
            return np.array([[self.x0, f], [self.x1, f], [self.x1, b], [self.x0, b]])
        return np.array([[self.x1, -f], [self.x0, -f], [self.x0, -b], [self.x1, -b]])


@dataclass
class Street:
    length: float
    houses: list
    sides: tuple
    cross: tuple | None  # (side, x0, x1)


def _split_counts(rng, n: int) -> dict:
    if n >= 2 and rng.random() < 0.7:
        left = int(np.clip(round(n * rng.uniform(0.35, 0.65)), 1, n - 1))
        return {1: left, -1: n - left}
    side = int(rng.choice([1, -1]))
    return {side: n, -side: 0}


def _blocks(rng, n: int) -> list[int]:
    """Block sizes for n houses: terraced rows of 2-5 or single detached houses."""
    out, left = [], n
    while left > 0:
        if left >= 2 and rng.random() < 0.55:
            size = int(min(left, rng.integers(2, 6)))
        else:
            size = 1
        out.append(size)
        left -= size
    return out


def _ensure_mix(rng, blocks: dict) -> None:
    """At least one terraced row and one detached house when there are 3 houses or more."""
    allb = [(s, i, b) for s in blocks for i, b in enumerate(blocks[s])]
    total = sum(b for _, _, b in allb)
    if total < 3:
        return
    if not any(b >= 2 for _, _, b in allb):  # merge two singles on the biggest side
        side = max(blocks, key=lambda s: len(blocks[s]))
        if len(blocks[side]) >= 2:
            blocks[side] = [2] + blocks[side][2:]
    allb = [b for s in blocks for b in blocks[s]]
    if not any(b == 1 for b in allb):
        side = max(blocks, key=lambda s: max(blocks[s], default=0))
        big = int(np.argmax(blocks[side]))
        blocks[side][big] -= 1
        blocks[side].append(1)


def _house_widths(rng, size: int) -> list[float]:
    if size == 1:
        return [float(rng.uniform(8.0, 14.0))]
    return [float(rng.uniform(5.0, 9.0)) for _ in range(size)]


def plan_street(rng, n_buildings: int, terrain: Terrain, length: float | None) -> Street:
    """Lay the houses out; may lengthen the street (up to 160 m) or narrow houses to fit them."""
    length = float(length) if length else float(rng.uniform(100.0, 160.0))
    counts = _split_counts(rng, n_buildings)
    blocks = {s: _blocks(rng, c) for s, c in counts.items()}
    _ensure_mix(rng, blocks)
    widths = {s: [_house_widths(rng, b) for b in blocks[s]] for s in blocks}
    gaps = {s: [float(rng.uniform(1.5, 12.0)) for _ in range(max(len(blocks[s]) - 1, 0))] for s in blocks}
    need = max(sum(map(sum, widths[s])) + sum(gaps[s]) + 10.0 for s in blocks)
    if need > length:
        length = min(160.0, need)
    for s in blocks:  # shrink when still too long
        total = sum(map(sum, widths[s])) + sum(gaps[s]) + 10.0
        if total > length:
            k = (length - 10.0 - 1.5 * len(gaps[s])) / max(sum(map(sum, widths[s])), 1e-9)
            widths[s] = [[max(4.5, w * k) for w in ws] for ws in widths[s]]
            gaps[s] = [1.5 for _ in gaps[s]]
    houses, bid, block_id = [], 1, 0
    ends = {}
    for s in (1, -1):
        if not blocks.get(s):
            continue
        total = sum(map(sum, widths[s])) + sum(gaps[s])
        x = float(rng.uniform(4.0, max(4.0, length - total - 4.0)))
        sw = terrain.sidewalk[s]
        for bi, ws in enumerate(widths[s]):
            row_front = terrain.road_half + sw
            row_back = row_front + float(rng.uniform(9.0, 13.0))
            for hi, w in enumerate(ws):
                h = _draw_house(rng, bid, block_id, s, x, x + w, row_front, row_back, len(ws) > 1)
                h.attached_lo = hi > 0
                h.attached_hi = hi < len(ws) - 1
                houses.append(h)
                bid += 1
                x += w
            block_id += 1
            if bi < len(gaps[s]):
                x += gaps[s][bi]
        ends[s] = x
    cross = _cross_street(rng, length, ends, terrain, houses)
    return Street(length, houses, tuple(sorted(blocks)), cross)


def _draw_house(rng, hid, block, side, x0, x1, row_front, row_back, terraced) -> House:
    front = row_front + (float(rng.uniform(0.0, 0.4)) if terraced else float(rng.uniform(0.0, 1.5)))
    back = row_back if terraced else front + float(rng.uniform(8.0, 13.0))
    roof = "gabled" if rng.random() < 0.55 else "flat"
    shop = bool(rng.random() < 0.3 / 0.85)  # shop fronts on 30 % of ground floors once 15 % are blank
    return House(
        id=hid, block=block, side=side, x0=x0, x1=x1, y_front=front, y_back=back,
        height=float(rng.uniform(7.0, 16.0)), roof=roof, pitch=float(np.radians(rng.uniform(30, 50))),
        overhang=float(rng.uniform(0.1, 0.5)) if rng.random() < 0.5 else 0.0,
        ground_floor=float(rng.uniform(3.8, 4.5) if shop else rng.uniform(3.0, 4.0)),
        storey=float(rng.uniform(2.8, 3.3)), shop=shop)


def _cross_street(rng, length, ends, terrain, houses) -> tuple | None:
    """A cross street 9-13 m wide just after the last house of one side (its corner house)."""
    for s in rng.permutation([1, -1]).tolist():
        if s not in ends:
            continue
        x0 = ends[s] + float(rng.uniform(2.0, 3.5))
        x1 = x0 + float(rng.uniform(9.0, 13.0))
        if x1 <= length - 2.0:
            last = max((h for h in houses if h.side == s), key=lambda h: h.x1)
            last.corner_hi = True
            terrain.cross = (s, x0, x1)
            return (s, x0, x1)
    return None


def finish_heights(street: Street, terrain: Terrain, rng) -> None:
    """Eave heights and storey levels from the ground along each street wall."""
    for h in street.houses:
        c = h.corners()
        s = np.linspace(0, 1, 25)[:, None]
        pts = c[0] + s * (c[1] - c[0])
        zg = terrain.z(pts[:, 0], pts[:, 1])
        h.eave_z = float(zg.max() + h.height)
        h.floor_z = float(zg.max() + rng.uniform(0.0, 0.1))
        top = h.eave_z - 0.45
        levels, z = [], h.floor_z + h.ground_floor
        while z + 0.8 + 1.0 <= top:  # an upper storey only where a 1 m window fits under the eave
            levels.append(float(z))
            z += h.storey
        h.levels = levels
