"""``lidarmap segment train|predict|evaluate``: building / not-building segmentation of aerial point clouds.

Inputs are LAS/LAZ files or prep output folders (``lidarmap prep``); a prep folder is segmented as one cloud (all its
buildings together, so each building sees its neighbours as context) and written back building by building.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from lidarmap.cli.common import (
    ConfigOption,
    CrsOption,
    SeedOption,
    console,
    handle_errors,
    params_from,
    progress,
)
from lidarmap.errors import ConfigError, InputError

segment_app = typer.Typer(name="segment", no_args_is_help=True, add_completion=False,
                          help="Building segmentation: PointNet++ (shipped model) or a gradient-boosting baseline.")

METHOD_HELP = "pointnet2 (default) or baseline (geometric features + gradient boosting)."
MODEL_HELP = "Model file (default: the shipped model of the method; a .joblib file implies --method baseline)."
DEVICE_HELP = "cpu, cuda or auto (a GPU when there is one)."
VegetationOption = typer.Option(None, "--vegetation/--no-vegetation", help="Drop building points that look like "
                                "vegetation (porous, scattered) after the model (default on; [segment] vegetation).")
#: Files of a prep folder copied next to the segmented buildings, so the output is a prep folder too.
PREP_SIDE_FILES = ("buildings.csv", "frame.json", "prep.json")


def register(app: typer.Typer) -> None:
    """Add ``segment`` (train, predict, evaluate) to the app."""
    app.add_typer(segment_app)


# ----------------------------------------------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Input:
    """One input: a LAS/LAZ file, or a prep folder read as one cloud (``parts``: building file and point count)."""

    path: Path
    cloud: Any  # PointCloud
    parts: list[tuple[Path, int]] | None = None

    @property
    def name(self) -> str:
        return self.path.name if self.parts is None else f"{self.path.name}/"


def read_input(path: Path, crs: str | None) -> Input:
    """Read a LAS/LAZ file, or every building of a prep folder as one cloud."""
    from lidarmap.core import PointCloud
    from lidarmap.io.las import read_las
    from lidarmap.io.prepdir import read_prep_index

    if not path.is_dir():
        return Input(path, read_las(path, crs=crs))
    if not (path / "buildings.csv").exists():
        raise InputError("folder is not a prep output (no buildings.csv); give LAS/LAZ files or a prep folder",
                         path)
    rows = read_prep_index(path)
    if not rows:
        raise InputError("prep output holds no buildings", path)
    clouds = [read_las(row["path"], crs=crs) for row in rows]
    return Input(path, PointCloud.concatenate(clouds), [(row["path"], len(c)) for row, c in zip(rows, clouds)])


def check_inputs(paths: list[Path]) -> None:
    """Refuse missing inputs and inputs given twice before any work starts."""
    seen: set[Path] = set()
    for path in paths:
        if not path.exists():
            raise InputError("file not found", path)
        key = path.resolve()
        if key in seen:
            raise InputError("input given twice", path)
        seen.add(key)


def load_segmenter(method: str | None, model: Path | None) -> tuple[str, Any]:
    """The method and its model (the shipped one when ``model`` is None)."""
    from lidarmap.segment.baseline import load_baseline
    from lidarmap.segment.modelfile import load_model
    from lidarmap.segment.predict import METHODS

    if method is None:
        method = "baseline" if model is not None and model.suffix == ".joblib" else "pointnet2"
    if method not in METHODS:
        raise ConfigError(f"unknown --method {method!r} (known: {', '.join(METHODS)})")
    return method, load_baseline(model) if method == "baseline" else load_model(model)


def _predict_params(config: Path | None, **flags: Any) -> Any:
    from lidarmap.segment.predict import PredictParams

    return params_from(PredictParams, config, **flags)


def _predict_with_bar(cloud: Any, model: Any, params: Any, description: str) -> Any:
    from lidarmap.segment.predict import predict

    with progress(transient=True) as bar:
        task = bar.add_task(description, total=None)
        return predict(cloud, model, params, lambda done, total: bar.update(task, completed=done, total=total))


# ----------------------------------------------------------------------------------------------------------------
# predict
# ----------------------------------------------------------------------------------------------------------------


#: Kind of the output-folder marker of ``segment predict`` (:mod:`lidarmap.io.outdir`).
PREDICT_KIND = "segment-predict"


def output_paths(item: Input, out_dir: Path) -> list[Path]:
    """Where the segmented input goes: OUT/<file name> (suffix .laz), or OUT/<prep folder>/buildings/<file>."""
    if item.parts is None:
        return [out_dir / f"{item.path.stem}.laz"]
    return [out_dir / item.path.name / "buildings" / part.name for part, _ in item.parts]


@segment_app.command("predict")
@handle_errors
def predict_command(
    inputs: list[Path] = typer.Argument(..., help="LAS/LAZ files and/or prep output folders."),
    out_dir: Path = typer.Option(..., "--out", "-o", help="Output folder (one LAZ per input file; a prep folder "
                                 "becomes OUT/<folder>/ with its index; created, or an empty folder or an earlier "
                                 "predict output: files of yours there are never replaced).", file_okay=False),
    method: Optional[str] = typer.Option(None, "--method", "-m", help=METHOD_HELP),
    model: Optional[Path] = typer.Option(None, "--model", help=MODEL_HELP, dir_okay=False),
    union: Optional[bool] = typer.Option(None, "--union/--no-union", help="Keep input class-6 points as building "
                                         "whatever the model says."),
    threshold: Optional[float] = typer.Option(None, "--threshold", help="Building probability threshold "
                                              "(default 0.5)."),
    vegetation: Optional[bool] = VegetationOption,
    write_vegetation: Optional[bool] = typer.Option(None, "--write-vegetation/--no-write-vegetation", help="Also "
                                                    "write class 5 (high vegetation) for confident vegetation "
                                                    "points (default off; [segment] write_vegetation)."),
    seed: Optional[int] = SeedOption,
    device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Classify building points: class 6 where predicted (class 5 for confident vegetation with
    --write-vegetation), extra dimension building_probability; order kept."""
    from lidarmap.io.atomic import write_text_atomic
    from lidarmap.io.las import write_las
    from lidarmap.io.outdir import atomic_out_dir, claim_out_dir
    from lidarmap.segment.predict import segmented_cloud

    params = _predict_params(config, union=union, threshold=threshold, seed=seed, device=device,
                             vegetation=vegetation, write_vegetation=write_vegetation)
    check_inputs(inputs)
    items = [Input(path, None, _prep_parts(path)) for path in inputs]
    sources = {p.resolve() for item in items for p in ([item.path] if item.parts is None else
                                                        [item.path / n for n in PREP_SIDE_FILES] +
                                                        [part for part, _ in item.parts])}
    planned: dict[Path, Path] = {}
    for item in items:  # name clashes and overwriting an input are refused before any work
        for target in output_paths(item, out_dir):
            key = target.resolve()
            if key in planned:
                raise InputError(f"two inputs would write the same output {target} (also {planned[key]})",
                                 item.path)
            if key in sources:
                raise InputError("output would overwrite an input; choose another -o", target)
            planned[key] = item.path
    claim_out_dir(out_dir, PREDICT_KIND)  # before any work: a foreign folder is refused at once
    method, segmenter = load_segmenter(method, model)
    table = Table(title=f"segment predict ({method}) into {out_dir}", title_justify="left")
    for column in ("input", "points", "building points", "output"):
        table.add_column(column, justify="left" if column in ("input", "output") else "right")
    # written into a temporary folder published at the end (like the stage commands): an error leaves out_dir as
    # it was; earlier predict outputs there stay (replace=False), files of the user's are never replaced
    with atomic_out_dir(out_dir, PREDICT_KIND, replace=False) as tmp:
        for path in inputs:
            item = read_input(path, crs)
            probability = _predict_with_bar(item.cloud, segmenter, params, f"segmenting {item.name}")
            result = segmented_cloud(item.cloud, probability, params)
            targets = output_paths(item, tmp)
            if item.parts is None:
                write_las(targets[0], result)
            else:
                start = 0
                for target, (_, count) in zip(targets, item.parts):
                    write_las(target, result.subset(slice(start, start + count)))
                    start += count
                for name in PREP_SIDE_FILES:
                    if (item.path / name).exists():
                        write_text_atomic(tmp / item.path.name / name, (item.path / name).read_text("utf-8"))
            building = int((result.attrs["classification"] == 6).sum())
            shown = output_paths(item, out_dir)
            table.add_row(item.name, f"{len(result):,}", f"{building:,}",
                          str(shown[0] if item.parts is None else shown[0].parent.parent))
    console.print(table)


