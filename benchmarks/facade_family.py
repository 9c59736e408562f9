"""Issue 18's targets on many scenes of the hard family at once: one line per scene, the targets counted per scene and
pooled, and what the drops between campaigns amount to.

``python benchmarks/facade_family.py --seeds 270-289 [--jobs 2] [--out runs.jsonl] [--family hard]``

``--eval`` is needed to run reserved evaluation seeds (``lidarmap.sim.family.EVAL_SEEDS``): benchmark figures only,
never diagnosis (benchmarks/facade_misses.py refuses them). Each scene is simulated and its campaigns are fused one by
one and scored after each by benchmarks/facade_scores.py (``score_scene``: truth openings at least 90 % seen so far,
IoU >= 0.5, same type). ``--out`` keeps one JSON line per scene as it finishes; a second run with the same file
skips the scenes it holds (a long run can be resumed). Scenes run in ``--jobs`` processes, one thread each; a scene's
result does not depend on which process ran it.

Printed: per-scene W+D F1 and door F1 after each campaign; the pooled figures; how many scenes meet each target of
issue 18 (W+D F1 >= 0.92 after one and >= 0.96 after the last, door F1 >= 0.90 after every campaign, F1 never
lower than after the campaign before); for the scenes whose F1 drops, by how much and by how many openings; the
false openings on blank walls per 500 m² of seen blank wall.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from multiprocessing import get_context
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one thread per process: --jobs processes share the cores

from lidarmap.sim.family import EVAL_SEEDS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import facade_scores  # noqa: E402  (benchmarks/facade_scores.py)

TARGET_FIRST, TARGET_LAST, TARGET_DOOR = 0.92, 0.96, 0.90  # issue 18
COUNTS = ("tp", "fp", "fn")


def parse_seeds(text: str) -> list[int]:
    """``"7001-7010,7015"`` -> [7001, ..., 7010, 7015] (ranges inclusive, order kept, duplicates dropped)."""
    out: list[int] = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        lo, _, hi = part.partition("-")
        first, last = int(lo), int(hi or lo)
        if last < first:
            raise ValueError(f"seed range {part!r} runs backwards")
        out += [s for s in range(first, last + 1) if s not in out]
    return out


def _counts(s) -> dict:
    return {"all": [s.tp, s.fp, s.fn], "door": [s.door[k] for k in COUNTS], "window": [s.window[k] for k in COUNTS],
            "false_blank": s.false_blank, "blank_area": round(s.blank_area, 2)}


def scene_record(family: str, seed: int) -> dict:
    """One scene simulated, fused campaign by campaign and scored (JSON-ready): counts after each campaign against
    the openings seen so far (``after``) and against those the first campaign saw (``fixed``)."""
    run = facade_scores.run_scene(family, seed, fixed=True)
    return {"family": family, "seed": seed, "points": run.points, "seconds": [round(s, 2) for s in run.seconds],
            "after": [_counts(s) for s in run.scores], "fixed": [_counts(s) for s in run.fixed],
            "legacy": [_counts(s) for s in run.legacy]}


def f1(counts) -> float:
    tp, fp, fn = counts
    return 2 * tp / max(1, 2 * tp + fp + fn)


def scene_f1(rec: dict, key: str = "all", truth: str = "after") -> list[float]:
    return [f1(a[key]) for a in rec[truth]]


def drops(rec: dict, truth: str = "after") -> list[tuple[int, float, int]]:
    """(campaign, F1 lost, openings lost) for every campaign after which the scene's W+D F1 is lower than before;
    openings lost = rise in fp + fn (each wrong or missed opening counts once; a retyped one counts twice).
    ``truth``: "after" (the openings seen so far) or "fixed" (those the first campaign saw)."""
    out = []
    for k in range(1, len(rec[truth])):
        before, now = rec[truth][k - 1]["all"], rec[truth][k]["all"]
        lost = f1(before) - f1(now)
        if lost > 1e-12:
            out.append((k + 1, lost, (now[1] + now[2]) - (before[1] + before[2])))
    return out


def pooled(records: list[dict], k: int, key: str = "all", truth: str = "after") -> list[int]:
    return [sum(r[truth][k][key][i] for r in records) for i in range(3)]


def _drop_line(records: list[dict], truth: str) -> str:
    every = [x for r in records for x in drops(r, truth)]
    if not every:
        return "none"
    lost = sorted(o for _, _, o in every)
    return (f"{len(every)} in {sum(bool(drops(r, truth)) for r in records)} scenes; F1 lost median "
            f"{sorted(x for _, x, _ in every)[len(every) // 2]:.3f}, largest {max(x for _, x, _ in every):.3f}; "
            "openings lost (fp + fn) per drop: " + ", ".join(f"{o:+d}: {lost.count(o)}" for o in sorted(set(lost))))


def summary(records: list[dict]) -> str:
    """The markdown of the module docstring for ``records`` (scene_record dicts, any order)."""
    records = sorted(records, key=lambda r: (r["family"], r["seed"]))
    n = min(len(r["after"]) for r in records)
    has_fixed = all(r.get("fixed") for r in records)
    lines = ["| seed | W+D F1 after " + " / ".join(str(k + 1) for k in range(n))
             + (" | on the first campaign's openings" if has_fixed else "") + " | door F1 | drops |",
             "|---|---|---|---|" + ("---|" if has_fixed else "")]
    for r in records:
        cells = [scene_f1(r)[:n]] + ([scene_f1(r, truth="fixed")[:n]] if has_fixed else []) + [scene_f1(r, "door")[:n]]
        lines.append(f"| {r['seed']} | " + " | ".join(" / ".join(f"{x:.3f}" for x in c) for c in cells) + " | "
                     + ", ".join(f"after {k}: -{lost:.3f} ({o:+d})" for k, lost, o in drops(r)) + " |")
    after = [pooled(records, k) for k in range(n)]
    doors = [pooled(records, k, "door") for k in range(n)]
    fixed = [pooled(records, k, truth="fixed") for k in range(n)] if has_fixed else []
    pooled_cells = [" / ".join(f"{f1(a):.4f}" for a in rows) for rows in (after, fixed) if rows]
    lines.append(f"| **pooled ({len(records)})** | " + " | ".join(f"**{c}**" for c in pooled_cells)
                 + f" | **{' / '.join(f'{f1(d):.3f}' for d in doors)}** | |")
    false = [sum(r["after"][k]["false_blank"] for r in records) for k in range(n)]
    area = [sum(r["after"][k]["blank_area"] for r in records) for k in range(n)]
    falling = [r for r in records if drops(r)]
    lines += ["", f"Scenes: {len(records)} ({', '.join(sorted({r['family'] for r in records}))}), {n} campaigns.",
              "- Pooled W+D F1 after each campaign: " + " -> ".join(f"{f1(a):.4f}" for a in after)
              + f" (tp/fp/fn after 1: {'/'.join(map(str, after[0]))}; after {n}: {'/'.join(map(str, after[-1]))}).",
              "- Pooled door F1 after each campaign: " + " -> ".join(f"{f1(d):.3f}" for d in doors) + ".",
              f"- Per scene: W+D F1 >= {TARGET_FIRST} after 1: "
              f"{sum(scene_f1(r)[0] >= TARGET_FIRST for r in records)}/{len(records)}; >= {TARGET_LAST} after {n}: "
              f"{sum(scene_f1(r)[n - 1] >= TARGET_LAST for r in records)}/{len(records)}; door F1 >= {TARGET_DOOR} "
              f"after every campaign: {sum(min(scene_f1(r, 'door')[:n]) >= TARGET_DOOR for r in records)}"
              f"/{len(records)}; never decreasing: {len(records) - len(falling)}/{len(records)}.",
              f"- Drops: {_drop_line(records, 'after')}."]
    if fixed:
        steady = sum(not drops(r, "fixed") for r in records)
        lines += ["- On the openings the first campaign saw (a truth set that does not grow), pooled W+D F1: "
                  + " -> ".join(f"{f1(a):.4f}" for a in fixed) + f" (tp/fp/fn after 1: {'/'.join(map(str, fixed[0]))};"
                  f" after {n}: {'/'.join(map(str, fixed[-1]))}); never decreasing {steady}/{len(records)}; drops: "
                  f"{_drop_line(records, 'fixed')}."]
    if all(r.get("legacy") for r in records):
        legacy = [pooled(records, k, truth="legacy") for k in range(n)]
        lines += ["- By the scorer before 2026-12-03 (a window over a hardly visible door counted false), pooled W+D "
                  "F1: " + " -> ".join(f"{f1(a):.4f}" for a in legacy) + f"; never decreasing "
                  f"{sum(not drops(r, 'legacy') for r in records)}/{len(records)}; drops: "
                  f"{_drop_line(records, 'legacy')}."]
    lines += [
              "- False openings on blank walls after each campaign: " + " / ".join(
                  f"{c} on {a:,.0f} m² ({500 * c / a:.2f} per 500 m²)" if a else f"{c} on 0 m²"
                  for c, a in zip(false, area)) + "."]
    return "\n".join(lines) + "\n"


def _run(job: tuple[str, int]) -> dict:
    return scene_record(*job)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", required=True, help="seeds and inclusive ranges, e.g. 270-289,301")
    ap.add_argument("--family", default="hard", choices=("hard", "standard"))
    ap.add_argument("--eval", action="store_true", help="allow reserved evaluation seeds (benchmark figures only)")
    ap.add_argument("--jobs", type=int, default=2, help="scenes run at once, one process each")
    ap.add_argument("--out", type=Path, default=None, help="JSON lines, one per scene; scenes already there are skipped")
    args = ap.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        ap.error(f"--seeds: {exc}")
    reserved = sorted(set(seeds) & set(EVAL_SEEDS))
    if reserved and not args.eval:
        ap.error(f"seeds {reserved[0]}..{reserved[-1]} are reserved for evaluation: pass --eval for benchmark figures")
    if args.jobs < 1:
        ap.error("--jobs must be at least 1")
    done = {}
    if args.out is not None and args.out.exists():
        done = {(r["family"], r["seed"]): r for r in map(json.loads, args.out.read_text().splitlines()) if r}
    todo = [(args.family, s) for s in seeds if (args.family, s) not in done]
    records = [done[(args.family, s)] for s in seeds if (args.family, s) in done]
    with get_context("spawn").Pool(args.jobs, maxtasksperchild=1) as pool:
        for rec in pool.imap_unordered(_run, todo):
            records.append(rec)
            print(f"seed {rec['seed']}: W+D F1 " + " / ".join(f"{x:.3f}" for x in scene_f1(rec)), file=sys.stderr,
                  flush=True)
            if args.out is not None:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(rec) + "\n")
    print(summary(records))


if __name__ == "__main__":
    main()
