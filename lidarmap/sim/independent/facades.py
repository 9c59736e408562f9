"""Walls of the houses: their frames, what openings they get, and their triangles.

Every house has four walls (from its counter-clockwise footprint). Street walls and exposed side walls (ends of
rows, detached houses, the corner house) are the façades listed in the truth; party walls and back walls are
plain geometry. Street walls get a storey grid of windows (jittered, some missing, some arched), a ground floor
that is a shop front, an ordinary entrance floor or blank; exposed side walls are mostly blank.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from .geometry import WALL, Frame, Materials, MeshBuilder, facade_polygon, frame_from
from .layout import House
from .openings import GLAZING_P, GLAZINGS, Opening, build_door, build_window, draw_door_leaf, draw_glass, window_look
from .terrain import Terrain

MARGIN = 0.7  # openings keep this far from the wall's ends (pilasters, drainpipes, party walls)
GAP = 0.6  # and this far from each other


@dataclass
class Facade:
    house: House
    role: str  # front | back | lo | hi  (the walls at x0 / x1 are lo / hi)
    frame: Frame
    width: float
    height: float  # eave above the origin (lowest ground along the base)
    tb: float  # the wall starts this far below the origin (under the ground)
    gable: float  # gable rise above the eave at mid-width (0: none)
    listed: bool
    street_facing: bool
    corner: bool = False
    openings: list = field(default_factory=list)
    structures: list = field(default_factory=list)
    style: dict = field(default_factory=dict)
    id: int = -1
    terrain: Terrain | None = None

    def ground_t(self, s):
        """Ground height (t) at the wall base at s (the reference plane)."""
        s = np.asarray(s, float)
        p = self.frame.o[:2] + s[..., None] * self.frame.u[:2]
        return self.terrain.z(p[..., 0], p[..., 1]) - self.frame.o[2]

    def ground_max(self, s0: float, s1: float) -> float:
        return float(np.max(self.ground_t(np.linspace(s0, s1, 9))))


def house_walls(h: House, terrain: Terrain, rng) -> list[Facade]:
    """The four walls of a house, with their frames; which are listed façades."""
    c = h.corners()
    roles = ["front", "hi", "back", "lo"] if h.side > 0 else ["front", "lo", "back", "hi"]
    out = []
    for i, role in enumerate(roles):
        a, b = c[i], c[(i + 1) % 4]
        width = float(np.linalg.norm(b - a))
        s = np.linspace(0, 1, 41)[:, None]
        base = a + s * (b - a)
        zg = terrain.z(base[:, 0], base[:, 1])
        oz = float(zg.min())
        attached = (role == "lo" and h.attached_lo) or (role == "hi" and h.attached_hi)
        listed = role == "front" or (role in ("lo", "hi") and not attached)
        lean = float(np.radians(rng.uniform(-0.3, 0.3))) if listed else 0.0
        height = h.eave_z - oz
        gable = width / 2 * np.tan(h.pitch) if (h.roof == "gabled" and role in ("lo", "hi")) else 0.0
        fr = frame_from(a, b, oz, height, lean)
        corner = (role == "hi" and h.corner_hi) or (role == "lo" and h.corner_lo)
        out.append(Facade(h, role, fr, width, height, -0.4, gable, listed,
                          role == "front", corner, terrain=terrain))
    return out


# ----------------------------------------------------------------------------------------------------------------------
# Planning the openings


def _style(rng) -> dict:
    return {"sills": bool(rng.random() < 0.5), "reveal": float(rng.uniform(0.08, 0.35)),
            "frame_w": float(rng.uniform(0.04, 0.08)), "bar_w": float(rng.uniform(0.05, 0.08)),
            "arched": bool(rng.random() < 0.2), "wall_refl": float(rng.choice(
                [rng.uniform(0.45, 0.75), rng.uniform(0.22, 0.4)]))}


def _window(rng, st: dict, rect, subtype="window", arch=0.0, storey=0) -> Opening:
    op = Opening("window", subtype, tuple(map(float, rect)), "", 0.0, arch_rise=float(arch), storey=storey)
    op.reveal = float(np.clip(st["reveal"] + rng.uniform(-0.02, 0.02), 0.08, 0.35))
    op.frame_w = st["frame_w"]
    op.bar_w = st["bar_w"]
    op.glass_set = float(rng.uniform(0.02, 0.04))
    if subtype == "shop_window":
        op.frame_w = float(rng.uniform(0.06, 0.1))
        op.bars = (int(rng.integers(1, 4)), 1) if rng.random() < 0.3 else (1, 1)
        glazing = str(rng.choice(["lit_room", "dark_room", "reflective"], p=[0.6, 0.2, 0.2]))
    else:
        if rng.random() < 0.6:
            op.bars = [(2, 1), (1, 2), (2, 2), (3, 1), (3, 2), (2, 3)][int(rng.integers(6))]
        op.sill = st["sills"]
        op.sill_proud = float(rng.uniform(0.03, 0.06))
        glazing = str(rng.choice(GLAZINGS, p=GLAZING_P))
    draw_glass(rng, op, glazing)
    return op


def _place_row(rng, width: float, widths: list[float]) -> list[float] | None:
    """Left edges for elements of the given widths, kept MARGIN from the ends and GAP apart; None if too wide."""
    need = sum(widths) + GAP * (len(widths) - 1)
    avail = width - 2 * MARGIN
    if not widths or need > avail:
        return None
    parts = rng.dirichlet(np.ones(len(widths) + 1)) * (avail - need)
    out, s = [], MARGIN + parts[0]
    for i, w in enumerate(widths):
        out.append(float(s))
        s += w + GAP + parts[i + 1]
    return out


def _ground_elements(rng, fac: Facade) -> list[tuple[str, float]]:
    h = fac.house
    if h.shop:
        count = 2 if fac.width > 9 and rng.random() < 0.5 else 1
        elems = [("shop_window", float(rng.uniform(2.0, 5.0))) for _ in range(count)]
        elems.append(("shop_door", float(rng.uniform(0.9, 1.2))))
    else:
        double = rng.random() < 0.3
        width = rng.uniform(1.6, 2.2) if double else rng.uniform(0.9, 1.3)
        elems = [("double_door" if double else "door", float(width))]
        if fac.width >= 6 and rng.random() < 0.2:
            elems.append(("garage", float(rng.uniform(2.4, 3.0))))
        elems += [("window", float(rng.uniform(0.6, 1.6))) for _ in range(int(rng.integers(1, 4)))]
    while elems and _place_row(rng, fac.width, [w for _, w in elems]) is None:
        shops = [i for i, (k, w) in enumerate(elems) if k == "shop_window" and w > 2.05]
        wins = [i for i, (k, _) in enumerate(elems) if k in ("window", "garage")]
        if shops:
            i = shops[0]
            elems[i] = ("shop_window", max(2.0, elems[i][1] - 0.5))
        elif wins:
            elems.pop(wins[-1])
        else:
            elems.pop()
    return [elems[i] for i in rng.permutation(len(elems))]


def _plan_ground_floor(rng, fac: Facade, st: dict) -> list[Opening]:
    h, oz = fac.house, fac.frame.o[2]
    gf_top = h.floor_z + h.ground_floor - oz
    elems = _ground_elements(rng, fac)
    lefts = _place_row(rng, fac.width, [w for _, w in elems]) or []
    out = []
    for (kind, w), s0 in zip(elems, lefts):
        s1 = s0 + w
        g = fac.ground_max(s0, s1)
        if kind == "shop_window":
            t0 = g + rng.uniform(0.2, 0.6)
            t1 = min(gf_top - 0.65, t0 + 3.2)
            if t1 - t0 >= 1.5:
                out.append(_window(rng, st, (s0, s1, t0, t1), "shop_window"))
        elif kind == "window":
            t0 = g + rng.uniform(0.1, 1.3)
            t1 = min(t0 + rng.uniform(0.8, 2.2), gf_top - 0.35)
            if t1 - t0 >= 0.8:
                out.append(_window(rng, st, (s0, s1, t0, t1)))
        else:
            out.append(_door(rng, kind, s0, s1, g, gf_top))
    return out


def _door(rng, kind: str, s0: float, s1: float, g: float, gf_top: float) -> Opening:
    sub = {"shop_door": "door", "door": "door", "double_door": "double_door", "garage": "garage"}[kind]
    op = Opening("door", sub, (0, 0, 0, 0), "", 0.0)
    op.glazed_panel = kind == "shop_door" or (sub != "garage" and rng.random() < 0.4)
    rise = 0.0
    if sub in ("door", "double_door") and kind != "shop_door" and rng.random() < 0.3:
        rise = float(rng.uniform(0.15, 0.5))
        op.steps = int(np.clip(np.ceil(rise / 0.17), 1, 3))
        op.step_rise = rise / op.steps
    low, high = {"door": (2.0, 2.35), "double_door": (2.1, 2.5), "garage": (2.0, 2.4)}[sub]
    height = rng.uniform(low, high)
    t0 = g + rise
    t1 = min(t0 + height, gf_top - 0.3)
    op.rect = (float(s0), float(s1), float(t0), float(t1))
    draw_door_leaf(rng, op)
    return op


def _plan_upper(rng, fac: Facade, st: dict, max_cols: int = 99) -> list[Opening]:
    h, oz, W = fac.house, fac.frame.o[2], fac.width
    ncol = min(max_cols, max(1, int(round((W - 2 * MARGIN) / rng.uniform(2.2, 3.8)))))
    while ncol > 1 and (W - 2 * MARGIN) / ncol < 1.3:
        ncol -= 1
    slot = (W - 2 * MARGIN) / ncol
    wmax = min(2.0, slot - GAP)
    if wmax < 0.5:
        return []
    wbase = rng.uniform(0.5, wmax) if rng.random() < 0.3 else rng.uniform(min(0.8, wmax), min(1.5, wmax))
    out = []
    for k, level in enumerate(h.levels):
        lv = level - oz
        t0 = lv + rng.uniform(0.75, 1.0)
        t1 = min(t0 + rng.uniform(1.1, 2.0), lv + h.storey - 0.35, fac.height - 0.45)
        if t1 - t0 < 0.8:
            continue
        missing = int(rng.integers(ncol)) if ncol >= 2 and rng.random() < 0.3 else -1
        for c in range(ncol):
            if c == missing:
                continue
            w = float(np.clip(wbase * rng.uniform(0.95, 1.05), 0.5, slot - GAP))
            centre = MARGIN + (c + 0.5) * slot + rng.uniform(-0.12, 0.12)
            s0 = float(np.clip(centre - w / 2, MARGIN, W - MARGIN - w))
            arch = 0.0
            if st["arched"]:
                arch = w / 2 if rng.random() < 0.5 else w * rng.uniform(0.15, 0.25)
                if (t1 - t0) - arch < 0.5:
                    arch = 0.0
            out.append(_window(rng, st, (s0, s0 + w, t0, t1), "arched" if arch else "window", arch, k + 1))
    return out


def plan_front(rng, fac: Facade) -> None:
    st = fac.style = _style(rng)
    fac.style["blank_ground"] = bool(rng.random() < 0.15)  # garages, shops' closed walls
    ops = [] if fac.style["blank_ground"] else _plan_ground_floor(rng, fac, st)
    fac.openings = ops + _plan_upper(rng, fac, st)


def plan_side(rng, fac: Facade) -> None:
    """Exposed side walls: blank, or (corner houses mostly) a column or two of windows."""
    st = fac.style = _style(rng)
    if rng.random() > (0.7 if fac.corner else 0.25):
        return
    ops = _plan_upper(rng, fac, st, max_cols=2 if not fac.corner else 4)
    if fac.corner and fac.house.levels:
        gf_top = fac.house.floor_z + fac.house.ground_floor - fac.frame.o[2]
        n = int(rng.integers(1, 3))
        widths = [float(rng.uniform(0.6, 1.5)) for _ in range(n)]
        for s0, w in zip(_place_row(rng, fac.width, widths) or [], widths):
            t0 = fac.ground_max(s0, s0 + w) + rng.uniform(0.6, 1.3)
            t1 = min(t0 + rng.uniform(0.8, 1.8), gf_top - 0.35)
            if t1 - t0 >= 0.8:
                ops.append(_window(rng, st, (s0, s0 + w, t0, t1)))
    fac.openings = ops


# ----------------------------------------------------------------------------------------------------------------------
# Geometry


def wall_material(rng, mats: Materials, fac: Facade) -> int:
    """Wall reflectance and relief (0.5-1.5 cm); 25 % of street walls have rusticated ground floors."""
    refl = fac.style.get("wall_refl", 0.5)
    kw = {"refl": refl, "relief": float(rng.uniform(0.005, 0.015)) if fac.listed else 0.008}
    if fac.street_facing and rng.random() < 0.25:
        kw.update(rust_period=float(rng.uniform(0.3, 0.45)), rust_groove=float(rng.uniform(0.02, 0.04)),
                  rust_depth=float(rng.uniform(0.02, 0.04)), rust_z0=float(fac.frame.o[2]),
                  rust_ztop=float(fac.house.floor_z + fac.house.ground_floor - 0.1))
        fac.style["rustication"] = True
    return mats.add(WALL, **kw)


def wall_polygon(fac: Facade) -> Polygon:
    """The wall's outline in (s, t), gable included, minus the openings' holes."""
    W, H = fac.width, fac.height
    outer = box(0.0, fac.tb, W, H)
    if fac.gable > 0:
        outer = outer.union(Polygon([(0, H), (W, H), (W / 2, H + fac.gable)]))
    holes = [op.outline() for op in fac.openings]
    return outer.difference(unary_union(holes)) if holes else outer


def build_facade(rng, mb: MeshBuilder, mats: Materials, fac: Facade) -> None:
    """Wall with holes, and each opening's construction."""
    if not fac.style:
        fac.style = _style(rng)
    wall = wall_material(rng, mats, fac)
    mb.add(facade_polygon(fac.frame, wall_polygon(fac), 0.0), wall)
    look = window_look(rng, mats, fac.style["wall_refl"])
    for op in fac.openings:
        if op.kind == "window":
            build_window(mb, mats, fac.frame, op, look)
        else:
            build_door(mb, mats, fac.frame, op, look, fac.ground_t)
