"""Shared scoring of the façade map on simulator scenes: the standard scene beside the hard family.

Used by bench_facade.py and bench_refine.py (``--eval`` scores the reserved evaluation seeds 7001-...; without it
the development seeds of :mod:`lidarmap.sim.family`). For every scene the campaigns are fused one after the other
into a map (``lidarmap.map.update.refine_map``, what ``lidarmap map update`` does) and the map after k campaigns is
scored with ``lidarmap.facade.eval.evaluate_facades`` against the truth openings at least 90 % seen by any of the
campaigns so far (in the hard family "seen" also needs incidence <= 80° and expected sample spacing <= 0.3 m:
openings no campaign could observe are not scored). Figures:

* window + door F1: one F1 over the windows' and doors' pooled tp/fp/fn (IoU >= 0.5, same type);
* door F1: doors alone (a window typed as door is a false door and a missed window);
* false openings per 500 m² of blank wall: windows/doors the map puts on façades that have no opening at all,
  per 500 m² of those façades' cells seen by the campaigns so far (in file coordinates).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from shapely.geometry import box

from lidarmap.facade.eval import (
    evaluate_facades,
    match_facade,
    polygon_iou,
    union_visibility,
)
from lidarmap.facade.model import ElementKind
from lidarmap.facade.params import FacadeParams
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las
from lidarmap.io.trajectory import read_trajectory
from lidarmap.map.model import BuildingMap
from lidarmap.map.refine import RefineParams
from lidarmap.map.update import refine_map
from lidarmap.sim import load_truth, simulate
from lidarmap.sim.family import family_params, seeds

BLANK_AREA_UNIT = 500.0  # m² of observed blank wall per reported false-opening rate


@dataclasses.dataclass
class MapScore:
    """Scores of one map against one scene's truth."""

    tp: int
    fp: int
    fn: int
    door: dict
    window: dict
    false_blank: int
    blank_area: float
    by_glazing: dict = dataclasses.field(default_factory=dict)  # see recall_by_glazing

    @property
    def f1(self) -> float:
        return 2 * self.tp / max(1, 2 * self.tp + self.fp + self.fn)

    @property
    def false_per_unit(self) -> float:
        return BLANK_AREA_UNIT * self.false_blank / self.blank_area if self.blank_area > 0 else math.nan


def blank_wall_false_openings(buildings: list, truth, campaigns: list[int]) -> tuple[int, float]:
    """Windows/doors on truth façades without openings, and those façades' area seen by ``campaigns`` (m²)."""
    blank = {tf.id: tf for tf in truth.facades.values() if not any(e.kind in ("window", "door") for e in tf.elements)
             and truth.building(tf.building_id).status == "existing"}
    seen: dict[int, np.ndarray] = {}
    for c in campaigns:
        for fid, g in truth.visibility(c).items():
            if fid in blank:
                seen[fid] = g["seen"] if fid not in seen else (seen[fid] | g["seen"])
    area = float(sum(g.sum() for g in seen.values())) * truth.visibility_cell ** 2
    by_building = {str(b.id): b for b in truth.buildings}
    false = 0
    for b in buildings:
        tb = by_building.get(str(b.building_id))
        if tb is None:
            continue
        for f in b.facades:
            tf = match_facade(f, tb.facades)
            if tf is not None and tf.id in blank:
                false += sum(1 for e in f.elements if e.kind in (ElementKind.WINDOW, ElementKind.DOOR))
    return false, area


