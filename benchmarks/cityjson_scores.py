"""Window and door scores of a CityJSON export against a scene's truth, as an outside user would measure them.

The map is judged only through what `lidarmap map export` writes: the ``Window`` / ``Door`` surfaces of the LoD 3
geometry (the highest LoD of each building), in CRS coordinates. No internal structure of lidarmap is read, so the
same scorer judges our own simulator's scenes and the independent generator's (``lidarmap.sim.independent``,
docs/independent_scenes.md).

Truth: ``truth.json`` of the independent generator (format ``lidarmap-independent-truth``): façades (origin, u,
normal) and openings (kind, ``rect`` [s0, s1, t0, t1] in the wall plane, ``observed`` share of their 0.2 m cells that
a pulse crossed, per campaign and for the campaigns 1..k together as key ``"1-k"``).

Rules (the issue-18 rules, end to end):

* a predicted opening belongs to the truth façade whose plane it lies on (centroid within ``plane_tol`` of the
  plane, normal within ``angle_tol`` degrees, inside the façade's extent with a margin); its outline is projected
  onto that plane (s, t);
* a truth opening is scored when at least ``observed_min`` of its cells were crossed by a pulse so far;
* prediction and truth match one to one (greedy by IoU) when their IoU >= ``iou`` and the kind is the same;
* an unmatched prediction over an unscored truth opening (IoU > 0.1, either kind) counts neither way; any other
  unmatched prediction is false, "on blank wall" when it touches no truth opening at all;
* ``aligned=True`` first shifts each façade's predictions by the median offset between predictions and truth openings
  that overlap (IoU > 0.2, two pairs at least): what the scores would be without the campaign's GNSS drift.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

KINDS = {"Window": "window", "Door": "door"}


@dataclasses.dataclass(frozen=True)
class TruthFacade:
    id: int
    building_id: int
    origin: np.ndarray
    u: np.ndarray
    normal: np.ndarray
    width: float
    height: float
    observed_wall_area: dict[str, float]

    def to_facade(self, xyz: np.ndarray) -> np.ndarray:
        """(s, t, d) of CRS points."""
        rel = np.asarray(xyz, float) - self.origin
        return np.column_stack([rel @ self.u, rel[:, 2], rel @ self.normal])


@dataclasses.dataclass(frozen=True)
class TruthOpening:
    id: int
    facade_id: int
    kind: str
    subtype: str
    rect: tuple[float, float, float, float]
    observed: dict[str, float]

    @property
    def polygon(self) -> Polygon:
        s0, s1, t0, t1 = self.rect
        return box(s0, t0, s1, t1)


@dataclasses.dataclass(frozen=True)
class SceneTruth:
    facades: dict[int, TruthFacade]
    openings: list[TruthOpening]
    campaigns: int


@dataclasses.dataclass(frozen=True)
class PredictedOpening:
    building: str
    kind: str
    rings: list[np.ndarray]  # exterior rings (CRS xyz) of its surfaces


@dataclasses.dataclass
class Counts:
    tp: int = 0
    fp: int = 0
    fn: int = 0

    def add(self, other: "Counts") -> None:
        self.tp, self.fp, self.fn = self.tp + other.tp, self.fp + other.fp, self.fn + other.fn

    @property
    def f1(self) -> float:
        """F1; 1.0 when there was nothing to find and nothing was claimed."""
        return 1.0 if self.tp + self.fp + self.fn == 0 else 2 * self.tp / (2 * self.tp + self.fp + self.fn)


@dataclasses.dataclass
class Score:
    all: Counts = dataclasses.field(default_factory=Counts)
    window: Counts = dataclasses.field(default_factory=Counts)
    door: Counts = dataclasses.field(default_factory=Counts)
    any_kind: Counts = dataclasses.field(default_factory=Counts)  # openings matched whatever their kind
    false_blank: int = 0  # false openings touching no truth opening
    off_facade: int = 0  # predictions on no truth façade
    wall_area: float = 0.0  # observed wall (m²) outside the openings
    missed: list[int] = dataclasses.field(default_factory=list)  # truth ids scored and not found
    false: list[tuple[int, str, tuple]] = dataclasses.field(default_factory=list)  # (façade, kind, bounds)

    def add(self, other: "Score") -> None:
        for name in ("all", "window", "door", "any_kind"):
            getattr(self, name).add(getattr(other, name))
        self.false_blank += other.false_blank
        self.off_facade += other.off_facade
        self.wall_area += other.wall_area

    @property
    def false_blank_per_500m2(self) -> float:
        return 500.0 * self.false_blank / self.wall_area if self.wall_area > 0 else float("nan")


def load_truth(path: str | Path) -> SceneTruth:
    """``truth.json`` of the independent generator."""
    doc = json.loads(Path(path).read_text())
    if doc.get("format") != "lidarmap-independent-truth":
        raise ValueError(f"{path}: not a lidarmap-independent-truth file")
    facades = {int(f["id"]): TruthFacade(int(f["id"]), int(f["building_id"]), np.asarray(f["origin"], float),
                                         np.asarray(f["u"], float), np.asarray(f["normal"], float),
                                         float(f["width"]), float(f["height"]),
                                         {k: float(v) for k, v in f.get("observed_wall_area", {}).items()})
               for f in doc["facades"]}
    openings = [TruthOpening(int(o["id"]), int(o["facade_id"]), o["kind"], o.get("subtype", o["kind"]),
                             tuple(float(x) for x in o["rect"]), {k: float(v) for k, v in o["observed"].items()})
                for o in doc["openings"]]
    return SceneTruth(facades, openings, len(doc["campaigns"]))


def _vertices(doc: dict) -> np.ndarray:
    transform = doc.get("transform")
    xyz = np.asarray(doc["vertices"], float).reshape(-1, 3)
    if transform:
        xyz = xyz * np.asarray(transform["scale"]) + np.asarray(transform["translate"])
    return xyz


def _top_geometry(geometries: list[dict]) -> dict | None:
    with_semantics = [g for g in geometries if g.get("semantics")]
    return max(with_semantics, key=lambda g: float(g.get("lod", 0))) if with_semantics else None


def read_openings(doc: dict) -> list[PredictedOpening]:
    """Every Window / Door of the highest-LoD geometry of every city object (one per semantic object: the surfaces
    that share a semantic value are one opening)."""
    xyz = _vertices(doc)
    out: list[PredictedOpening] = []
    for name, obj in doc["CityObjects"].items():
        geometry = _top_geometry(obj.get("geometry", []))
        if geometry is None or geometry["type"] != "MultiSurface":
            continue
        surfaces, values = geometry["semantics"]["surfaces"], geometry["semantics"]["values"]
        rings: dict[int, list[np.ndarray]] = {}
        for polygon, value in zip(geometry["boundaries"], values):
            if value is not None and surfaces[value]["type"] in KINDS:
                rings.setdefault(value, []).append(xyz[polygon[0]])
        out += [PredictedOpening(name, KINDS[surfaces[v]["type"]], r) for v, r in sorted(rings.items())]
    return out


def _normal(ring: np.ndarray) -> np.ndarray:
    centred = ring - ring.mean(axis=0)
    n = np.cross(centred[np.arange(len(ring))], centred[(np.arange(len(ring)) + 1) % len(ring)]).sum(axis=0)
    length = np.linalg.norm(n)
    return n / length if length > 0 else n


def place_on_facade(pred: PredictedOpening, facades: list[TruthFacade], plane_tol: float = 0.8,
                    angle_tol: float = 30.0, margin: float = 0.5) -> tuple[int, Polygon] | None:
    """The truth façade a predicted opening lies on and its outline in that façade's (s, t); None if none."""
    points = np.vstack(pred.rings)
    normal = _normal(pred.rings[0])
    best = None
    for f in facades:
        if abs(float(normal @ f.normal)) < np.cos(np.radians(angle_tol)):
            continue
        s, t, d = f.to_facade(points.mean(axis=0)[None])[0]
        inside = -margin <= s <= f.width + margin and -margin - 1.0 <= t <= f.height + margin
        if inside and abs(d) <= plane_tol and (best is None or abs(d) < best[0]):
            best = (abs(d), f)
    if best is None:
        return None
    f = best[1]
    parts = [Polygon(f.to_facade(r)[:, :2]).buffer(0) for r in pred.rings]
    return f.id, unary_union(parts)


