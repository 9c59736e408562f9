"""Reproduce the shipped segmentation models: ``python scripts/train_segmentation.py [--out-dir DIR]``.

Trains, from the recipe in :mod:`lidarmap.segment.recipe` (real labelled data of ``../shared/data`` minus the
held-out areas; the held-out points never reach training, not even as block context):

* the PointNet++ model -> ``lidarmap/weights/segment_pointnet2.pt``
* the gradient-boosting baseline -> ``lidarmap/weights/segment_baseline.joblib``

Same data, seed and thread count give the same weights. One line per epoch goes to stdout (loss, learning rate,
elapsed seconds, validation scores every ``val_every`` epochs). ``--config FILE`` overrides training parameters
(``[segment_train]`` / ``[segment_baseline]`` tables) for experiments; the shipped models use none.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lidarmap.config import load_toml, resolve
from lidarmap.segment import recipe
from lidarmap.segment.baseline import BaselineParams, save_baseline, train_baseline
from lidarmap.segment.modelfile import MODELS_DIR, save_model
from lidarmap.segment.train import TrainParams, train


def log(text: str) -> None:
    print(text, flush=True)


def epoch_line(entry: dict) -> str:
    if "averaged" in entry:  # the weights averaged over the last epochs (swa_epochs)
        line = f"average of the last {entry['averaged']} epochs  {entry['seconds']:7.1f} s"
    else:
        line = f"epoch {entry['epoch']:3d}  loss {entry['loss']:.4f}  lr {entry['lr']:.5f}  {entry['seconds']:7.1f} s"
    val = entry.get("val")
    if val:
        line += (f"  val OA {val['overall_accuracy']:.4f}  building IoU {val['iou']['building']:.4f}"
                 f"  mIoU {val['miou']:.4f}")
    return line


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=MODELS_DIR, help="where the model files go")
    parser.add_argument("--data", type=Path, default=None, help="the shared real data folder (default: "
                        "$LIDARMAP_DATA, else ../shared/data from the working directory)")
    parser.add_argument("--config", type=Path, default=None, help="TOML overrides (experiments only)")
    parser.add_argument("--only", choices=("pointnet2", "baseline"), default=None, help="train one model only")
    parser.add_argument("--vegetation-labels", action="store_true", help="label the tree-like points of the training "
                        "parts high vegetation (not-building); experiments only, the shipped models use none")
    args = parser.parse_args(argv)

    config = load_toml(args.config)
    data = recipe.load(args.data, vegetation_labels=args.vegetation_labels)
    log(f"training clouds: {', '.join(f'{n} ({len(c):,} pts)' for n, c in data.train)}")
    log(f"held out (never read by training): {', '.join(n for n, _ in data.held_out)}")
    args.out_dir.mkdir(parents=True, exist_ok=True)

    if args.only in (None, "pointnet2"):
        params = resolve(TrainParams, config) if config else recipe.PARAMS
        log(f"pointnet2 parameters: {json.dumps(params.__dict__)}")
        result = train(data.train, params, arch=recipe.ARCH, source_weights=recipe.source_weights(data.train),
                       report=lambda entry: log(epoch_line(entry)))
        path = save_model(args.out_dir / "segment_pointnet2.pt", result.model)
        training = result.model.training
        log(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) after {training['seconds']:.0f} s on "
            f"{training['device']} with {training['threads']} threads")

    if args.only in (None, "baseline"):
        params_b = resolve(BaselineParams, config) if config else BaselineParams()
        started = time.perf_counter()
        model = train_baseline(data.train, params_b, source_weights=recipe.source_weights(data.train))
        path = save_baseline(args.out_dir / "segment_baseline.joblib", model)
        log(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) after {time.perf_counter() - started:.0f} s, "
            f"{model.training['samples']:,} samples")


if __name__ == "__main__":
    main(sys.argv[1:])