def recall_by_glazing(buildings: list, truth, campaigns: list[int], min_visible: float = 0.9) -> dict:
    """Truth windows/doors seen by ``campaigns`` by glazing (hard family; else subtype): [found with their kind,
    found as another kind (window as door, structure, ...), total], at IoU >= 0.5 in file coordinates."""
    visible = union_visibility(truth, campaigns)
    raw = {el["id"]: el for b in truth.doc["buildings"] for f in b["facades"] for el in f["elements"]}
    by_building = {str(b.building_id): b for b in buildings}
    out: dict[str, list[int]] = {}
    for tb in truth.buildings:
        rects: dict[int, list] = {}
        for f in getattr(by_building.get(str(tb.id)), "facades", []):
            tf = match_facade(f, tb.facades)
            for e in f.elements if tf is not None else []:
                st = tf.to_facade(f.frame.polygon_to_crs(e.polygon))[:, :2]
                rects.setdefault(tf.id, []).append((e.kind.value, box(*st.min(axis=0), *st.max(axis=0))))
        for tf in tb.facades:
            for e in tf.elements:
                if e.kind not in ("window", "door") or visible.get(e.id, 0.0) < min_visible:
                    continue
                key = f"{e.kind} {raw[e.id].get('glazing') or e.subtype}"
                best = max(((polygon_iou(r, e.polygon), k) for k, r in rects.get(tf.id, [])), default=(0.0, ""))
                row = out.setdefault(key, [0, 0, 0])
                row[2] += 1
                if best[0] >= 0.5:
                    row[0 if best[1] == e.kind else 1] += 1
    return out


def score_map(buildings: list, truth, campaigns: list[int], parapets_hide: bool = True,
              across_kinds: bool = True) -> MapScore:
    """The map's scores after ``campaigns`` (``parapets_hide``: :func:`lidarmap.facade.eval.union_visibility`;
    ``across_kinds``: :func:`lidarmap.facade.eval.unscored_outlines`)."""
    ev = evaluate_facades(buildings, truth, campaigns[-1], campaigns=campaigns, parapets_hide=parapets_hide,
                          across_kinds=across_kinds)
    w, d = ev["window"], ev["door"]
    false, area = blank_wall_false_openings(buildings, truth, campaigns)
    return MapScore(tp=w["tp"] + d["tp"], fp=w["fp"] + d["fp"], fn=w["fn"] + d["fn"], door=d, window=w,
                    false_blank=false, blank_area=area, by_glazing=recall_by_glazing(buildings, truth, campaigns))


@dataclasses.dataclass
class SceneRun:
    """One scene: its family and seed, points per campaign, and the map's score after each campaign."""

    family: str
    seed: int
    points: list[int]
    scores: list[MapScore]
    seconds: list[float]
    openings: int  # truth windows + doors of existing buildings
    setups: list[str]
    # the map after each campaign scored on the openings the first campaign saw (a truth set that does not grow:
    # what refinement did to them, apart from the openings later campaigns bring into the score); score_scene(fixed=)
    fixed: list[MapScore] = dataclasses.field(default_factory=list)
    # the scores after each campaign by the scorer before 2026-12-03 (a window over a hardly visible door counted
    # false): figures comparable with the earlier rounds'; score_scene(fixed=) too
    legacy: list[MapScore] = dataclasses.field(default_factory=list)


def run_scene(family: str, seed: int, campaigns: int = 3, fixed: bool = False) -> SceneRun:
    """Simulate one scene and fuse its campaigns one by one, scoring the map after each (``fixed``: score_scene)."""
    with tempfile.TemporaryDirectory() as tmp:
        simulate(tmp, family_params(family, seed, campaigns=campaigns))
        return score_scene(Path(tmp), fixed=fixed)