def _iou(a: Polygon, b: Polygon) -> float:
    inter = a.intersection(b).area
    return inter / (a.area + b.area - inter) if inter > 0 else 0.0


def _greedy(pairs: list[tuple[float, int, int]], threshold: float) -> list[tuple[int, int]]:
    used_p, used_t, out = set(), set(), []
    for iou, p, t in sorted(pairs, key=lambda x: (-x[0], x[1], x[2])):
        if iou >= threshold and p not in used_p and t not in used_t:
            used_p.add(p)
            used_t.add(t)
            out.append((p, t))
    return out


def _aligned(preds: list[tuple[str, Polygon]], truth: list[TruthOpening]) -> list[tuple[str, Polygon]]:
    """Predictions shifted by the median offset to the truth openings they overlap (IoU > 0.2), if >= 2 pairs."""
    offsets = []
    for _, p in preds:
        best = max(((_iou(p, o.polygon), o) for o in truth), default=(0.0, None), key=lambda x: x[0])
        if best[0] > 0.2:
            pc, tc = p.centroid, best[1].polygon.centroid
            offsets.append((tc.x - pc.x, tc.y - pc.y))
    if len(offsets) < 2:
        return preds
    ds, dt = np.median(np.asarray(offsets), axis=0)
    from shapely.affinity import translate
    return [(k, translate(p, ds, dt)) for k, p in preds]


