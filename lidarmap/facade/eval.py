"""Façade extraction scored against simulator truth (``lidarmap.sim.load_truth``): window/door F1, plane errors.

Used by tests/test_facade.py and benchmarks/bench_facade.py (and usable for refinement results, which have the same
model). Matching rules:

* an extracted façade matches the truth façade of the same building (footprint id = truth building id) whose
  normal is within 10° and whose plane passes within 1 m of the extracted façade's centre;
* a window/door/structure matches a truth one of the same kind at IoU >= ``iou`` in the truth façade's (s, t) (greedy, best
  IoU first, one to one over the elements of *all* extracted façades that match that truth façade: a wall held as
  two façades counts each truth opening once, and an opening found on both as one match and one false positive;
  until 2026-12-01 each extracted façade was scored against all of the truth façade's openings, so the openings of
  one piece counted as missed by the other). Only truth openings with ``visible_fraction[campaign] >= min_visible`` count (true positives and false
  negatives); predictions on less visible truth openings (IoU > 0.1) count neither way — of either opening kind: a
  window over a hardly visible door (its seen top) counts neither way, like a door there (until 2026-12-03 only
  truth of the prediction's own kind was looked at, so such a window was a false positive). Truth façades that no
  extracted façade matched contribute their visible openings as false negatives. For a map refined by several
  campaigns pass ``campaigns``: an opening is visible when the cells seen by *any* of them (the truth's
  per-campaign ``wall_seen`` grids, OR-ed: a window behind a balcony's parapet is hidden by it) cover
  ``min_visible`` of it. Structures (balconies, pilasters) are scored
  by the same rules on the bounding boxes of their outlines;
* the plane offset error of a matched façade is the mean distance of its extent corners (on d = 0) to the truth
  plane, the angle error the angle between normals.

``register`` maps file coordinates to true coordinates (the simulator misregisters each campaign by a few cm; pass
``TruthCampaign.register`` to score the extraction itself, or ``None`` to include the misregistration).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from shapely.geometry import Polygon, box

from lidarmap.facade.model import ElementKind, Facade


#: Element kinds scored against the truth (unknown regions are scored by area, see :func:`map_statistics`).
class ObservedBuilding(Protocol):
    """What the scores read of a building (a map's :class:`lidarmap.map.model.Building` is one): its id and
    façades. A protocol, so that scoring observations needs nothing of the map."""

    building_id: str
    facades: list[Facade]


SCORED_KINDS = ("window", "door", "structure")
OPENING_KINDS = ("window", "door")


def polygon_iou(a: Polygon, b: Polygon) -> float:
    """Intersection over union of two polygons (0 when both are empty)."""
    union = a.union(b).area
    return a.intersection(b).area / union if union > 0 else 0.0


def greedy_match(pred: list[Polygon], truth: list[Polygon], thr: float = 0.5) -> list[tuple[int, int, float]]:
    """One-to-one matches (pred index, truth index, IoU) with IoU >= ``thr``, best IoU first."""
    pairs = sorted(((polygon_iou(p, t), i, j) for i, p in enumerate(pred) for j, t in enumerate(truth)), reverse=True)
    used_p: set[int] = set()
    used_t: set[int] = set()
    out = []
    for value, i, j in pairs:
        if value < thr or i in used_p or j in used_t:
            continue
        used_p.add(i)
        used_t.add(j)
        out.append((i, j, value))
    return out


def _to_truth_rect(f: Facade, polygon: Polygon, tf, register) -> Polygon:
    pts = f.frame.polygon_to_crs(polygon)
    if register is not None:
        pts = register(pts)
    st = tf.to_facade(pts)[:, :2]
    return box(st[:, 0].min(), st[:, 1].min(), st[:, 0].max(), st[:, 1].max())


def match_facade(f: Facade, truth_facades: list, register: Callable | None = None):
    """The truth façade an extracted façade lies on (see the module doc), or ``None``."""
    s0, s1, t0, t1 = f.extent
    centre = f.frame.to_crs(np.array([[0.5 * (s0 + s1), 0.5 * (t0 + t1), 0.0]]))
    if register is not None:
        centre = register(centre)
    best, best_d = None, math.inf
    for tf in truth_facades:
        if float(tf.normal @ f.frame.normal) < math.cos(math.radians(10.0)):
            continue
        sdt = tf.to_facade(centre)[0]
        if abs(sdt[2]) > 1.0 or sdt[0] < -1.0 or sdt[0] > tf.width + 1.0:
            continue
        if abs(sdt[2]) < best_d:
            best, best_d = tf, abs(sdt[2])
    return best


def union_visibility(truth, campaigns: list[int], parapets_hide: bool = True) -> dict[int, float]:
    """Fraction of each truth element's cells seen by at least one of ``campaigns`` (element id -> fraction).

    Windows and doors by the ``wall_seen`` grids (a line of sight ending on a balcony's parapet does not see the
    opening behind it), structures by ``seen``. ``parapets_hide=False`` scores the openings by ``seen`` too: the
    truth before 2026-11-26, kept to compare figures across that change.
    """
    from lidarmap.sim.visibility import (
        visible_fraction,  # the simulator's own rule (cell centres in the rect)
    )

    grids: dict[str, dict[int, np.ndarray]] = {"seen": {}, "wall_seen": {}}
    for c in campaigns:
        for fid, g in truth.visibility(c).items():
            for layer, union in grids.items():
                union[fid] = g[layer] if fid not in union else (union[fid] | g[layer])
    cell = truth.visibility_cell
    out: dict[int, float] = {}
    for tf in truth.facades.values():
        for e in tf.elements:
            layer = "wall_seen" if parapets_hide and e.kind != "structure" else "seen"
            out[e.id] = visible_fraction(grids[layer][tf.id], e.rect, cell) if tf.id in grids[layer] else 0.0
    return out


class _Tally:
    """Counts of one scoring run: tp/fp/fn per kind, window IoUs, plane errors, the truth façades matched."""

    def __init__(self) -> None:
        self.counts = {k: {"tp": 0, "fp": 0, "fn": 0} for k in SCORED_KINDS}
        self.ious: list[float] = []
        self.offsets: list[float] = []
        self.angles: list[float] = []
        self.matched_truth: set[int] = set()
        self.n_facades = 0

    def summary(self) -> dict:
        out: dict = {"facades": self.n_facades, "matched_facades": len(self.matched_truth)}
        for kind, c in self.counts.items():
            p = c["tp"] / max(1, c["tp"] + c["fp"])
            r = c["tp"] / max(1, c["tp"] + c["fn"])
            out[kind] = {**c, "precision": p, "recall": r, "f1": 2 * p * r / max(1e-12, p + r)}
        out["window_mean_iou"] = float(np.mean(self.ious)) if self.ious else 0.0
        out["offset_mean"] = float(np.mean(self.offsets)) if self.offsets else math.nan
        out["offset_max"] = float(np.max(self.offsets)) if self.offsets else math.nan
        out["angle_max_deg"] = float(np.max(self.angles)) if self.angles else math.nan
        return out


def _plane_errors(f: Facade, tf, register: Callable | None, tally: _Tally) -> None:
    """Offset (mean distance of the extent corners to the truth plane) and angle of a matched façade."""
    s0, s1, t0, t1 = f.extent
    corners = f.frame.to_crs(np.array([[s0, t0, 0.0], [s1, t0, 0.0], [s0, t1, 0.0], [s1, t1, 0.0]]))
    if register is not None:
        corners = register(corners)
    tally.offsets.append(float(np.mean(np.abs(tf.to_facade(corners)[:, 2]))))
    tally.angles.append(math.degrees(math.acos(min(1.0, abs(float(tf.normal @ f.frame.normal))))))


def unscored_outlines(elements: list, kind: str, is_visible: Callable, across_kinds: bool = True) -> list[Polygon]:
    """The outlines of the hardly visible truth elements a prediction of ``kind`` counts neither way over: those of
    its kind, and for a window or door those of the other opening kind too (the seen top of a door is a window's
    rectangle: its type cannot be scored where the door is not; until 2026-12-03 only the prediction's own kind
    was looked at, and such a window was a false positive)."""
    kinds = OPENING_KINDS if across_kinds and kind in OPENING_KINDS else (kind,)
    return [e.polygon for e in elements if e.kind in kinds and not is_visible(e)]


def _score_kind(pred: list[Polygon], true: list, visible: list[bool], kind: str, iou: float, tally: _Tally,
                unscored: list[Polygon]) -> None:
    """Greedy matches of one kind on one façade; predictions over the ``unscored`` outlines (IoU > 0.1:
    :func:`unscored_outlines`) count neither way."""
    matches = greedy_match(pred, [e.polygon for e in true], iou)
    matched_p = {i for i, _, _ in matches}
    matched_t = {j for _, j, _ in matches}
    c = tally.counts[kind]
    for _, j, value in matches:
        if visible[j]:
            c["tp"] += 1
            if kind == "window":
                tally.ious.append(value)
    for i, p in enumerate(pred):
        if i in matched_p or any(polygon_iou(p, h) > 0.1 for h in unscored):
            continue
        c["fp"] += 1
    c["fn"] += sum(1 for j in range(len(true)) if visible[j] and j not in matched_t)


def _on_truth(f: Facade, tb, register: Callable | None, tally: _Tally, on_truth: dict) -> None:
    """Put one extracted façade's elements on the truth façade it matches (``on_truth``: truth façade id -> (truth
    façade, [(kind, rectangle in its s, t)])); all its elements are false when it matches none."""
    tally.n_facades += 1
    tf = match_facade(f, tb.facades, register) if tb is not None else None
    preds = [e for e in f.elements if e.kind.value in SCORED_KINDS]
    if tf is None:
        for e in preds:
            tally.counts[e.kind.value]["fp"] += 1
        return
    tally.matched_truth.add(tf.id)
    _plane_errors(f, tf, register, tally)
    rects = on_truth.setdefault(tf.id, (tf, []))[1]
    rects += [(e.kind.value, _to_truth_rect(f, e.polygon, tf, register)) for e in preds]


def evaluate_facades(buildings: list[ObservedBuilding], truth, campaign_id: int, register: Callable | None = None,
                     iou: float = 0.5, min_visible: float = 0.9, campaigns: list[int] | None = None,
                     parapets_hide: bool = True, across_kinds: bool = True) -> dict:
    """Window and door precision/recall/F1, mean IoU, plane offset and angle errors (see the module doc).

    ``campaigns`` (a refined map): visibility is the union over these campaigns instead of ``campaign_id`` alone.
    ``parapets_hide``: see :func:`union_visibility` (False: the truth before 2026-11-26). ``across_kinds``: see
    :func:`unscored_outlines` (False: the scorer before 2026-12-03, for comparisons with earlier figures).
    """
    if not parapets_hide and not campaigns:
        campaigns = [campaign_id]
    union = union_visibility(truth, campaigns, parapets_hide) if campaigns else None

    def is_visible(e) -> bool:
        fraction = union.get(e.id, 0.0) if union is not None else e.visible_fraction.get(campaign_id, 0.0)
        return fraction >= min_visible

    tally = _Tally()
    by_building = {str(b.id): b for b in truth.buildings}
    on_truth: dict[int, tuple] = {}
    for b in buildings:
        for f in b.facades:
            _on_truth(f, by_building.get(str(b.building_id)), register, tally, on_truth)
    # one truth façade is scored once, against the elements of every extracted façade on it: a wall the map holds
    # as two façades (a piece a later campaign added) has each truth opening matched, missed or duplicated once
    for tf, rects in on_truth.values():
        for kind in SCORED_KINDS:
            true = [e for e in tf.elements if e.kind == kind]
            _score_kind([r for k, r in rects if k == kind], true, [is_visible(e) for e in true], kind, iou, tally,
                        unscored_outlines(tf.elements, kind, is_visible, across_kinds))
    for tb in truth.buildings:  # truth façades nobody found: their visible openings are missed
        for tf in tb.facades:
            if tf.id in tally.matched_truth:
                continue
            for e in tf.elements:
                if e.kind in tally.counts and is_visible(e):
                    tally.counts[e.kind]["fn"] += 1
    return tally.summary()


def map_statistics(buildings: list[ObservedBuilding]) -> dict:
    """What a map says about itself (no truth needed): façade/window/door/unknown counts, unknown area (m²),
    mean window/door uncertainty ε (eq. 3), mean and max main-layer σ (m), campaigns per façade."""
    facades = [f for b in buildings for f in b.facades]
    openings = [e for f in facades for e in f.elements if e.kind in (ElementKind.WINDOW, ElementKind.DOOR)]
    unknown = [e for f in facades for e in f.elements if e.is_unknown]
    sigmas = [f.sigma for f in facades if math.isfinite(f.sigma)]
    eps = [e.uncertainty for e in openings if math.isfinite(e.uncertainty)]
    return {
        "facades": len(facades),
        "windows": sum(1 for e in openings if e.kind is ElementKind.WINDOW),
        "doors": sum(1 for e in openings if e.kind is ElementKind.DOOR),
        "unknown": len(unknown),
        "unknown_area": float(sum(e.polygon.area for e in unknown)),
        "mean_uncertainty": float(np.mean(eps)) if eps else math.nan,
        "sigma_mean": float(np.mean(sigmas)) if sigmas else math.nan,
        "sigma_max": float(np.max(sigmas)) if sigmas else math.nan,
        "campaigns_per_facade": float(np.mean([len(f.campaigns) for f in facades])) if facades else 0.0,
    }
