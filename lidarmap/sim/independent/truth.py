"""truth.json: campaigns, buildings, façades and openings in the scene CRS, with observation shares."""

from __future__ import annotations

import numpy as np

from .observe import CELL, WALL_CELL, ObsFacade, opening_fraction, wall_mask
from .scanners import drift
from .scene import World


def _r(x, nd=4):
    return [round(float(v), nd) for v in np.ravel(x)]


def observation_keys(n: int) -> list[tuple[str, list[int]]]:
    """("1", [1]) ... ("n", [n]) and ("1-2", [1, 2]) ... ("1-n", [1..n])."""
    keys = [(str(i), [i]) for i in range(1, n + 1)]
    keys += [(f"1-{k}", list(range(1, k + 1))) for k in range(2, n + 1)]
    return keys


def _union(grids: dict, ids: list[int], f_index: int, which: int) -> np.ndarray:
    return np.logical_or.reduce([grids[c][f_index][which] for c in ids])


def campaign_entry(world: World, camp, count: int) -> dict:
    m = camp.motion
    span = np.arange(np.floor(-0.5), np.ceil(m.t_fire + 0.5) + 1e-9, 1.0)
    d = drift(camp.drift, span)
    stop = [round(camp.t0 + m.stop[0], 3), round(camp.t0 + m.stop[1], 3)]
    return {"id": camp.id, "points": f"mls_{camp.id}.laz", "trajectory": f"trajectory_{camp.id}.csv",
            "scanner": camp.kind, "lane_offset": round(camp.lane_offset, 3),
            "direction": "forward" if camp.direction > 0 else "backward", "speed": round(camp.speed, 3),
            "stop": stop, "classified": camp.classified,
            "gnss_drift": {"horizontal": round(camp.drift["horizontal"], 4),
                           "vertical": round(camp.drift["vertical"], 4),
                           "samples": [[round(camp.t0 + t, 3), *_r(v, 4)] for t, v in zip(span, d)]},
            "points_count": int(count)}


def facade_entry(world: World, f, grids: dict, keys) -> dict:
    fi = world.facades.index(f)
    s = np.unique(np.concatenate([np.arange(0.0, f.width, 0.25), [f.width]]))
    line = [[float(a), float(b)] for a, b in zip(s, f.ground_t(s))]
    for op in f.openings:  # a door's threshold replaces the ground across its width
        if op.kind == "door":
            s0, s1, t0, _ = op.rect
            line = [p for p in line if not s0 <= p[0] <= s1]
            line += [[s0, float(f.ground_t(s0))], [s0, t0], [s1, t0], [s1, float(f.ground_t(s1))]]
    line.sort(key=lambda p: p[0])
    mask = wall_mask(_obs(f), [op.rect for op in f.openings], f.ground_t)
    area = {k: round(float((_union(grids, ids, fi, 1) & mask).sum()) * WALL_CELL ** 2, 3) for k, ids in keys}
    return {"id": f.id, "building_id": f.house.id, "origin": _r(world.to_crs(f.frame.o)),
            "u": _r(world.vec_to_crs(f.frame.u), 7), "normal": _r(world.vec_to_crs(f.frame.n), 7),
            "width": round(f.width, 4), "height": round(f.height, 4), "street_facing": f.street_facing,
            "blank": not f.openings, "ground_line": [[round(a, 4), round(b, 4)] for a, b in line],
            "observed_wall_area": area}


def _obs(f) -> ObsFacade:
    return ObsFacade(f.id, f.frame.o, f.frame.u, f.frame.n, f.width, f.height, f.style.get("wall_refl", 0.5))


def opening_entry(world: World, op, grids: dict, keys) -> dict:
    f = next(x for x in world.facades if x.id == op.facade_id)
    fi = world.facades.index(f)
    s0, s1, t0, t1 = op.rect
    st = np.array([[s0, t0], [s1, t0], [s1, t1], [s0, t1]])
    local = f.frame.o + st[:, :1] * f.frame.u + st[:, 1:] * np.array([0.0, 0.0, 1.0])
    corners = world.to_crs(local)
    cols, rows = op.bars
    return {"id": op.id, "facade_id": op.facade_id, "kind": op.kind, "subtype": op.subtype,
            "rect": _r(op.rect), "corners": [_r(c) for c in corners],
            "depth_of_returns": round(op.depth_of_returns(), 4), "glazing": op.glazing,
            "mullions": int((cols - 1) + (rows - 1)), "sill_protrudes": bool(op.sill), "steps": int(op.steps),
            "observed": {k: round(opening_fraction(_union(grids, ids, fi, 0), op.rect), 4) for k, ids in keys}}


def truth_document(world: World, camps: list, counts: dict, grids: dict, cad: dict) -> dict:
    keys = observation_keys(len(camps))
    buildings = []
    for h in world.street.houses:
        c = cad[h.id]
        buildings.append({"id": h.id, "footprint_true": [_r(p[:2]) for p in world.to_crs(
            np.column_stack([c["true"], np.zeros(4)]))], "footprint_offset": _r(world.vec_to_crs(
                np.append(c["offset"], 0.0))[:2]), "footprint_rotation_deg": round(c["rotation_deg"], 5)})
    return {"format": "lidarmap-independent-truth", "version": 1, "seed": int(world.seed),
            "crs": f"EPSG:{world.epsg}", "observation_cell": CELL,
            "campaigns": [campaign_entry(world, c, counts[c.id]) for c in camps],
            "buildings": buildings,
            "facades": [facade_entry(world, f, grids, keys) for f in world.facades],
            "openings": [opening_entry(world, op, grids, keys) for op in world.openings]}
