"""Windows and doors: their parameters and the triangles that make them.

All geometry is in façade coordinates (s, t, d): the opening is a hole in the wall plane d = 0 (its truth
rectangle ``rect``); the reveal runs from d = 0 back to the frame or leaf; glass, curtains and leaves lie behind.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from shapely.geometry import Polygon, box

from .geometry import (CURTAIN, DOOR, FRAME, GLASS, PART, REVEAL, Frame, Materials, MeshBuilder, facade_box,
                       facade_polygon, outline_band, ring_of)


@dataclass
class Opening:
    kind: str  # "window" | "door"
    subtype: str  # window | shop_window | arched | door | double_door | garage
    rect: tuple  # (s0, s1, t0, t1)
    glazing: str
    reveal: float  # depth of the frame face / door leaf behind the wall plane (m)
    frame_w: float = 0.06
    glass_set: float = 0.03  # glass behind the frame face
    arch_rise: float = 0.0
    bars: tuple = (1, 1)  # panes: columns, rows
    bar_w: float = 0.06
    sill: bool = False
    sill_proud: float = 0.0
    curtain_gap: float = 0.0  # curtain / blind behind the glass
    blind_frac: float = 0.0  # share of the height covered by a half-closed blind (from the top)
    glazed_panel: bool = False
    steps: int = 0
    step_rise: float = 0.0
    p0: float = 0.2
    k: float = 4.0
    spec: float = 0.0
    pint: float = 0.5
    storey: int = 0
    clear: bool = True  # nothing built in front of it (balcony, oriel, awning, planter)
    id: int = -1
    facade_id: int = -1

    @property
    def width(self) -> float:
        return self.rect[1] - self.rect[0]

    def outline(self) -> Polygon:
        """The hole in the wall: the rectangle, or the rectangle with an arched (round or segmental) top."""
        s0, s1, t0, t1 = self.rect
        if self.arch_rise <= 0:
            return box(s0, t0, s1, t1)
        w, a = s1 - s0, self.arch_rise
        half, spring = w / 2, t1 - a
        radius = (a * a + half * half) / (2 * a)
        centre = t1 - radius
        phi = np.arcsin(np.clip(half / radius, -1, 1))
        ang = np.linspace(np.pi / 2 - phi, np.pi / 2 + phi, 13)
        arc = np.stack([(s0 + s1) / 2 + radius * np.cos(ang), centre + radius * np.sin(ang)], 1)
        arc[0], arc[-1] = (s1, spring), (s0, spring)
        return Polygon(np.vstack([[[s0, t0], [s1, t0]], arc]))

    def depth_of_returns(self) -> float:
        """Where most returns through the opening come from (negative: behind the wall plane)."""
        if self.kind == "door":
            return -self.reveal
        if self.glazing in ("curtain", "half_blind"):
            return -(self.reveal + self.glass_set + self.curtain_gap)
        return -(self.reveal + self.glass_set)

    def arch_top(self, s: float) -> float:
        """Top of the hole at s (the arch, or t1)."""
        s0, s1, _, t1 = self.rect
        if self.arch_rise <= 0:
            return t1
        half, a = (s1 - s0) / 2, self.arch_rise
        radius = (a * a + half * half) / (2 * a)
        dx = s - (s0 + s1) / 2
        return (t1 - radius) + np.sqrt(max(radius * radius - dx * dx, 0.0))


GLAZINGS = ("curtain", "dark_room", "lit_room", "half_blind", "reflective")
GLAZING_P = (0.40, 0.20, 0.15, 0.15, 0.10)


def draw_glass(rng, op: Opening, glazing: str) -> None:
    """Glass behaviour of one opening: return probability p0 cos^k, mirror share, what is behind it."""
    op.glazing = glazing
    op.p0 = float(rng.uniform(0.05, 0.5))
    op.k = float(rng.uniform(2.0, 8.0))
    op.spec = float(rng.uniform(0.05, 0.3)) if rng.random() < 0.3 else 0.0
    op.pint = {"dark_room": rng.uniform(0.02, 0.10), "lit_room": rng.uniform(0.6, 0.9),
               "reflective": rng.uniform(0.03, 0.15), "curtain": rng.uniform(0.1, 0.4),
               "half_blind": rng.uniform(0.1, 0.5), "glazed_door": rng.uniform(0.05, 0.2)}.get(glazing, 0.3)
    if glazing == "reflective":
        op.spec = float(rng.uniform(0.3, 0.6))
        op.p0 = float(rng.uniform(0.05, 0.2))
    if glazing in ("curtain", "half_blind"):
        op.curtain_gap = float(rng.uniform(0.05, 0.15))
    if glazing == "half_blind":
        op.blind_frac = float(rng.uniform(0.3, 0.7))


def glass_material(mats: Materials, op: Opening) -> int:
    return mats.add(GLASS, refl=0.03, p0=op.p0, k=op.k, spec=op.spec, pint=op.pint, opening=op.id)


def build_window(mb: MeshBuilder, mats: Materials, fr: Frame, op: Opening, look: dict) -> None:
    """Reveal, frame, mullions/transoms, glass, curtain or blind, stone sill."""
    outline = op.outline()
    r, g = op.reveal, op.glass_set
    mb.add(outline_band(fr, ring_of(outline), 0.0, -r), look["reveal"])
    inner = outline.buffer(-op.frame_w, join_style="mitre")
    mb.add(facade_polygon(fr, outline.difference(inner), -r), look["frame"])
    mb.add(outline_band(fr, ring_of(inner), -r, -r - g), look["frame"])
    for bar in _bars(op, inner):
        mb.add(facade_polygon(fr, bar, -r), look["frame"])
        mb.add(outline_band(fr, ring_of(bar), -r, -r - g), look["frame"])
    mb.add(facade_polygon(fr, inner, -r - g), glass_material(mats, op))
    if op.glazing in ("curtain", "half_blind"):
        cover = outline
        if op.glazing == "half_blind":
            s0, s1, t0, t1 = op.rect
            split = t1 - op.blind_frac * (t1 - t0)
            cover = outline.intersection(box(s0 - 1, split, s1 + 1, t1 + 1))
        refl = float(look["rng"].uniform(0.3, 0.8))
        mb.add(facade_polygon(fr, cover, -(r + g + op.curtain_gap)), mats.add(CURTAIN, refl=refl))
    if op.sill:
        s0, s1, t0, _ = op.rect
        mb.add(facade_box(fr, s0 - 0.1, s1 + 0.1, t0 - 0.07, t0, 0.0, op.sill_proud), look["sill"])


def _bars(op: Opening, inner: Polygon) -> list:
    """Mullions (full height, up to the arch) and transoms (below the springline), flush with the frame."""
    cols, rows = op.bars
    if cols * rows <= 1 or inner.is_empty:
        return []
    s0, t0, s1, t1 = inner.bounds
    spring = t1 - max(op.arch_rise - op.frame_w, 0.0)
    out, half = [], op.bar_w / 2
    for i in range(1, cols):
        sm = s0 + (s1 - s0) * i / cols
        out.append(box(sm - half, t0, sm + half, t1).intersection(inner))
    for j in range(1, rows):
        tm = t0 + (spring - t0) * j / rows
        out.append(box(s0, tm - half, s1, tm + half).intersection(inner))
    return [b for b in out if b.geom_type == "Polygon" and b.area > 1e-6]


def build_door(mb: MeshBuilder, mats: Materials, fr: Frame, op: Opening, look: dict, ground_t) -> None:
    """Reveal (jambs, head, threshold), leaf (with a glazed upper panel), steps in front."""
    s0, s1, t0, t1 = op.rect
    outline = box(s0, t0, s1, t1)
    leaf_d = -op.reveal
    mb.add(outline_band(fr, ring_of(outline), 0.0, leaf_d), look["reveal"])
    leaf = outline
    rng = look["rng"]
    leaf_mat = mats.add(DOOR, refl=float(rng.uniform(0.08, 0.5)))
    if op.glazed_panel:
        panel = box(s0 + 0.15, t0 + 1.1, s1 - 0.15, t1 - 0.2)
        if op.subtype == "double_door":
            mid = (s0 + s1) / 2
            panel = box(s0 + 0.12, t0 + 1.0, mid - 0.1, t1 - 0.2).union(box(mid + 0.1, t0 + 1.0, s1 - 0.12, t1 - 0.2))
        leaf = outline.difference(panel)
        mb.add(facade_polygon(fr, panel, leaf_d - 0.01), glass_material(mats, op))
    mb.add(facade_polygon(fr, leaf, leaf_d), leaf_mat)
    if op.subtype == "double_door":  # the meeting stiles stand a little proud of the leaves
        mid = (s0 + s1) / 2
        mb.add(facade_box(fr, mid - 0.03, mid + 0.03, t0, t1, leaf_d, leaf_d + 0.015), leaf_mat)
    if op.steps:
        bottom = float(min(ground_t(s0 - 0.2), ground_t(s1 + 0.2))) - 0.3
        for i in range(op.steps):  # the top step is the landing in front of the door
            top = t0 - i * op.step_rise
            mb.add(facade_box(fr, s0 - 0.15, s1 + 0.15, bottom, top, 0.0, 0.3 * (i + 1)), look["step"])


def draw_door_leaf(rng, op: Opening) -> None:
    """Flush (2-5 cm behind the wall) or recessed (15-60 cm) leaf; garages 5-30 cm."""
    if op.subtype == "garage":
        op.reveal = float(rng.uniform(0.05, 0.3))
        op.glazing = "garage"
    elif rng.random() < 0.6:
        op.reveal = float(rng.uniform(0.02, 0.05))
        op.glazing = "flush_leaf"
    else:
        op.reveal = float(rng.uniform(0.15, 0.6))
        op.glazing = "recessed_leaf"
    if op.glazed_panel:
        op.glazing = "glazed_door"
        draw_glass_door(rng, op)


def draw_glass_door(rng, op: Opening) -> None:
    op.p0 = float(rng.uniform(0.05, 0.5))
    op.k = float(rng.uniform(2.0, 8.0))
    op.spec = 0.0
    op.pint = float(rng.uniform(0.05, 0.3))


def window_look(rng, mats: Materials, wall_refl: float) -> dict:
    """Materials shared by a façade's windows: reveal (like the wall), frame, sill, steps."""
    frame_refl = float(rng.choice([rng.uniform(0.55, 0.8), rng.uniform(0.06, 0.2)]))
    return {"rng": rng, "reveal": mats.add(REVEAL, refl=wall_refl * 0.9, relief=0.004),
            "frame": mats.add(FRAME, refl=frame_refl),
            "sill": mats.add(PART, refl=float(rng.uniform(0.3, 0.6)), relief=0.003),
            "step": mats.add(PART, refl=float(rng.uniform(0.25, 0.5)), relief=0.003)}
