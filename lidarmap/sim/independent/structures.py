"""Things built on a street façade that are not openings but occlude or mimic them.

Cornices (under the eave, between storeys), pilasters, drainpipes, balconies (solid parapet or see-through
railings), oriels (bay windows) on the upper storeys, shop signs, awnings and window boxes with plants. Planning
marks the openings they stand in front of (``clear = False``) and removes windows an oriel covers.
"""

from __future__ import annotations

import numpy as np
from shapely.geometry import box

from .facades import MARGIN, Facade
from .geometry import GLASS, LEAF, PART, RAILING, Materials, MeshBuilder, facade_box, facade_polygon


def _overlap(a0, a1, b0, b1) -> bool:
    return min(a1, b1) - max(a0, b0) > 0


def plan_structures(rng, fac: Facade) -> None:
    """Decide the structures of a street façade (stored in ``fac.structures``)."""
    h, W, H = fac.house, fac.width, fac.height
    levels = [lv - fac.frame.o[2] for lv in h.levels]
    out = fac.structures
    if rng.random() < 0.45:
        out.append({"kind": "cornice", "t0": H - rng.uniform(0.2, 0.4), "t1": H, "proud": rng.uniform(0.15, 0.4)})
    if levels and rng.random() < 0.3:
        proud = rng.uniform(0.06, 0.2)
        out += [{"kind": "cornice", "t0": lv - 0.08, "t1": lv + 0.08, "proud": proud} for lv in levels]
    pil = 0.0, 0.0
    if rng.random() < 0.2:
        pil = rng.uniform(0.3, 0.45), rng.uniform(0.05, 0.1)
        out.append({"kind": "pilasters", "w": pil[0], "proud": pil[1]})
    if rng.random() < 0.5:
        s = pil[0] + rng.uniform(0.12, 0.2)
        out.append({"kind": "drainpipe", "s": s if rng.random() < 0.5 else W - s, "d0": pil[1] + 0.03})
    oriel = _plan_oriel(rng, fac, levels)
    _plan_balconies(rng, fac, levels, oriel)
    _plan_shop_front(rng, fac)
    if rng.random() < 0.2:
        for op in fac.openings:
            if op.kind == "window" and op.storey > 0 and op.clear and rng.random() < 0.5:
                op.clear = False
                out.append({"kind": "planter", "rect": op.rect, "sill": op.sill_proud if op.sill else 0.0})


def _plan_oriel(rng, fac: Facade, levels: list) -> tuple | None:
    if len(levels) < 2 or fac.width < 6 or rng.random() >= 0.15:
        return None
    ups = [op for op in fac.openings if op.storey == 1]
    if not ups:
        return None
    centre = float(np.mean(ups[int(rng.integers(len(ups)))].rect[:2]))
    half = rng.uniform(2.0, 3.2) / 2
    a, b = max(MARGIN, centre - half), min(fac.width - MARGIN, centre + half)
    top = min(fac.height - 0.5, levels[-1] + fac.house.storey - 0.2)
    fac.openings = [op for op in fac.openings
                    if op.storey == 0 or not _overlap(op.rect[0], op.rect[1], a - 0.2, b + 0.2)]
    fac.structures.append({"kind": "oriel", "s0": a, "s1": b, "t0": levels[0], "t1": top,
                           "proud": rng.uniform(0.5, 0.9), "levels": levels})
    return a, b