def score_scene(root: Path, fixed: bool = False) -> SceneRun:
    """Fuse the campaigns of the simulated scene in ``root`` one by one, scoring the map after each; ``fixed``: also
    against the openings the first campaign saw (:attr:`SceneRun.fixed`)."""
    fparams, rparams = FacadeParams(), RefineParams()
    truth = load_truth(root)
    m = BuildingMap(crs_wkt=truth.crs.to_wkt())
    points, scores, secs, first_seen, legacy = [], [], [], [], []
    for k, camp in enumerate(truth.campaigns, start=1):
        cloud, traj = read_las(camp.laz), read_trajectory(camp.trajectory)
        fps = read_footprints(root / "footprints.geojson", crs=cloud.crs)
        clock = time.perf_counter()
        m = refine_map(m, cloud, traj, fps, fparams, rparams, camp.id, seed=0)
        secs.append(time.perf_counter() - clock)
        points.append(len(cloud))
        scores.append(score_map(list(m.buildings.values()), truth, [c.id for c in truth.campaigns[:k]]))
        if fixed:
            first_seen.append(score_map(list(m.buildings.values()), truth, [truth.campaigns[0].id]))
            legacy.append(score_map(list(m.buildings.values()), truth, [c.id for c in truth.campaigns[:k]],
                                    across_kinds=False))
    openings = sum(1 for e in truth.elements.values() if e.kind in ("window", "door"))
    setups = [_setup(c) for c in truth.doc["campaigns"]]
    return SceneRun(truth.doc.get("family", "standard"), int(truth.doc["seed"]), points, scores, secs, openings,
                    setups, first_seen, legacy)


def _setup(c: dict) -> str:
    s = c.get("setup")
    if s is None:
        return f"lane {c['lane_offset']:+.1f} m, {c['speed']:.1f} m/s"
    yaws = "/".join(f"{y:+.0f}°" for y in s["yaws_deg"])
    return (f"lane {c['lane_offset']:+.1f} m, {c['speed']:.1f} m/s, h {s['sensor_height']:.1f} m, "
            f"{s['rate']:.0f} Hz, yaw {yaws}")


def run_families(evaluation: bool, scenes: int, standard: bool = True, hard: bool = True,
                 campaigns: int = 3) -> list[SceneRun]:
    """The standard scene and/or the hard family on the first ``scenes`` evaluation (or development) seeds."""
    runs = []
    chosen = seeds(evaluation, scenes)
    for family, wanted in (("standard", standard), ("hard", hard)):
        if wanted:
            runs += [run_scene(family, seed, campaigns) for seed in chosen]
    return runs


def _pooled(scores: list[MapScore]) -> MapScore:
    door = {k: sum(s.door[k] for s in scores) for k in ("tp", "fp", "fn")}
    window = {k: sum(s.window[k] for s in scores) for k in ("tp", "fp", "fn")}
    return MapScore(tp=sum(s.tp for s in scores), fp=sum(s.fp for s in scores), fn=sum(s.fn for s in scores),
                    door=door, window=window, false_blank=sum(s.false_blank for s in scores),
                    blank_area=sum(s.blank_area for s in scores))


def _rate(s: MapScore) -> str:
    """False openings per 500 m² of seen blank wall, and the count behind it ("∞" when none of it was seen)."""
    if s.blank_area > 0:
        return f"{s.false_per_unit:.1f} ({s.false_blank})"
    return f"∞ ({s.false_blank})" if s.false_blank else "– (0)"


def _door_f1(s: MapScore) -> float:
    d = s.door
    return 2 * d["tp"] / max(1, 2 * d["tp"] + d["fp"] + d["fn"])