def _prep_parts(path: Path) -> list[tuple[Path, int]] | None:
    """The building files of a prep folder (counts from its index), None for a file."""
    from lidarmap.io.prepdir import read_prep_index

    if not path.is_dir():
        return None
    if not (path / "buildings.csv").exists():
        raise InputError("folder is not a prep output (no buildings.csv); give LAS/LAZ files or a prep folder",
                         path)
    return [(row["path"], row["points"]) for row in read_prep_index(path)]


# ----------------------------------------------------------------------------------------------------------------
# evaluate
# ----------------------------------------------------------------------------------------------------------------


@segment_app.command("evaluate")
@handle_errors
def evaluate_command(
    inputs: list[Path] = typer.Argument(..., help="Labelled LAS/LAZ files and/or prep output folders."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help=METHOD_HELP),
    model: Optional[Path] = typer.Option(None, "--model", help=MODEL_HELP, dir_okay=False),
    keep_labels: bool = typer.Option(False, "--keep-labels", help="Let the model see the input classes (ground "
                                     "class 2 for height above ground); default: labels removed first."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (for scripts)."),
    vegetation: Optional[bool] = VegetationOption,
    seed: Optional[int] = SeedOption,
    device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Score the model on labelled points (class 6 = building, other labelled classes = not; 0/1 not scored) and
    on every point: the share of tree-like points predicted building, the share of added building points that are
    tree-like (docs/segmentation.md)."""
    import numpy as np

    from lidarmap.segment.blocks import hide_labels
    from lidarmap.segment.metrics import (
        combine_tree_scores,
        evaluate_classes,
        scores,
        tree_scores,
    )
    from lidarmap.segment.vegetation import tree_like_cloud

    params = _predict_params(config, seed=seed, device=device, vegetation=vegetation)
    check_inputs(inputs)
    method, segmenter = load_segmenter(method, model)
    report: dict[str, Any] = {"method": method, "labels_removed": not keep_labels, "inputs": {}}
    total = np.zeros((2, 2), np.int64)
    for path in inputs:
        item = read_input(path, crs)
        truth = item.cloud.attrs.get("classification")
        if truth is None:
            raise InputError("has no classification to evaluate against", path)
        cloud = item.cloud if keep_labels else hide_labels(item.cloud)
        probability = _predict_with_bar(cloud, segmenter, params, f"segmenting {item.name}")
        result = evaluate_classes(truth, probability >= params.threshold)
        if result["points"] == 0:
            raise InputError("has no labelled points (all class 0/1): nothing to evaluate", path)
        result["trees"] = tree_scores(tree_like_cloud(item.cloud), truth, probability >= params.threshold)
        report["inputs"][str(path)] = result
        total += np.asarray(result["confusion"]["matrix"], np.int64)
    report["total"] = scores(total)
    report["total"]["trees"] = combine_tree_scores([r["trees"] for r in report["inputs"].values()])
    if as_json:
        typer.echo(json.dumps(report))
        return
    _print_scores(report)


def _print_scores(report: dict[str, Any]) -> None:
    table = Table(title=f"segment evaluate ({report['method']}, labels "
                  f"{'removed' if report['labels_removed'] else 'kept'})", title_justify="left")
    for column in ("input", "points", "OA", "IoU bldg", "IoU other", "mIoU", "TN FP / FN TP"):
        table.add_column(column, justify="left" if column == "input" else "right")
    rows = list(report["inputs"].items()) + ([("total", report["total"])] if len(report["inputs"]) > 1 else [])
    for name, s in rows:
        table.add_row(Path(name).name if name != "total" else "[bold]total[/]", f"{s['points']:,}",
                      f"{s['overall_accuracy']:.4f}", f"{s['iou']['building']:.4f}",
                      f"{s['iou']['not-building']:.4f}", f"{s['miou']:.4f}", _confusion(s["confusion"]["matrix"]))
    console.print(table)
    trees = Table(title="every point: tree-like points (docs/segmentation.md) called building", title_justify="left")
    for column in ("input", "tree-like", "called building", "added building", "of which tree-like"):
        trees.add_column(column, justify="left" if column == "input" else "right")
    for name, s in rows:
        t = s["trees"]
        trees.add_row(Path(name).name if name != "total" else "[bold]total[/]", f"{t['tree_like_points']:,}",
                      _share(t["tree_like_false_positive_rate"]), f"{t['added_points']:,}",
                      _share(t["added_tree_like_share"]))
    console.print(trees)


def _share(value: float) -> str:
    """A share with 4 decimals; '-' when there was nothing to share (nan)."""
    return "-" if math.isnan(value) else f"{value:.4f}"


def _confusion(matrix: list[list[int]]) -> str:
    (tn, fp), (fn, tp) = matrix
    return f"{tn:,} {fp:,} / {fn:,} {tp:,}"


# ----------------------------------------------------------------------------------------------------------------
# train
# ----------------------------------------------------------------------------------------------------------------


@segment_app.command("train")
@handle_errors
def train_command(
    inputs: list[Path] = typer.Argument(..., help="Labelled LAS/LAZ files and/or prep folders to learn from."),
    out: Path = typer.Option(..., "--out", "-o", help="Model file to write (.pt for pointnet2, .joblib for "
                             "baseline).", dir_okay=False),
    method: Optional[str] = typer.Option(None, "--method", "-m", help=METHOD_HELP),
    val: Optional[list[Path]] = typer.Option(None, "--val", help="Validation files (default: a seeded spatial "
                                             "split of the inputs). Repeat for several."),
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Training epochs (default 64)."),
    seed: Optional[int] = SeedOption,
    device: Optional[str] = typer.Option(None, "--device", help=DEVICE_HELP),
    crs: Optional[str] = CrsOption,
    config: Optional[Path] = ConfigOption,
) -> None:
    """Train a model on labelled points (class 6 vs other labelled classes; class 0/1 excluded from the loss)."""
    from lidarmap.segment.baseline import BaselineParams, save_baseline, train_baseline
    from lidarmap.segment.modelfile import save_model
    from lidarmap.segment.predict import METHODS
    from lidarmap.segment.train import TrainParams, train

    method = method or ("baseline" if out.suffix == ".joblib" else "pointnet2")
    if method not in METHODS:
        raise ConfigError(f"unknown --method {method!r} (known: {', '.join(METHODS)})")
    if out.exists() and out.is_dir():
        raise InputError("output is a folder; give a model file name", out)
    check_inputs(inputs + list(val or []))
    clouds = [(str(i.path), i.cloud) for i in (read_input(p, crs) for p in inputs)]
    if method == "baseline":
        params_b = params_from(BaselineParams, config, seed=seed)
        with progress(transient=True) as bar:
            bar.add_task("training baseline", total=None)
            model = train_baseline(clouds, params_b)
        save_baseline(out, model)
        console.print(f"wrote {out} ({model.training['samples']:,} samples, {model.training['seconds']:.0f} s)")
        return
    params = params_from(TrainParams, config, epochs=epochs, seed=seed, device=device)
    val_clouds = [(str(i.path), i.cloud) for i in (read_input(p, crs) for p in val)] if val else None
    with progress() as bar:
        task = bar.add_task("training", total=params.epochs + params.swa_epochs)

        def report(entry: dict[str, Any]) -> None:
            what = (f"average of the last {entry['averaged']} epochs" if "averaged" in entry
                    else f"loss {entry['loss']:.4f}")
            bar.update(task, completed=entry["epoch"], description=f"training ({what})")
            if "val" in entry:
                v = entry["val"]
                bar.console.print(f"epoch {entry['epoch']}: {what}, validation OA "
                                  f"{v['overall_accuracy']:.4f}, building IoU {v['iou']['building']:.4f}")

        result = train(clouds, params, val_clouds, report=report)
    save_model(out, result.model)
    metrics = result.model.training.get("metrics") or {}
    console.print(f"wrote {out} after {result.model.training['seconds']:.0f} s"
                  + (f"; validation OA {metrics['overall_accuracy']:.4f}, building IoU "
                     f"{metrics['iou']['building']:.4f}" if metrics else ""))