def _plan_balconies(rng, fac: Facade, levels: list, oriel) -> None:
    if not levels or rng.random() >= 0.25:
        return
    ups = [op for op in fac.openings if op.storey > 0]
    if not ups:
        return
    centres = []  # one per window column (window centres jitter from storey to storey)
    for c in sorted(float(np.mean(op.rect[:2])) for op in ups):
        if not centres or c - centres[-1] > 0.6:
            centres.append(c)
    cols = rng.choice(centres, size=min(len(centres), int(rng.integers(1, 3))), replace=False)
    storeys = [k + 1 for k in range(len(levels)) if rng.random() < 0.6] or [1]
    railing = bool(rng.random() < 0.6)
    depth = rng.uniform(1.0, 1.5)
    for c in cols:
        for k in storeys:
            win = [op for op in ups if op.storey == k and abs(np.mean(op.rect[:2]) - c) < 0.5]
            if not win:
                continue
            ext = rng.uniform(0.5, 1.0)
            a, b = max(0.3, win[0].rect[0] - ext), min(fac.width - 0.3, win[0].rect[1] + ext)
            if oriel and _overlap(a, b, oriel[0] - 0.1, oriel[1] + 0.1):
                continue
            if any(st["kind"] == "balcony" and st["level"] == levels[k - 1]
                   and _overlap(a, b, st["s0"] - 0.2, st["s1"] + 0.2) for st in fac.structures):
                continue  # no two balconies run into each other
            for op in fac.openings:  # the window behind and the one below the slab are partly hidden
                if op.storey in (k, k - 1) and _overlap(op.rect[0], op.rect[1], a, b):
                    op.clear = False
            fac.structures.append({"kind": "balcony", "s0": a, "s1": b, "level": levels[k - 1],
                                   "depth": depth, "railing": railing})


def _plan_shop_front(rng, fac: Facade) -> None:
    gf_top = fac.house.floor_z + fac.house.ground_floor - fac.frame.o[2]
    for op in fac.openings:
        if op.subtype != "shop_window":
            continue
        s0, s1, t0, t1 = op.rect
        if rng.random() < 0.7 and t1 + 0.5 <= gf_top - 0.1:
            fac.structures.append({"kind": "sign", "rect": (s0, s1, t1 + 0.12, t1 + 0.5)})
        if rng.random() < 0.4:
            depth = rng.uniform(1.2, 1.8)
            drop = 0.45 * depth
            ground = fac.ground_max(s0 - 0.1, s1 + 0.1)
            if t1 + 0.06 - drop - 0.25 >= ground + 2.2:
                op.clear = False
                fac.structures.append({"kind": "awning", "s0": s0 - 0.1, "s1": s1 + 0.1, "t": t1 + 0.06,
                                       "depth": depth, "drop": drop})


# ----------------------------------------------------------------------------------------------------------------------


def build_structures(rng, mb: MeshBuilder, mats: Materials, fac: Facade) -> None:
    fr, W, H = fac.frame, fac.width, fac.height
    part = mats.add(PART, refl=fac.style.get("wall_refl", 0.5) * 0.95, relief=0.005)
    for st in fac.structures:
        kind = st["kind"]
        if kind == "cornice":
            mb.add(facade_box(fr, 0.0, W, st["t0"], st["t1"], 0.0, st["proud"]), part)
        elif kind == "pilasters":
            mb.add(facade_box(fr, 0.0, st["w"], fac.tb, H, 0.0, st["proud"]), part)
            mb.add(facade_box(fr, W - st["w"], W, fac.tb, H, 0.0, st["proud"]), part)
        elif kind == "drainpipe":
            pipe = mats.add(PART, refl=float(rng.uniform(0.2, 0.6)))
            mb.add(facade_box(fr, st["s"] - 0.05, st["s"] + 0.05, fac.tb, H - 0.1, st["d0"], st["d0"] + 0.1), pipe)
        elif kind == "balcony":
            _build_balcony(rng, mb, mats, fac, st, part)
        elif kind == "oriel":
            _build_oriel(rng, mb, mats, fac, st, part)
        elif kind == "sign":
            s0, s1, t0, t1 = st["rect"]
            mb.add(facade_box(fr, s0, s1, t0, t1, 0.0, 0.08), mats.add(PART, refl=float(rng.uniform(0.1, 0.9))))
        elif kind == "awning":
            _build_awning(rng, mb, mats, fac, st)
        elif kind == "planter":
            _build_planter(rng, mb, mats, fac, st)


