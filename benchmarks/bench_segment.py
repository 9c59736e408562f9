"""Building segmentation: held-out real accuracy, wall recall on a simulated scene, CPU inference throughput.

``python benchmarks/bench_segment.py [--model FILE] [--baseline-model FILE] [--sim-seed N]``

PointNet++ (the shipped model) against the named baseline, the geometric-feature gradient-boosting classifier
(shipped too), in the same run on the same data:

* held-out real data of :mod:`lidarmap.segment.recipe` (never used in training), input labels removed (every point
  class 1, so height above ground comes from the estimated ground), scored on the points the data labels
  (class 6 = building, other labelled classes = not; class 1 is not scored), per part and in total;
* a simulated city (``lidarmap.sim``, a seed never used in training), delivered labels kept as input: recall of the
  true building points the input left unlabelled (80 % of wall points, 12 % of roof area), walls and roofs apart,
  and OA / building IoU of the output classes against the simulator's truth on every point;
* throughput: input points per second of ``predict`` (features, windows with their overlap, network), 2 threads.

Targets: held-out OA >= 0.96 and building IoU >= 0.90; wall recall >= 0.85; >= 50,000 points/s.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "2")
os.environ.setdefault("MKL_NUM_THREADS", "2")

import numpy as np  # noqa: E402

from lidarmap.io.las import read_las  # noqa: E402
from lidarmap.segment import recipe  # noqa: E402
from lidarmap.segment.baseline import load_baseline  # noqa: E402
from lidarmap.segment.blocks import hide_labels  # noqa: E402
from lidarmap.segment.metrics import confusion_matrix, evaluate_classes, scores  # noqa: E402
from lidarmap.segment.modelfile import load_model  # noqa: E402
from lidarmap.segment.predict import PredictParams, apply_classes, predict  # noqa: E402

THREADS = 2
TARGETS = {"oa": 0.96, "iou": 0.90, "wall_recall": 0.85, "throughput": 50_000}
WALL_KINDS = ("wall", "window_reveal", "window_interior", "door", "structure")


def timed_predict(cloud, model, params: PredictParams) -> tuple[np.ndarray, float]:
    started = time.perf_counter()
    prob = predict(cloud, model, params)
    return prob, time.perf_counter() - started


def held_out(models: dict, params: PredictParams) -> tuple[dict, dict]:
    """Scores per (method, part) and seconds per method on the recipe's held-out parts, labels removed."""
    data = recipe.load()
    results: dict[tuple[str, str], dict] = {}
    seconds = {m: 0.0 for m in models}
    points = 0
    for name, cloud in data.held_out:
        hidden = hide_labels(cloud)
        points += len(cloud)
        for method, model in models.items():
            prob, took = timed_predict(hidden, model, params)
            seconds[method] += took
            results[(method, name)] = evaluate_classes(cloud.attrs["classification"], prob >= params.threshold)
    for method in models:
        total = sum(np.asarray(results[(method, n)]["confusion"]["matrix"]) for n, _ in data.held_out)
        results[(method, "total")] = scores(total)
    return results, {"seconds": seconds, "points": points, "parts": [n for n, _ in data.held_out]}


def simulated(models: dict, params: PredictParams, seed: int) -> dict:
    """Recall of unlabelled true building points (walls, roofs) and OA / IoU against truth on a simulated city."""
    from lidarmap.sim import SimParams, load_truth, simulate

    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        result = simulate(tmp, SimParams(seed=seed, campaigns=0))
        cloud = read_las(result.als)
        truth = load_truth(tmp).labels("als")
    given = cloud.attrs["classification"]
    true_building = truth.classification == 6
    unlabelled = np.isin(given, (0, 1)) & true_building
    wall = np.isin(truth.kind, [truth.kind_names.index(k) for k in WALL_KINDS])
    roof = truth.kind == truth.kind_names.index("roof")
    for method, model in models.items():
        prob, took = timed_predict(cloud, model, params)
        classes = apply_classes(given, prob, params.threshold, params.union)
        building = classes == 6
        out[method] = {
            "points": len(cloud), "seconds": took,
            "wall_unlabelled": int((unlabelled & wall).sum()),
            "wall_recall": float(building[unlabelled & wall].mean()),
            "roof_unlabelled": int((unlabelled & roof).sum()),
            "roof_recall": float(building[unlabelled & roof].mean()),
            "unlabelled_recall": float(building[unlabelled].mean()),
            "truth": scores(confusion_matrix(true_building, building)),
            "input": scores(confusion_matrix(true_building, given == 6)),
        }
    return out