def markdown(runs: list[SceneRun], evaluation: bool, title: str = "Standard scene vs hard family") -> str:
    """One table row per scene and one pooled row per family (after the first and after the last campaign)."""
    kind = "reserved evaluation seeds" if evaluation else "development seeds"
    lines = [f"### {title} ({kind})\n",
             ("The map after 1 and after all campaigns fused one by one (`refine_map`, as `lidarmap map update`), "
             "scored against truth openings at least 90 % seen by the campaigns so far (a line of sight that ends on "
             "a balcony's parapet does not see the wall behind it; hard family: seen = line of sight at <= 80° "
             "incidence with expected samples <= 0.3 m apart). W+D F1: windows and doors "
             "pooled (IoU >= 0.5, same type). False/500 m²: windows and doors on façades without any opening, per "
             "500 m² of their seen area (∞: openings on blank walls of which no cell counts as seen). Figures in benchmarks/facade_scores.py.\n"),
             ("| family | seed | points per campaign | W+D F1 after 1 | W+D F1 after last | door F1 after 1 / last | "
             "window tp/fp/fn after last | door tp/fp/fn after last | false/500 m² (count) after 1 / last | "
              "seen blank m² after 1 / last | "
             "update s |"),
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        first, last = r.scores[0], r.scores[-1]
        w, d = last.window, last.door
        lines.append(f"| {r.family} | {r.seed} | {' / '.join(f'{n / 1e6:.2f} M' for n in r.points)} | "
                     f"{first.f1:.3f} | {last.f1:.3f} | {_door_f1(first):.3f} / {_door_f1(last):.3f} | "
                     f"{w['tp']}/{w['fp']}/{w['fn']} | {d['tp']}/{d['fp']}/{d['fn']} | "
                     f"{_rate(first)} / {_rate(last)} | {first.blank_area:.0f} / {last.blank_area:.0f} | "
                     f"{' / '.join(f'{s:.0f}' for s in r.seconds)} |")
    for family in dict.fromkeys(r.family for r in runs):
        mine = [r for r in runs if r.family == family]
        n = min(len(r.scores) for r in mine)
        after = [_pooled([r.scores[k] for r in mine]) for k in range(n)]
        lines.append(f"| **{family}, all seeds** | | | **{after[0].f1:.3f}** | **{after[-1].f1:.3f}** | "
                     f"**{_door_f1(after[0]):.3f} / {_door_f1(after[-1]):.3f}** | | | "
                     f"**{_rate(after[0])} / {_rate(after[-1])}** | {after[0].blank_area:.0f} / "
                     f"{after[-1].blank_area:.0f} | |")
    hard = [r for r in runs if r.family == "hard"]
    if hard:
        lines.append("\nHard-family campaigns: " + "; ".join(
            f"seed {r.seed}: " + ", ".join(f"[{s}]" for s in r.setups) for r in hard) + ".")
        series = [_pooled([r.scores[k] for r in hard]).f1 for k in range(min(len(r.scores) for r in hard))]
        lines.append("Hard family W+D F1 after each campaign (all seeds pooled): "
                     + " → ".join(f"{x:.3f}" for x in series) + ".")
        lines.append("Hard-family truth openings by glazing / door style, after the first and the last campaign "
                     "(all seeds pooled; found with their type / found as another kind / seen):")
        for k in (0, -1):
            pooled: dict[str, list[int]] = {}
            for r in hard:
                for key, row in r.scores[k].by_glazing.items():
                    pooled[key] = [a + b for a, b in zip(pooled.get(key, [0, 0, 0]), row)]
            lines.append(f"after {'1' if k == 0 else 'last'}: " + ", ".join(
                f"{key} {a}/{b}/{c}" for key, (a, b, c) in sorted(pooled.items())) + ".")
    return "\n".join(lines) + "\n"


def print_family_section(args, bench: str, campaigns: int, title: str) -> None:
    """The standard-vs-hard table of ``bench`` (its own heading when it is all the bench prints)."""
    if args.family_only:
        print(f"## {bench}\n")
    else:
        print()  # a blank line between the bench's own last table and this section's heading
    runs = run_families(args.eval, args.scenes, campaigns=campaigns)
    print(markdown(runs, args.eval, title=title))


def add_arguments(ap) -> None:
    """The flags bench_facade.py and bench_refine.py share."""
    ap.add_argument("--eval", action="store_true", help="score the reserved evaluation seeds (benchmark figures)")
    ap.add_argument("--scenes", type=int, default=3, help="scenes (seeds) per family")
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--family-only", action="store_true", help="only the standard-vs-hard comparison")
    group.add_argument("--no-family", action="store_true", help="skip the standard-vs-hard comparison")