def _build_balcony(rng, mb, mats, fac, st, part) -> None:
    fr, a, b, lv, dep = fac.frame, st["s0"], st["s1"], st["level"], st["depth"]
    mb.add(facade_box(fr, a, b, lv - 0.18, lv, 0.0, dep), part)
    if not st["railing"]:
        mb.add(facade_box(fr, a, b, lv, lv + 1.0, dep - 0.1, dep), part)
        mb.add(facade_box(fr, a, a + 0.1, lv, lv + 1.0, 0.0, dep - 0.1), part)
        mb.add(facade_box(fr, b - 0.1, b, lv, lv + 1.0, 0.0, dep - 0.1), part)
        return
    rail = mats.add(RAILING, refl=float(rng.uniform(0.1, 0.5)))
    top = lv + 0.95
    mb.add(facade_box(fr, a, b, top, top + 0.05, dep - 0.05, dep), rail)
    mb.add(facade_box(fr, a, a + 0.05, top, top + 0.05, 0.0, dep), rail)
    mb.add(facade_box(fr, b - 0.05, b, top, top + 0.05, 0.0, dep), rail)
    for s in np.arange(a + 0.06, b - 0.03, 0.12):  # vertical bars 2 cm wide every 12 cm: see-through
        mb.add(facade_box(fr, s - 0.01, s + 0.01, lv, top, dep - 0.035, dep - 0.015), rail)
    for d in np.arange(0.1, dep - 0.05, 0.12):
        mb.add(facade_box(fr, a + 0.015, a + 0.035, lv, top, d - 0.01, d + 0.01), rail)
        mb.add(facade_box(fr, b - 0.035, b - 0.015, lv, top, d - 0.01, d + 0.01), rail)


def _build_oriel(rng, mb, mats, fac, st, part) -> None:
    fr, a, b, dep = fac.frame, st["s0"], st["s1"], st["proud"]
    mb.add(facade_box(fr, a, b, st["t0"], st["t1"], 0.0, dep), part)
    glass = mats.add(GLASS, refl=0.03, p0=float(rng.uniform(0.05, 0.4)), k=float(rng.uniform(2, 8)),
                     spec=float(rng.uniform(0.0, 0.2)), pint=0.4)
    for lv in st["levels"]:
        t0, t1 = lv + 0.9, min(lv + 2.1, st["t1"] - 0.2)
        if t1 - t0 > 0.5 and b - a > 0.8:
            mb.add(facade_polygon(fr, box(a + 0.3, t0, b - 0.3, t1), dep + 0.01), glass)


def _build_awning(rng, mb, mats, fac, st) -> None:
    fr, s0, s1, t, dep, drop = fac.frame, st["s0"], st["s1"], st["t"], st["depth"], st["drop"]
    cloth = mats.add(PART, refl=float(rng.uniform(0.2, 0.7)))
    S = np.array([s0, s1, s1, s0])
    slope = fr.xyz(S, np.array([t, t, t - drop, t - drop]), np.array([0.0, 0.0, dep, dep]))
    front = fr.xyz(S, np.array([t - drop - 0.25, t - drop - 0.25, t - drop, t - drop]), np.full(4, dep))
    for q in (slope, front):
        mb.add(np.stack([q[[0, 1, 2]], q[[0, 2, 3]]]), cloth)
    for s in (s0, s1):
        side = fr.xyz(np.full(3, s), np.array([t, t - drop, t - drop - 0.25]), np.array([0.0, dep, dep]))
        mb.add(side[None], cloth)


def _build_planter(rng, mb, mats, fac, st) -> None:
    fr = fac.frame
    s0, s1, t0, _ = st["rect"]
    d0 = st["sill"] + 0.01
    mb.add(facade_box(fr, s0 + 0.05, s1 - 0.05, t0 - 0.25, t0 - 0.07, d0, d0 + 0.2),
           mats.add(PART, refl=float(rng.uniform(0.2, 0.6))))
    n = int(60 * (s1 - s0))
    c = fr.xyz(rng.uniform(s0 + 0.05, s1 - 0.05, n), rng.uniform(t0 - 0.07, t0 + 0.3, n),
               rng.uniform(d0 + 0.02, d0 + 0.2, n))
    off = rng.normal(scale=0.05, size=(n, 3, 3))
    mb.add(c[:, None, :] + off, mats.add(LEAF, refl=float(rng.uniform(0.3, 0.5)), leafq=float(rng.uniform(0.4, 0.7))))
