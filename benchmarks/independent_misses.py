"""What the map gets wrong on one independent scene, façade by façade: the openings it misses or invents (as
benchmarks/cityjson_scores.py matches them), listed, and one PNG per façade with errors: the campaign's points in
(s, t) coloured by depth, truth openings (black), predicted windows (blue) and doors (red).

``python benchmarks/independent_misses.py SCENE_DIR EXPORT.city.json --key 1-2 [--campaigns 1,2] [--png OUT_DIR]``

For diagnosis on development seeds only (a reserved seed's folder is refused: its ``truth.json`` names the seed).
A hard-family scene of bench_independent's work folder (``hard_SEED``, its ``truth_independent.json``) works too;
its seed comes from the folder's name.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import cityjson_scores as cs  # noqa: E402


def _points(scene: Path, campaigns: list[int]) -> np.ndarray:
    import laspy

    parts = []
    for c in campaigns:
        las = laspy.read(scene / f"mls_{c}.laz")
        parts.append(np.column_stack([las.x, las.y, las.z]))
    return np.vstack(parts)


def _plot(path: Path, f: cs.TruthFacade, sdt: np.ndarray, truth: list, preds: list, missed: set) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    keep = ((sdt[:, 0] > -1) & (sdt[:, 0] < f.width + 1) & (sdt[:, 1] > -1) & (sdt[:, 1] < f.height + 2)
            & (np.abs(sdt[:, 2]) < 1.0))
    fig, ax = plt.subplots(figsize=(max(6.0, f.width * 0.8), max(5.0, f.height * 0.8)))
    art = ax.scatter(sdt[keep, 0], sdt[keep, 1], c=np.clip(sdt[keep, 2], -0.6, 0.3), s=0.2, cmap="turbo")
    fig.colorbar(art, label="d (m)")
    for o in truth:
        s0, s1, t0, t1 = o.rect
        ax.add_patch(Rectangle((s0, t0), s1 - s0, t1 - t0, fill=False, ec="k", lw=2 if o.id in missed else 1,
                               ls="--" if o.id in missed else "-"))
        ax.text(s0, t1 + 0.05, f"{o.id} {o.subtype} obs {max(o.observed.values(), default=0):.2f}", fontsize=6)
    for kind, poly in preds:
        xs, ys = poly.exterior.xy if poly.geom_type == "Polygon" else poly.convex_hull.exterior.xy
        ax.plot(xs, ys, color="b" if kind == "window" else "r", lw=1)
    ax.set_aspect("equal")
    ax.set_title(f"façade {f.id} (building {f.building_id}), width {f.width:.1f} m")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("export", type=Path)
    ap.add_argument("--key", default="1")
    ap.add_argument("--campaigns", default="1")
    ap.add_argument("--png", type=Path, default=None)
    args = ap.parse_args(argv)
    from lidarmap.sim.family import EVAL_SEEDS as HARD_EVAL_SEEDS
    from lidarmap.sim.independent import EVAL_SEEDS

    # an independent scene's truth, or the one bench_independent wrote for a hard-family scene (folder hard_SEED)
    truth_path = args.scene / "truth.json"
    if truth_path.exists():
        reserved = json.loads(truth_path.read_text()).get("seed") in EVAL_SEEDS
    else:
        truth_path = args.scene / "truth_independent.json"
        tail = args.scene.resolve().name.rsplit("_", 1)[-1]
        reserved = not tail.isdigit() or int(tail) in HARD_EVAL_SEEDS
    if reserved:
        ap.error("reserved evaluation seed (or a scene whose seed is unknown): figures only, no diagnosis")
    truth = cs.load_truth(truth_path)
    doc = json.loads(args.export.read_text())
    facades = list(truth.facades.values())
    placed: dict[int, list] = {f.id: [] for f in facades}
    for pred in cs.read_openings(doc):
        where = cs.place_on_facade(pred, facades)
        if where is None:
            print(f"OFF-FACADE {pred.kind} in building {pred.building}")
        else:
            placed[where[0]].append((pred.kind, where[1]))
    xyz = _points(args.scene, [int(c) for c in args.campaigns.split(",")]) if args.png else None
    for f in facades:
        openings = [o for o in truth.openings if o.facade_id == f.id]
        score = cs.score_facade(placed[f.id], openings, args.key, 0.6, 0.5)
        if not score.missed and not score.false:
            continue
        print(f"façade {f.id} (building {f.building_id}): tp {score.all.tp} fp {score.all.fp} fn {score.all.fn}")
        for o in openings:
            if o.id in score.missed:
                print(f"  MISS {o.id} {o.kind}/{o.subtype} rect {np.round(o.rect, 2).tolist()} "
                      f"observed {o.observed.get(args.key, 0):.2f}")
        for _, kind, bounds in score.false:
            print(f"  FALSE {kind} bounds {bounds}")
        if args.png:
            args.png.mkdir(parents=True, exist_ok=True)
            _plot(args.png / f"facade_{f.id}.png", f, f.to_facade(xyz), openings, placed[f.id], set(score.missed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