def score_facade(preds: list[tuple[str, Polygon]], truth: list[TruthOpening], key: str, observed_min: float,
                 iou: float) -> Score:
    """Counts on one façade: predictions (kind, outline in s, t) against its truth openings."""
    score = Score()
    scored = [o.observed.get(key, 0.0) >= observed_min for o in truth]
    pairs = [(_iou(p, o.polygon), i, j) for i, (_, p) in enumerate(preds) for j, o in enumerate(truth)]
    same = _greedy([(v, i, j) for v, i, j in pairs if preds[i][0] == truth[j].kind and scored[j]], iou)
    anyk = _greedy([(v, i, j) for v, i, j in pairs if scored[j]], iou)
    score.any_kind.tp = len(anyk)
    score.any_kind.fn = sum(scored) - len(anyk)
    matched_p, matched_t = {i for i, _ in same}, {j for _, j in same}
    for j, o in enumerate(truth):
        counts = getattr(score, o.kind)
        if j in matched_t:
            counts.tp += 1
        elif scored[j]:
            counts.fn += 1
            score.missed.append(o.id)
    overlaps = {}
    for v, i, j in pairs:
        overlaps.setdefault(i, []).append((v, j))
    for i, (kind, p) in enumerate(preds):
        if i in matched_p:
            continue
        hits = overlaps.get(i, [])
        if any(v > 0.1 and not scored[j] for v, j in hits):
            continue  # over an opening nobody could see: neither way
        getattr(score, kind).fp += 1
        score.any_kind.fp += 0 if i in {a for a, _ in anyk} else 1
        touching = any(p.intersects(truth[j].polygon) for _, j in hits)
        score.false_blank += 0 if touching else 1
        score.false.append((-1, kind, tuple(round(x, 2) for x in p.bounds)))
    for name in ("tp", "fp", "fn"):
        setattr(score.all, name, getattr(score.window, name) + getattr(score.door, name))
    return score


def score_export(doc: dict, truth: SceneTruth, key: str, observed_min: float = 0.6, iou: float = 0.5,
                 aligned: bool = False) -> Score:
    """Scores of one CityJSON document against the truth after the campaigns ``key`` ("1", "1-2", ...)."""
    facades = list(truth.facades.values())
    by_facade: dict[int, list[tuple[str, Polygon]]] = {f.id: [] for f in facades}
    total = Score()
    for pred in read_openings(doc):
        placed = place_on_facade(pred, facades)
        if placed is None:
            total.off_facade += 1
            getattr(total, pred.kind).fp += 1
            total.all.fp += 1
            total.any_kind.fp += 1
            continue
        by_facade[placed[0]].append((pred.kind, placed[1]))
    for f in facades:
        openings = [o for o in truth.openings if o.facade_id == f.id]
        preds = _aligned(by_facade[f.id], openings) if aligned else by_facade[f.id]
        one = score_facade(preds, openings, key, observed_min, iou)
        one.wall_area = f.observed_wall_area.get(key, 0.0)
        one.false = [(f.id, k, b) for _, k, b in one.false]
        total.add(one)
        total.missed += one.missed
        total.false += one.false
    return total
