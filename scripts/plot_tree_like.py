"""Picture of the tree-like rule and the vegetation filter on AHN3 Delft: ``python scripts/plot_tree_like.py [--data DIR]``.

Writes ``docs/images/tree_like_delft.png``, three top views of the whole tile (x to the east, metres from the
tile's corner; the recipe's held-out strip right of the dashed line):

1. the tree-like rule (:func:`lidarmap.segment.vegetation.tree_like`) on the delivered labels: what it picks (green)
   against class 6 (dark grey) and the rest (light grey): does it pick trees?
2. the shipped PointNet++ without the vegetation filter, labels removed: tree-like points it calls building (red);
3. the same with the filter (the default): tree-like points still called building (red), labelled building points
   the filter took away (blue).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lidarmap.segment import recipe  # noqa: E402
from lidarmap.segment.blocks import hide_labels  # noqa: E402
from lidarmap.segment.modelfile import load_model  # noqa: E402
from lidarmap.segment.predict import PredictParams, predict, without_vegetation  # noqa: E402
from lidarmap.segment.vegetation import tree_like_cloud  # noqa: E402

IMAGE = Path(__file__).resolve().parents[1] / "docs" / "images" / "tree_like_delft.png"


def panel(ax, xy: np.ndarray, classes: np.ndarray, layers: list[tuple[np.ndarray, str, str]], title: str,
          strip: float) -> None:
    """Background (class 6 dark, the rest light, every 4th point), then the highlighted layers."""
    step = slice(None, None, 4)
    ax.scatter(xy[step, 0], xy[step, 1], s=0.05, c=np.where(classes[step] == 6, "0.45", "0.85"), rasterized=True)
    for mask, colour, label in layers:
        ax.scatter(xy[mask, 0], xy[mask, 1], s=0.15, c=colour, label=f"{label} ({int(mask.sum()):,})",
                   rasterized=True)
    ax.axvline(strip, color="k", linestyle="--", linewidth=0.8)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="lower left", fontsize=8, markerscale=12)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="the shared real data folder")
    parser.add_argument("--out", type=Path, default=IMAGE)
    args = parser.parse_args(argv)
    cloud = recipe.read(recipe.DELFT, args.data)
    classes = cloud.attrs["classification"]
    xy = cloud.xyz[:, :2] - cloud.xyz[:, :2].min(axis=0)
    trees = tree_like_cloud(cloud)
    hidden = hide_labels(cloud)
    params = PredictParams(threads=2)
    raw = predict(hidden, load_model(), dataclasses.replace(params, vegetation=False))
    filtered = without_vegetation(hidden, raw, params)
    strip = recipe.HOLDOUT_STRIPS[recipe.DELFT]
    fig, axes = plt.subplots(1, 3, figsize=(21, 8.5))
    panel(axes[0], xy, classes, [(trees, "tab:green", "tree-like")], "tree-like rule on the delivered labels", strip)
    panel(axes[1], xy, classes, [(trees & (raw >= 0.5), "tab:red", "tree-like called building")],
          f"shipped model, no filter: tree-like FP {(raw[trees] >= 0.5).mean():.3f}", strip)
    taken = (classes == 6) & (raw >= 0.5) & (filtered < 0.5)
    panel(axes[2], xy, classes, [(trees & (filtered >= 0.5), "tab:red", "tree-like called building"),
                                 (taken, "tab:blue", "class 6 taken by the filter")],
          f"with the vegetation filter: tree-like FP {(filtered[trees] >= 0.5).mean():.3f}", strip)
    fig.suptitle("AHN3 Delft (real data, labels removed before predicting); dashed: the held-out strip starts",
                 fontsize=11)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80, bbox_inches="tight")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
