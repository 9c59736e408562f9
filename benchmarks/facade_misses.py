"""Which openings the façade map misses or invents on development scenes, campaign by campaign (a diagnostic).

``python benchmarks/facade_misses.py --seeds 138,139 [--family hard] [--campaigns 3] [--keep DIR]``

For each development seed: simulate the scene (or reuse ``DIR/<family><seed>`` with ``--keep``), fuse its campaigns one
by one as ``lidarmap map update`` does, and after each print the scores of benchmarks/facade_scores.py and one line
per scored error:

* ``MISS``: a truth window/door seen (>= 90 %) by the campaigns so far that no map opening of its kind matches
  (IoU >= 0.5, one to one, as the scorer matches): its rectangle (façade s, t), how much of it each campaign saw,
  and the best map opening of any kind over it;
* ``FALSE``: a map window/door that no truth opening of its kind matches (nor overlaps one hardly seen), or one on
  no truth façade at all.

``--fixed`` scores every campaign's map on the openings the *first* campaign saw (a truth set that does not grow):
an error new after a later campaign is then what the fusion did to an opening already scored, or a false opening,
not an opening the later campaign brought into the score. ``--summary`` ends with the errors counted by class after
each campaign, all of them and those new after each later
campaign (:func:`error_class`): typing errors (a door found as a window), shape errors (IoU 0.1-0.5), slivers (a
false opening under 0.65 m one way over no truth opening), misses with nothing over them.

Reserved evaluation seeds (``lidarmap.sim.family.EVAL_SEEDS``) are refused: they are for benchmark figures only.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from collections import Counter
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from lidarmap.facade.eval import (  # noqa: E402
    _to_truth_rect,  # the scorer's own projection of a map rectangle into the truth façade
    greedy_match,
    match_facade,
    polygon_iou,
    union_visibility,
    unscored_outlines,
)
from lidarmap.facade.model import ElementKind  # noqa: E402
from lidarmap.facade.params import FacadeParams  # noqa: E402
from lidarmap.io.footprints import read_footprints  # noqa: E402
from lidarmap.io.las import read_las  # noqa: E402
from lidarmap.io.trajectory import read_trajectory  # noqa: E402
from lidarmap.map.model import BuildingMap  # noqa: E402
from lidarmap.map.refine import RefineParams  # noqa: E402
from lidarmap.map.update import refine_map  # noqa: E402
from lidarmap.sim import load_truth, simulate  # noqa: E402
from lidarmap.sim.family import EVAL_SEEDS, family_params  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import facade_scores  # noqa: E402  (benchmarks/facade_scores.py)

OPENINGS = (ElementKind.WINDOW, ElementKind.DOOR)
MIN_VISIBLE = 0.9  # as facade_scores / evaluate_facades


def map_openings(m: BuildingMap, truth) -> tuple[dict[int, list[tuple[str, object]]], list[str]]:
    """The map's windows/doors per matched truth façade id (kind, rectangle in that façade's s, t), and lines for
    those on no truth façade."""
    by_building = {str(b.id): b for b in truth.buildings}
    per_facade: dict[int, list[tuple[str, object]]] = {}
    orphans: list[str] = []
    for b in m.buildings.values():
        tb = by_building.get(str(b.building_id))
        for f in b.facades:
            tf = match_facade(f, tb.facades) if tb is not None else None
            for e in f.elements:
                if e.kind not in OPENINGS:
                    continue
                if tf is None:
                    orphans.append(f"  FALSE building {b.building_id} façade {f.facade_id}: {e.kind.value} on no "
                                   f"truth façade")
                    continue
                per_facade.setdefault(tf.id, []).append((e.kind.value, _to_truth_rect(f, e.polygon, tf, None)))
    return per_facade, orphans


def error_lines(m: BuildingMap, truth, campaigns: list[int]) -> list[str]:
    """One line per missed truth opening and per false map opening after ``campaigns``, matched as the scorer
    matches them (``lidarmap.facade.eval``: per kind, one to one, best IoU first; a prediction over a hardly seen
    truth opening counts neither way: ``unscored_outlines``)."""
    seen = union_visibility(truth, campaigns)
    each = {c: union_visibility(truth, [c]) for c in campaigns}
    per_facade, lines = map_openings(m, truth)
    for tf in truth.facades.values():
        found = per_facade.get(tf.id, [])
        for kind in ("window", "door"):
            pred = [p for k, p in found if k == kind]
            true = [te for te in tf.elements if te.kind == kind]
            visible = [seen.get(te.id, 0.0) >= MIN_VISIBLE for te in true]
            matches = greedy_match(pred, [te.polygon for te in true], 0.5)
            matched_p, matched_t = {i for i, _, _ in matches}, {j for _, j, _ in matches}
            for j, te in enumerate(true):
                if not visible[j] or j in matched_t:
                    continue
                iou, other = max(((polygon_iou(p, te.polygon), k) for k, p in found), default=(0.0, "-"))
                s0, s1, t0, t1 = te.rect
                by = " ".join(f"{c}:{each[c].get(te.id, 0.0):.2f}" for c in campaigns)
                lines.append(f"  MISS façade {tf.id} element {te.id} {kind}/{te.subtype} s {s0:.2f}-{s1:.2f} "
                             f"t {t0:.2f}-{t1:.2f} depth {te.depth:+.2f} seen by campaign [{by}]; best map "
                             f"opening IoU {iou:.2f} ({other})")
            unscored = unscored_outlines(tf.elements, kind, lambda te: seen.get(te.id, 0.0) >= MIN_VISIBLE)
            for i, p in enumerate(pred):
                if i in matched_p or any(polygon_iou(p, h) > 0.1 for h in unscored):
                    continue
                iou, te = max(((polygon_iou(p, te.polygon), te) for te in tf.elements), key=lambda x: x[0],
                              default=(0.0, None))
                s0, t0, s1, t1 = p.bounds
                lines.append(f"  FALSE façade {tf.id} {kind} s {s0:.2f}-{s1:.2f} t {t0:.2f}-{t1:.2f}; best truth "
                             f"element IoU {iou:.2f}" + (f" ({te.kind})" if te is not None else ""))
    return lines


SLIVER = 0.65  # m: a false opening narrower or lower than this over no truth opening is a sliver
_MISS = re.compile(r"MISS .* (window|door)/\S+ s .*best map opening IoU ([\d.]+) \(([\w-]+)\)")
_FALSE = re.compile(r"FALSE .* (window|door) s ([\d.-]+)-([\d.-]+) t ([\d.-]+)-([\d.-]+); best truth element IoU "
                    r"([\d.]+)(?: \((\w+)\))?")


def error_class(line: str) -> str:
    """The class of one error line of :func:`error_lines` (what ``--summary`` counts)."""
    m = _MISS.search(line)
    if m:
        kind, iou, other = m.group(1), float(m.group(2)), m.group(3)
        if iou >= 0.5 and other != kind:
            return f"{kind} typed {other}"
        return f"{kind} missed, shape (IoU {iou:.1f})" if iou > 0.1 else f"{kind} missed, nothing over it"
    m = _FALSE.search(line)
    if m:
        kind, iou, other = m.group(1), float(m.group(6)), m.group(7)
        width, height = float(m.group(3)) - float(m.group(2)), float(m.group(5)) - float(m.group(4))
        if iou >= 0.5 and other != kind:
            return f"false {kind} over a {other}"
        if iou > 0.1:
            return f"false {kind}, shape"
        return f"false {kind}, sliver" if min(width, height) < SLIVER else f"false {kind}, over nothing"
    return "false, on no truth façade" if "on no truth façade" in line else "other"


def _key(line: str) -> str:
    """An error line without what each campaign saw of the opening (that list grows with every campaign)."""
    return re.sub(r" seen by campaign \[[^\]]*\]", "", line)


def summary(per_campaign: list[list[list[str]]]) -> list[str]:
    """Error counts by class after each campaign, over scenes (``per_campaign[scene][k]``: the error lines after
    campaign k + 1), and those new after each later campaign (not among the scene's lines one campaign before,
    :func:`_key`)."""
    out = []
    for k in range(max((len(c) for c in per_campaign), default=0)):
        every = Counter(error_class(x) for c in per_campaign if k < len(c) for x in c[k])
        before = [{_key(y) for y in c[k - 1]} if 0 < k < len(c) else set() for c in per_campaign]
        new = Counter(error_class(x) for c, old in zip(per_campaign, before) if 0 < k < len(c)
                      for x in c[k] if _key(x) not in old)
        out.append(f"after {k + 1}: " + ", ".join(f"{n} {name}" for name, n in every.most_common()))
        if k:
            out.append(f"  new after {k + 1}: " + ", ".join(f"{n} {name}" for name, n in new.most_common()))
    return out


def diagnose(root: Path, fixed: bool = False) -> list[str]:
    """Fuse the campaigns of the scene in ``root`` one by one; the scores and errors after each (``fixed``: on the
    openings the first campaign saw)."""
    truth = load_truth(root)
    m = BuildingMap(crs_wkt=truth.crs.to_wkt())
    out, previous = [], None
    for k, camp in enumerate(truth.campaigns, start=1):
        cloud, traj = read_las(camp.laz), read_trajectory(camp.trajectory)
        footprints = read_footprints(root / "footprints.geojson", crs=cloud.crs)
        m = refine_map(m, cloud, traj, footprints, FacadeParams(), RefineParams(), camp.id, seed=0)
        campaigns = [c.id for c in truth.campaigns[:1 if fixed else k]]
        s = facade_scores.score_map(list(m.buildings.values()), truth, campaigns)
        drop = " DROP" if previous is not None and s.f1 < previous - 1e-12 else ""
        out.append(f"seed {truth.doc['seed']} after {k} ({facade_scores._setup(truth.doc['campaigns'][k - 1])}): "
                   f"W+D F1 {s.f1:.3f}, windows {s.window['tp']}/{s.window['fp']}/{s.window['fn']}, doors "
                   f"{s.door['tp']}/{s.door['fp']}/{s.door['fn']} (tp/fp/fn), door F1 {facade_scores._door_f1(s):.3f}"
                   f"{drop}")
        out += error_lines(m, truth, campaigns)
        previous = s.f1
    return out


def by_campaign(lines: list[str]) -> list[list[str]]:
    """The error lines of one scene's :func:`diagnose` output, one list per campaign (split at the score lines)."""
    out: list[list[str]] = []
    for line in lines:
        if line.startswith("seed "):
            out.append([])
        elif out:
            out[-1].append(line)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", required=True, help="comma-separated development seeds")
    ap.add_argument("--family", default="hard", choices=("hard", "standard"))
    ap.add_argument("--campaigns", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None, help="keep (or reuse) the simulated scenes under this folder")
    ap.add_argument("--summary", action="store_true", help="end with the errors counted by class (error_class)")
    ap.add_argument("--fixed", action="store_true", help="score every campaign on the openings campaign 1 saw")
    args = ap.parse_args(argv)
    seeds = [int(x) for x in args.seeds.split(",")]
    reserved = sorted(set(seeds) & set(EVAL_SEEDS))
    if reserved:
        ap.error(f"seeds {reserved} are reserved for evaluation (lidarmap.sim.family.EVAL_SEEDS): not diagnosed")
    scenes: list[list[list[str]]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            root = (args.keep or Path(tmp)) / f"{args.family}{seed}"
            if not (root / "truth" / "scene.json").exists():
                simulate(str(root), family_params(args.family, seed, campaigns=args.campaigns))
            lines = diagnose(root, args.fixed)
            print("\n".join(lines), flush=True)
            scenes.append(by_campaign(lines))
    if args.summary:
        print("\n".join(["", f"errors by class over {len(scenes)} scenes:"] + summary(scenes)))


if __name__ == "__main__":
    main()