def mark(ok: bool) -> str:
    return "yes" if ok else "**no**"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=None, help="PointNet++ model (default: shipped)")
    ap.add_argument("--baseline-model", type=Path, default=None, help="baseline model (default: shipped)")
    ap.add_argument("--sim-seed", type=int, default=101, help="simulated city seed (default 101)")
    args = ap.parse_args()
    models = {"pointnet2": load_model(args.model), "baseline": load_baseline(args.baseline_model)}
    params = PredictParams(threads=THREADS)
    load_before = os.getloadavg()[0]
    real, info = held_out(models, params)
    sim = simulated(models, params, args.sim_seed)
    load_after = os.getloadavg()[0]

    print("## bench_segment\n")
    training = models["pointnet2"].training
    print(f"PointNet++ = the shipped model (`{Path(models['pointnet2'].source).name}`, trained "
          f"{training.get('epochs', '?')} epochs in {training.get('seconds', 0) / 60:.0f} min on "
          f"{training.get('device', '?')}); **baseline** = geometric features + gradient boosting "
          f"(`{Path(models['baseline'].source).name}`). Both trained by `scripts/train_segmentation.py` on the same "
          f"recipe. {THREADS} torch/BLAS threads; machine load average {load_before:.1f} before, {load_after:.1f} after "
          f"(shared 2-core machine: timings are noisy, compare the two methods).\n")
    print("### Held-out real data, input labels removed\n")
    print("Held out by `lidarmap/segment/recipe.py` (whole areas, never seen in training, not even as context). "
          "Scored on labelled points (class 1 = unlabelled is not scored).\n")
    print("| part | method | scored points | OA | building IoU | not-building IoU | mIoU | building P | building R |")
    print("|---|---|---|---|---|---|---|---|---|")
    for part in [*info["parts"], "total"]:
        for method in models:
            s = real[(method, part)]
            label = f"**{part}**" if part == "total" else part
            print(f"| {label} | {method} | {s['points']:,} | {s['overall_accuracy']:.4f} | {s['iou']['building']:.4f} | "
                  f"{s['iou']['not-building']:.4f} | {s['miou']:.4f} | {s['building_precision']:.4f} | "
                  f"{s['building_recall']:.4f} |")
    tot = real[("pointnet2", "total")]
    print(f"\nTargets (PointNet++, total): OA >= {TARGETS['oa']:.2f}: {mark(tot['overall_accuracy'] >= TARGETS['oa'])} "
          f"({tot['overall_accuracy']:.4f}); building IoU >= {TARGETS['iou']:.2f}: "
          f"{mark(tot['iou']['building'] >= TARGETS['iou'])} ({tot['iou']['building']:.4f}).\n")

    print(f"### Simulated city (seed {args.sim_seed}), delivered labels as input\n")
    first = next(iter(sim.values()))
    print(f"{first['points']:,} ALS points; true building points left unlabelled by the input: "
          f"{first['wall_unlabelled']:,} on walls, {first['roof_unlabelled']:,} on roofs. Output classes (model "
          f"building where p >= 0.5; input 6 kept only if the model agrees) against the truth on every point; "
          f"the input classes alone score OA {first['input']['overall_accuracy']:.4f}, building IoU "
          f"{first['input']['iou']['building']:.4f}.\n")
    print("| method | wall recall | roof-patch recall | all unlabelled recall | OA vs truth | building IoU vs truth |")
    print("|---|---|---|---|---|---|")
    for method, s in sim.items():
        print(f"| {method} | {s['wall_recall']:.4f} | {s['roof_recall']:.4f} | {s['unlabelled_recall']:.4f} | "
              f"{s['truth']['overall_accuracy']:.4f} | {s['truth']['iou']['building']:.4f} |")
    wall = sim["pointnet2"]["wall_recall"]
    print(f"\nTarget (PointNet++): wall recall >= {TARGETS['wall_recall']:.2f}: "
          f"{mark(wall >= TARGETS['wall_recall'])} ({wall:.4f}).\n")

    print(f"### Inference throughput ({THREADS} threads, CPU)\n")
    print("Input points per second of `predict` (features + ground estimate + overlapping windows + network, or "
          "features + classifier), over the held-out parts and the simulated city.\n")
    print("| method | held-out points | s | points/s | simulated points | s | points/s |")
    print("|---|---|---|---|---|---|---|")
    for method in models:
        t_real, t_sim = info["seconds"][method], sim[method]["seconds"]
        print(f"| {method} | {info['points']:,} | {t_real:.1f} | {info['points'] / t_real:,.0f} | "
              f"{sim[method]['points']:,} | {t_sim:.1f} | {sim[method]['points'] / t_sim:,.0f} |")
    rate = info["points"] / info["seconds"]["pointnet2"]
    print(f"\nTarget (PointNet++, held-out): >= {TARGETS['throughput']:,} points/s: "
          f"{mark(rate >= TARGETS['throughput'])} ({rate:,.0f}).")


if __name__ == "__main__":
    sys.exit(main())
