"""The aerial pipeline end to end (``lidarmap run``): tiles + footprints -> one folder of results per building.

::

    prep (stream the tiles chunk by chunk into a spool on disk, per footprint: buildings cut by tile edges are
          assembled whole)
      -> per group of neighbouring buildings, one task (this process, or a dask worker): segmentation of their
         points with the kept points of the buildings around them as context; then per building densify / flatten
         (order configurable) -> voxelize (majority label) -> meshes
      -> this process writes OUT/buildings/<id>/, OUT/summary.json, OUT/buildings.city.json,
         OUT/buildings.gpkg (every footprint with its status, for a GIS)

Memory is bounded by the largest group plus its context, a chunk of input and a few tasks in flight, not by the
input size (docs/cluster.md).

Per building (``OUT/buildings/<id>/``, see docs/pipeline.md): ``points.laz`` (the building's area: every input point
in canonical order (x, y, z, then the attributes: the same however the input was tiled) with its new class and
``building_probability``, building points moved by flattening, removed outliers as class 7, then the new points of
densification with the LAS ``synthetic`` flag), ``voxels.npz`` + ``voxels.vox`` (building voxels, majority label),
``mesh.ply`` + ``mesh.obj`` (CRS, double precision), the other mesh kind as ``mesh_<kind>.ply``, and
``building.json`` (statistics and the fingerprint), written last: a folder without it does not exist (each folder is
written to a temporary folder and renamed into place).

Resumable: a building whose ``building.json`` carries the current fingerprint (its input points, its segmentation
context, the model, every parameter) is skipped. Deterministic: every building draws its random numbers from (seed,
building id), a group's segmentation from (seed, its first building's id), so serial, distributed (dask) and resumed runs write the same results. A
building whose task fails is reported in ``summary.json`` (``failed``: id -> reason) and the others go on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import trimesh
from pyproj import CRS

from lidarmap._version import __version__
from lidarmap.aerial.coverage import CoverageParams, footprint_coverage
from lidarmap.aerial.densify import DensifyParams, densify
from lidarmap.aerial.flatten import FlattenParams, flatten_points
from lidarmap.aerial.gislayer import write_buildings_gpkg
from lidarmap.aerial.mesh import MeshParams, surface_mesh, voxel_mesh
from lidarmap.aerial.prep import (
    BuildingPoints,
    PrepParams,
    PrepResult,
    SpooledPrep,
    spool_chunks,
)
from lidarmap.aerial.voxel import VoxelParams, voxelize
from lidarmap.config import check_params
from lidarmap.core import Footprints, PointCloud, VoxelGrid
from lidarmap.errors import ConfigError, InputError
from lidarmap.export.planar import PlanarParams
from lidarmap.executor import (
    TaskFailure,
    building_seed,
    group_by_cell,
    map_tasks,
    run_task,
)
from lidarmap.io.atomic import atomic_dir, write_text_atomic
from lidarmap.io.las import write_las
from lidarmap.io.meshfile import write_mesh
from lidarmap.io.outdir import abandon_marked_dir, claim_out_dir, start_marked_dir
from lidarmap.io.prepdir import unique_stems
from lidarmap.io.tiles import read_tiles, scan_tiles
from lidarmap.io.voxels import write_vox, write_voxels
from lidarmap.segment.features import BUILDING_CLASS
from lidarmap.segment.predict import PredictParams, apply_classes, predict

log = logging.getLogger(__name__)

__all__ = ["RunParams", "PipelineConfig", "BuildingOutput", "RunResult", "process_building", "run_pipeline",
           "segment_group", "group_task", "GroupJob", "building_groups", "NOISE_CLASS", "STAGES"]

#: Stages that may follow segmentation, in any order.
STAGES = ("densify", "flatten")
#: Class of building points that densification's outlier removal rejects (ASPRS 7: noise).
NOISE_CLASS = 7
MESH_KINDS = ("surface", "voxels")

Report = Callable[[str, int, int], None]


@dataclasses.dataclass(frozen=True)
class RunParams:
    """``lidarmap run`` (``[run]`` table); the stages read their own tables (``[prep]``, ``[segment]``,
    ``[densify]``, ``[flatten]``, ``[voxel]``, ``[mesh]``).

    stages (("densify", "flatten")): what runs on each building's points after segmentation, in this order: any of
        "densify" and "flatten", in either order, or none.
    method ("pointnet2"): segmentation method, "pointnet2" or "baseline" (geometric features + gradient boosting).
    model (""): segmentation model file; "" = the shipped model of the method.
    union (True): points the input classifies as building stay building whatever the model says (the paper's fix
        for large roofs, §4.1); overrides ``[segment] union``.
    min_points (50): a building with fewer building points after segmentation is reported as failed (nothing to
        densify, flatten or mesh) and gets no folder.
    mesh ("surface"): the mesh written as mesh.ply/mesh.obj: "surface" (2.5D reconstruction from the processed
        points: roof height field + walls + floor; accurate, docs/voxel_mesh.md) or "voxels" (watertight voxel
        mesh); the other kind is written as mesh_<kind>.ply.
    mesh_voxel_size (0.5): voxel size (m) of the voxel mesh; the voxel output uses ``[voxel] size``.
    group_size (100.0): buildings whose points' centre falls in the same ``group_size`` x ``group_size`` m cell are
        one task, segmented together (a city of small buildings in one network call per building would cost 2x);
        0 = one building per task. Memory per task: a group plus its context.
    context (16.0): segmentation context (m): each group is segmented with the kept points of the other buildings
        within this distance of its points' bounds (half the shipped model's 32 m block: a window centred on a
        building's edge is full); 0 = the group alone. Results do not depend on what else is in the run.
    workers (1): worker processes on this machine (dask.distributed LocalCluster); 1 = everything in this process.
    scheduler (""): address of a running dask scheduler (e.g. "tcp://10.0.0.5:8786") for multi-machine runs;
        overrides ``workers``. Workers compute, this process writes, so only this machine needs the output folder.
    seed (0): seeds segmentation and every building's random draws.
    """

    section = "run"
    constraints: ClassVar[dict[str, str]] = {
        "method": "in pointnet2, baseline",
        "min_points": ">= 0",
        "mesh": "in surface, voxels",
        "mesh_voxel_size": ">= 0",
        "group_size": ">= 0",
        "context": ">= 0",
        "workers": ">= 0",
        "seed": ">= 0",
    }

    stages: tuple[str, ...] = ("densify", "flatten")
    method: str = "pointnet2"
    model: str = ""
    union: bool = True
    min_points: int = 50
    mesh: str = "surface"
    mesh_voxel_size: float = 0.5
    group_size: float = 100.0
    context: float = 16.0
    workers: int = 1
    scheduler: str = ""
    seed: int = 0

    def __post_init__(self) -> None:
        check_params(self)
        stages = tuple(self.stages)
        object.__setattr__(self, "stages", stages)
        unknown = [s for s in stages if s not in STAGES]
        if unknown or len(set(stages)) != len(stages):
            raise ValueError(f"stages must be distinct names among {', '.join(STAGES)}; got {list(stages)}")
        if self.method not in ("pointnet2", "baseline"):
            raise ValueError("method must be pointnet2 or baseline")
        if self.mesh not in MESH_KINDS:
            raise ValueError(f"mesh must be one of {', '.join(MESH_KINDS)}")
        if self.min_points < 3:
            raise ValueError("min_points must be at least 3")
        if not (math.isfinite(self.mesh_voxel_size) and self.mesh_voxel_size > 0):
            raise ValueError("mesh_voxel_size must be > 0")
        if self.workers < 1:
            raise ValueError("workers must be at least 1")
        if not (math.isfinite(self.context) and self.context >= 0):
            raise ValueError("context must be >= 0")
        if not (math.isfinite(self.group_size) and self.group_size >= 0):
            raise ValueError("group_size must be >= 0")
        if self.scheduler and not self.scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
            raise ValueError(f"scheduler address {self.scheduler!r} must look like tcp://HOST:PORT")


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Every parameter of a run: its own and each stage's."""

    run: RunParams = RunParams()
    prep: PrepParams = PrepParams()
    segment: PredictParams = PredictParams()
    densify: DensifyParams = DensifyParams()
    flatten: FlattenParams = FlattenParams()
    voxel: VoxelParams = VoxelParams()
    mesh: MeshParams = MeshParams()
    coverage: CoverageParams = CoverageParams()
    lod22: PlanarParams = PlanarParams()

    def result_params(self) -> dict[str, Any]:
        """The parameters that shape results (how the work is spread over machines does not)."""
        params = {f.name: dataclasses.asdict(getattr(self, f.name)) for f in dataclasses.fields(self)}
        for key in ("workers", "scheduler"):
            params["run"].pop(key)
        for key in ("threads", "device", "batch_size"):
            params["segment"].pop(key, None)
        return params


# ----------------------------------------------------------------------------------------------------------------------
# One building


@dataclasses.dataclass
class BuildingOutput:
    """What :func:`process_building` makes of one building (written by :func:`write_building`)."""

    id: str
    cloud: PointCloud
    voxels: VoxelGrid
    meshes: dict[str, trimesh.Trimesh]
    stats: dict[str, Any]


def _with_extra(cloud: PointCloud, name: str, values: np.ndarray) -> None:
    """Set an extra dimension of ``cloud`` (added to its extra_dims when new)."""
    cloud.attrs[name] = values
    if name not in cloud.extra_dims:
        cloud.extra_dims = [*cloud.extra_dims, name]


def _copy(cloud: PointCloud) -> PointCloud:
    return PointCloud(xyz=cloud.xyz.copy(), attrs={k: v.copy() for k, v in cloud.attrs.items()}, crs=cloud.crs,
                      extra_dims=list(cloud.extra_dims), source=cloud.source)


def building_mask(cloud: PointCloud) -> np.ndarray:
    """The points the reconstruction stages work on: class 6 (building)."""
    classes = cloud.attrs.get("classification")
    if classes is None:
        raise InputError("the points have no classification: segment them first (lidarmap segment predict)",
                         cloud.source)
    return classes == BUILDING_CLASS


def densify_cloud(cloud: PointCloud, params: DensifyParams, seed: int = 0,
                  selection: np.ndarray | None = None) -> tuple[PointCloud, dict[str, Any]]:
    """Densify the building points of ``cloud`` (or ``selection``): every input point stays in place and order
    (outliers the densifier rejects become class 7, noise), the new points follow, class 6 with the LAS synthetic
    flag set, other attributes copied from their nearest input point, colour transferred (IDW)."""
    index = np.flatnonzero(building_mask(cloud) if selection is None else selection)
    rgb8 = cloud.rgb8()
    dense = densify(cloud.xyz[index], None if rgb8 is None else rgb8[index], params, seed)
    out = _copy(cloud)
    kept = index[dense.source_index[~dense.is_new]]
    noise = np.setdiff1d(index, kept)
    out.attrs["classification"][noise] = NOISE_CLASS
    if "synthetic" not in out.attrs:
        out.attrs["synthetic"] = np.zeros(len(out), dtype=np.uint8)
    new = out.subset(index[dense.source_index[dense.is_new]])
    new.xyz = dense.xyz[dense.is_new]
    new.attrs["classification"] = np.full(len(new), BUILDING_CLASS, dtype=np.uint8)
    new.attrs["synthetic"] = np.ones(len(new), dtype=np.uint8)
    if "plane_id" in new.attrs:
        new.attrs["plane_id"] = np.full(len(new), -1, dtype=new.attrs["plane_id"].dtype)
    if dense.rgb is not None and out.has_rgb:
        scale = 257 if max(int(out.attrs[c].max(initial=0)) for c in ("red", "green", "blue")) > 255 else 1
        for c, name in enumerate(("red", "green", "blue")):
            new.attrs[name] = (dense.rgb[dense.is_new, c].astype(np.uint16) * scale).astype(out.attrs[name].dtype)
    stats = {"outliers_removed": len(noise), "new_points": len(new), "densify_stats": dense.stats}
    return PointCloud.concatenate([out, new]), stats


def flatten_cloud(cloud: PointCloud, params: FlattenParams, seed: int = 0,
                  selection: np.ndarray | None = None) -> tuple[PointCloud, dict[str, Any]]:
    """Move the building points of ``cloud`` (or ``selection``) onto their planes; extra dimension ``plane_id``
    (int32, -1 = on no plane, left where it was)."""
    index = np.flatnonzero(building_mask(cloud) if selection is None else selection)
    flat = flatten_points(cloud.xyz[index], params, seed)
    out = _copy(cloud)
    out.xyz[index] = flat.xyz
    plane_id = np.full(len(out), -1, dtype=np.int32)
    plane_id[index] = flat.plane_id
    _with_extra(out, "plane_id", plane_id)
    on_plane = flat.plane_id >= 0
    stats = {"planes": len(flat.planes), "planar_share": float(on_plane.mean()) if len(index) else 0.0,
             "mean_move": float(flat.moved[on_plane].mean()) if on_plane.any() else 0.0,
             "plane_list": [{"normal": pl.normal.tolist(), "offset": pl.offset, "rms": pl.rms,
                             "points": len(pl.inliers)} for pl in flat.planes]}
    return out, stats


STAGE_FUNCTIONS = {"densify": densify_cloud, "flatten": flatten_cloud}


def densify_seeds(cloud: PointCloud, classes_in: np.ndarray) -> np.ndarray:
    """The building points densification may multiply: all but those the model added (not class 6 in the input)
    that are not the last return of a multi-return pulse -- a pulse that goes on after hitting them went through
    something porous, a crown that slipped past the vegetation filter, and must not be multiplied. (Only the
    input points: points added by an earlier stage carry the return fields of their source point.)"""
    seeds = building_mask(cloud)
    rn, nr = cloud.attrs.get("return_number"), cloud.attrs.get("number_of_returns")
    if rn is None or nr is None:
        return seeds
    n_in = len(classes_in)
    through = np.zeros(len(cloud), bool)
    through[:n_in] = (np.asarray(classes_in) != BUILDING_CLASS) & (nr[:n_in] > 1) & (rn[:n_in] < nr[:n_in])
    return seeds & ~through


def process_building(bp: BuildingPoints, probability: np.ndarray, config: PipelineConfig) -> BuildingOutput:
    """Densify/flatten, voxelize and mesh one building whose points were segmented (``probability``, per point).

    Raises :class:`~lidarmap.errors.InputError` for a building with fewer than ``run.min_points`` building points.
    """
    run = config.run
    started = time.perf_counter()
    seconds: dict[str, float] = {}
    seed = building_seed(run.seed, bp.id)
    cloud = _copy(bp.cloud)
    classes_in = cloud.attrs.get("classification", np.zeros(len(cloud), np.uint8))
    cloud.attrs["classification"] = apply_classes(classes_in, probability, config.segment.threshold, run.union)
    _with_extra(cloud, "building_probability", np.asarray(probability, dtype=np.float32))
    n_building = int(building_mask(cloud).sum())
    if n_building < run.min_points:
        raise InputError(f"building {bp.id}: {n_building} building points after segmentation, fewer than "
                         f"min_points = {run.min_points}; nothing to reconstruct")
    stats: dict[str, Any] = {"id": bp.id, "points": len(cloud),
                             "building_points_in": int(np.sum(classes_in == BUILDING_CLASS)),
                             "building_points": n_building}
    for stage in run.stages:
        tick = time.perf_counter()
        params = config.densify if stage == "densify" else config.flatten
        selection = densify_seeds(cloud, classes_in) if stage == "densify" else None
        cloud, stage_stats = STAGE_FUNCTIONS[stage](cloud, params, seed, selection)
        stage_stats.pop("densify_stats", None)
        stage_stats.pop("plane_list", None)
        stats.update(stage_stats)
        seconds[stage] = time.perf_counter() - tick
    stats["output_points"] = len(cloud)

    tick = time.perf_counter()
    voxels = building_voxels(cloud, config.voxel)
    seconds["voxelize"] = time.perf_counter() - tick
    tick = time.perf_counter()
    building = building_mask(cloud)
    rgb = cloud.rgb8()
    cover = footprint_coverage(cloud.xyz[building, :2], bp.footprint, config.coverage)
    if cover.outline.is_empty:
        raise InputError(f"building {bp.id}: its building points cover none of its footprint; nothing to model")
    stats.update(coverage=round(cover.share, 3), status=cover.status)
    if cover.partial:  # model only what was measured; the outline goes to the CityJSON's LoD 1 block
        stats["covered_outline"] = cover.outline.wkt
    meshes = _meshes(cloud.xyz[building], None if rgb is None else rgb[building], bp, config, cloud.crs,
                     cover.outline)
    seconds["mesh"] = time.perf_counter() - tick
    seconds["total"] = time.perf_counter() - started
    stats.update(voxels=len(voxels.ijk), voxel_size=voxels.size, seconds={k: round(v, 3) for k, v in seconds.items()},
                 mesh_faces={k: len(m.faces) for k, m in meshes.items()},
                 watertight={k: bool(m.is_watertight) for k, m in meshes.items()})
    return BuildingOutput(id=bp.id, cloud=cloud, voxels=voxels, meshes=meshes, stats=stats)


def building_voxels(cloud: PointCloud, params: VoxelParams) -> VoxelGrid:
    """Voxels whose majority of points is building (noise left out): ground and trees in a voxel outvote a stray
    building point, so segmentation speckle does not become voxels."""
    classes = cloud.attrs["classification"]
    use = classes != NOISE_CLASS
    rgb = cloud.rgb8()
    grid = voxelize(cloud.xyz[use], (classes[use] == BUILDING_CLASS).astype(np.int32),
                    None if rgb is None else rgb[use], params, crs=cloud.crs)
    return grid.subset(grid.label == 1)


def _meshes(xyz: np.ndarray, rgb: np.ndarray | None, bp: BuildingPoints, config: PipelineConfig,
            crs: CRS | None, outline: Any) -> dict[str, trimesh.Trimesh]:
    fine = voxelize(xyz, None, rgb, dataclasses.replace(config.voxel, size=config.run.mesh_voxel_size,
                                                         keep_labels=()), crs=crs)
    ground = bp.ground_z if math.isfinite(bp.ground_z) else None
    return {"surface": surface_mesh(xyz, config.mesh, footprint=outline, ground_z=ground, rgb=rgb),
            "voxels": voxel_mesh(fine, config.mesh)}


# ----------------------------------------------------------------------------------------------------------------------
# Writing and resuming


def building_dir(out_dir: Path, stem: str) -> Path:
    """``OUT/buildings/<stem>``: the building's id made safe for file names and unique in the run
    (:func:`lidarmap.io.prepdir.unique_stems`; the id -> folder map is in summary.json)."""
    return out_dir / "buildings" / stem


def building_fingerprint(bp: BuildingPoints, config: PipelineConfig, model_digest: str, context_digest: str = ""
                         ) -> str:
    """Digest of everything a building's results depend on: its points and attributes, its segmentation context
    (digest), the model, the parameters."""
    h = hashlib.sha256()
    h.update(json.dumps({"lidarmap": __version__, "model": model_digest, "params": config.result_params(),
                         "context": context_digest,
                         "footprint": bp.footprint.wkb_hex, "ground_z": bp.ground_z}, sort_keys=True,
                        default=str).encode())
    h.update(np.ascontiguousarray(bp.cloud.xyz).tobytes())
    for name in sorted(bp.cloud.attrs):
        h.update(name.encode())
        h.update(np.ascontiguousarray(bp.cloud.attrs[name]).tobytes())
    return h.hexdigest()


def finished(out_dir: Path, building_id: str, stem: str, fingerprint: str) -> dict[str, Any] | None:
    """The stats of a building finished by an earlier run with the same fingerprint, else ``None``."""
    path = building_dir(out_dir, stem) / "building.json"
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("id") != building_id:
        return None
    return record if record.get("fingerprint") == fingerprint else None


def write_building(out_dir: Path, output: BuildingOutput, fingerprint: str, mesh_kind: str,
                   stem: str) -> dict[str, Any]:
    """Write one building's folder ``buildings/<stem>`` whole (temporary folder renamed into place); returns its
    building.json record."""
    record = {"id": output.id, "folder": f"buildings/{stem}", "fingerprint": fingerprint, "mesh": mesh_kind,
              **output.stats}
    with atomic_dir(building_dir(out_dir, stem)) as tmp:
        write_las(tmp / "points.laz", output.cloud)
        write_voxels(tmp / "voxels.npz", output.voxels)
        if len(output.voxels.ijk):
            write_vox(tmp / "voxels.vox", output.voxels)
        main = output.meshes[mesh_kind]
        crs = output.cloud.crs
        write_mesh(tmp / "mesh.ply", main, crs)
        write_mesh(tmp / "mesh.obj", main, crs)
        for kind, mesh in output.meshes.items():
            if kind != mesh_kind:
                write_mesh(tmp / f"mesh_{kind}.ply", mesh, crs)
        write_text_atomic(tmp / "building.json", json.dumps(record, indent=2, default=_json_default))
    return record


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


# ----------------------------------------------------------------------------------------------------------------------
# The run


@dataclasses.dataclass
class RunResult:
    """What a run did: per building its building.json record (processed now or earlier), failures with reasons.
    ``prep`` describes the buildings (entries: ids, footprints, heights, bounds); its spool is gone once the run
    returns, so its points cannot be loaded any more (use :func:`lidarmap.aerial.pipeline.prep_tiles` for that)."""

    out_dir: Path
    records: list[dict[str, Any]]
    processed: list[str]
    skipped: list[str]
    failed: dict[str, str]
    dropped: dict[str, str]
    prep: SpooledPrep
    seconds: float


def load_segmenter(run: RunParams) -> tuple[Any, str]:
    """The segmentation model of ``run`` and a digest of its file (part of every building's fingerprint)."""
    from lidarmap.segment.baseline import DEFAULT_BASELINE, load_baseline
    from lidarmap.segment.modelfile import DEFAULT_MODEL, load_model

    if run.method == "baseline":
        path = Path(run.model) if run.model else DEFAULT_BASELINE
        model = load_baseline(path)
    else:
        path = Path(run.model) if run.model else DEFAULT_MODEL
        model = load_model(path)
    return model, hashlib.sha256(path.read_bytes()).hexdigest()


def segment_group(buildings: Sequence[BuildingPoints], context: PointCloud | None, model: Any,
                  params: PredictParams) -> list[np.ndarray]:
    """Building probability of every point of a group of neighbouring buildings, segmented together (windows
    cover their points) with the kept points of the buildings around them as context (``context``, cropped to what
    the windows see): the same whatever else is in the run, on whatever machine."""
    own = PointCloud.concatenate([b.cloud for b in buildings])
    if context is not None and hasattr(model, "spec"):
        context = _within_windows(context, own.xyz[:, :2], model.spec.block_size, params.overlap)
    if context is None or not len(context):
        prob = predict(own, model, params)
    else:
        targets = np.zeros(len(own) + len(context), dtype=bool)
        targets[:len(own)] = True
        prob = predict(PointCloud.concatenate([own, context]), model, params, targets=targets)
    return np.split(prob, np.cumsum([len(b.cloud) for b in buildings])[:-1])


#: Context kept beyond the windows' edges (m): the neighbourhoods of the shape features of points near an edge.
WINDOW_MARGIN = 2.0


def _within_windows(context: PointCloud, xy: np.ndarray, block_size: float, overlap: float) -> PointCloud | None:
    """The context points that the windows covering ``xy`` can see (plus :data:`WINDOW_MARGIN`)."""
    from lidarmap.segment.blocks import window_centres

    centres = window_centres(xy, block_size, overlap)
    reach = block_size / 2 + WINDOW_MARGIN
    lo, hi = centres.min(axis=0) - reach, centres.max(axis=0) + reach
    cxy = context.xyz[:, :2]
    inside = np.all((cxy >= lo) & (cxy <= hi), axis=1)
    return context.subset(np.flatnonzero(inside)) if inside.any() else None


@dataclasses.dataclass
class GroupJob:
    """One task: a group of neighbouring buildings, their segmentation context, the configuration."""

    buildings: list[BuildingPoints]
    context: PointCloud | None
    config: PipelineConfig
    todo: list[bool]  # False: finished by an earlier run (segmented with the group, not reconstructed again)


def group_task(job: GroupJob, model: Any) -> list[BuildingOutput | TaskFailure | None]:
    """Segment a group of buildings together, then reconstruct each one to do (in this process or on a dask
    worker); a building that fails gives a :class:`~lidarmap.executor.TaskFailure` and the others go on."""
    run = job.config.run
    first = job.buildings[0].id
    params = dataclasses.replace(job.config.segment, union=run.union, seed=building_seed(run.seed, first))
    probabilities = segment_group(job.buildings, job.context, model, params)
    return [run_task(process_building, bp, prob, job.config) if todo else None
            for bp, prob, todo in zip(job.buildings, probabilities, job.todo)]


def building_groups(spooled: SpooledPrep, size: float) -> list[list[int]]:
    """Prep entries grouped by the ``size`` m cell of their points' bounds (:func:`lidarmap.executor.group_by_cell`)."""
    return group_by_cell(np.array([e.bounds[:4] for e in spooled.entries]).reshape(-1, 4), size)


def _context_digest(clouds: Sequence[PointCloud | None]) -> str:
    h = hashlib.sha256()
    for cloud in clouds:
        if cloud is None:
            continue
        h.update(np.ascontiguousarray(cloud.xyz).tobytes())
        for name in sorted(cloud.attrs):
            h.update(name.encode())
            h.update(np.ascontiguousarray(cloud.attrs[name]).tobytes())
    return h.hexdigest()


def _jobs(spooled: SpooledPrep, groups: list[list[int]], out: Path, config: PipelineConfig, model_digest: str,
          plan: dict[str, Any]) -> Iterator[GroupJob]:
    """The jobs of the groups holding a building not finished by an earlier run, one group loaded at a time;
    fills ``plan`` (per job: its entries and fingerprints; finished records) as it goes."""
    for members in groups:
        buildings = [spooled.load(k) for k in members]
        context = spooled.context(members, config.run.context) if config.run.context > 0 else None
        digest = _context_digest([b.cloud for b in buildings] + [context])
        prints = [building_fingerprint(b, config, model_digest, digest) for b in buildings]
        earlier = [finished(out, b.id, plan["stems"][b.id], fp) for b, fp in zip(buildings, prints)]
        for k, b, rec in zip(members, buildings, earlier):
            if rec is not None:
                plan["records"][k] = rec
                plan["skipped"].append(b.id)
        if all(rec is not None for rec in earlier):
            continue
        plan["todo"].append(list(zip(members, prints)))
        yield GroupJob(buildings, context, config, [rec is None for rec in earlier])


def _worker_config(config: PipelineConfig) -> PipelineConfig:
    """On dask workers torch gets one thread per worker process (results do not depend on it)."""
    if config.run.workers == 1 and not config.run.scheduler:
        return config
    return dataclasses.replace(config, segment=dataclasses.replace(config.segment, threads=1))


#: Kind of the output-folder marker of a run (:mod:`lidarmap.io.outdir`).
KIND = "run"
#: What a run writes into its output folder (listed in the folder's marker).
RUN_OUTPUTS = ("buildings", "summary.json", "buildings.city.json", "buildings.gpkg", "buildings.glb")


def check_out_dir(out_dir: str | Path) -> Path:
    """Refuse an output path a run may not write (:func:`lidarmap.io.outdir.claim_out_dir`): a file, a non-empty
    folder lidarmap did not write, another command's output. An earlier run's folder is resumed."""
    return claim_out_dir(out_dir, KIND)


#: Prefix of the spool folder a run keeps in its output folder while it runs (a killed run's is removed by the next).
WORK_PREFIX = ".work-"


def _remove_stale_work(out: Path) -> None:
    for stale in out.glob(f"{WORK_PREFIX}*"):
        shutil.rmtree(stale, ignore_errors=True)


def run_pipeline(tiles: Sequence[str | Path], footprints: Footprints, out_dir: str | Path,
                 config: PipelineConfig = PipelineConfig(), crs: str | CRS | None = None,
                 report: Report | None = None) -> RunResult:
    """The whole aerial pipeline; ``report(step, done, total)`` follows progress ("read", "buildings").

    Memory: the tiles are streamed into a spool on disk (``OUT/.work-*``, removed at the end); then one group of
    buildings (plus its context) at a time is loaded and sent to a task, at most a few tasks in flight.
    """

    started = time.perf_counter()
    out = Path(out_dir)
    created = start_marked_dir(out, KIND, RUN_OUTPUTS)  # marked before anything is written: a killed run resumes
    _remove_stale_work(out)
    run = config.run
    work = Path(tempfile.mkdtemp(prefix=WORK_PREFIX, dir=out))  # the spool: beside the output, on its disk
    try:
        spooled = stream_tiles(tiles, footprints, config.prep, crs, work_dir=work,
                               progress=(lambda n: report("read", n, 0)) if report else None)
        model, model_digest = load_segmenter(run)
        stems = unique_stems(e.id for e in spooled.entries)
        plan: dict[str, Any] = {"records": {}, "skipped": [], "todo": [], "stems": stems}
        failed: dict[str, str] = {}
        processed: list[str] = []
        jobs = _jobs(spooled, building_groups(spooled, run.group_size), out, _worker_config(config), model_digest,
                     plan)
        done = 0
        for number, results in map_tasks(group_task, jobs, run.workers, run.scheduler, shared=(model,)):
            members = plan["todo"][number]
            if isinstance(results, TaskFailure):  # the whole group (segmentation) failed
                results = [results] * len(members)
            for (k, fingerprint), result in zip(members, results):
                if result is None:  # finished earlier
                    continue
                if isinstance(result, TaskFailure):
                    failed[spooled.entries[k].id] = result.reason
                    log.warning("building %s failed: %s", spooled.entries[k].id, result.reason)
                else:
                    plan["records"][k] = write_building(out, result, fingerprint, run.mesh, stems[result.id])
                    processed.append(result.id)
            done += sum(result is not None for result in results)
            if report:
                report("buildings", done + len(plan["skipped"]), len(spooled.entries))
        records = [plan["records"][k] for k in sorted(plan["records"])]
        order = _entry_order(spooled)  # results arrive in completion order; report them in prep order
        result = RunResult(out_dir=out, records=records, processed=sorted(processed, key=order),
                           skipped=sorted(plan["skipped"], key=order),
                           failed={k: failed[k] for k in sorted(failed, key=order)},
                           dropped=dict(spooled.dropped), prep=spooled, seconds=time.perf_counter() - started)
        _write_summary(out, result, config, stems)
        _write_cityjson(out, result, config, stems)
        write_buildings_gpkg(result, footprints, lambda out_dir, fid: building_dir(out_dir, stems[fid]))
        _write_glb(out, result, stems)
        return result
    finally:
        shutil.rmtree(work, ignore_errors=True)
        abandon_marked_dir(out, created)  # refused input: leave no folder behind


def _entry_order(spooled: Any) -> Callable[[str], int]:
    position = {e.id: k for k, e in enumerate(spooled.entries)}
    return lambda building_id: position[building_id]


def _write_summary(out: Path, result: RunResult, config: PipelineConfig, stems: dict[str, str]) -> None:
    prep = result.prep
    summary = {
        "lidarmap": __version__, "tiles": prep.sources, "crs": None if prep.crs is None else prep.crs.to_wkt(),
        "points_read": prep.points_read, "points_kept": prep.points_kept, "buildings": len(result.records),
        "processed": result.processed, "skipped_finished": result.skipped, "failed": result.failed,
        "dropped_footprints": result.dropped, "repaired_footprints": prep.repaired, "seconds": round(result.seconds, 3),
        "partial": [r["id"] for r in result.records if r.get("status") == "partial"],
        "params": config.result_params(), "records": result.records,
        "folders": {e.id: f"buildings/{stems[e.id]}" for e in prep.entries},
    }
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=_json_default))


def _write_cityjson(out: Path, result: RunResult, config: PipelineConfig, stems: dict[str, str]) -> None:
    """``buildings.city.json``, streamed: one building's mesh in memory at a time. A partial building's LoD 1 block
    stands on the covered part of its footprint (``covered_outline``), as its mesh does."""
    import shapely

    from lidarmap.export.cityjson import AerialBuilding, write_aerial_cityjson

    by_id = {e.id: e for e in result.prep.entries}

    def buildings() -> Iterator[AerialBuilding]:
        for record in result.records:
            e = by_id[record["id"]]
            mesh = trimesh.load(building_dir(out, stems[e.id]) / "mesh.ply", process=False)
            attributes = {**e.properties, "lidarmap_points": record["output_points"],
                          "lidarmap_building_points": record["building_points"], "lidarmap_voxels": record["voxels"],
                          "lidarmap_height_source": e.height_source,
                          "lidarmap_coverage": record.get("coverage"), "lidarmap_status": record.get("status")}
            outline = record.get("covered_outline")
            yield AerialBuilding(id=e.id, footprint=shapely.from_wkt(outline) if outline else e.footprint, ground_z=e.ground_z, height=e.height,
                                 mesh_vertices=np.asarray(mesh.vertices, dtype=np.float64),
                                 mesh_faces=np.asarray(mesh.faces), attributes=attributes)

    entries = [by_id[r["id"]] for r in result.records]
    grounds = [e.ground_z for e in entries if math.isfinite(e.ground_z)]
    translate = ([math.floor(min(e.bounds[0] for e in entries)), math.floor(min(e.bounds[1] for e in entries)),
                  math.floor(min(grounds, default=0.0))] if entries else [0.0, 0.0, 0.0])
    crs_wkt = result.prep.crs.to_wkt() if result.prep.crs is not None else ""
    write_aerial_cityjson(out / "buildings.city.json", buildings(), crs_wkt, translate, planar=config.lod22)


def _write_glb(out: Path, result: RunResult, stems: dict[str, str]) -> None:
    crs_wkt = result.prep.crs.to_wkt() if result.prep.crs is not None else ""
    write_run_glb(out, result.records, stems, result.prep.entries, crs_wkt)


def run_folders(summary: dict[str, Any]) -> dict[str, str]:
    """Building id -> folder name of a run from its ``summary.json``; runs written before the ``folders`` map named
    every folder by its file-safe id (the stems of :func:`unique_stems` for ids without collisions)."""
    folders = summary.get("folders")
    if isinstance(folders, dict):
        return {str(fid): Path(str(folder)).name for fid, folder in folders.items()}
    return unique_stems(str(r["id"]) for r in summary["records"])


def run_glb_buildings(out_dir: str | Path, records: Sequence[dict[str, Any]], stems: dict[str, str],
                      entries: Sequence[Any] = ()) -> Iterator[Any]:
    """A run's buildings for :mod:`lidarmap.export.gltf`, one mesh.ply loaded at a time: their building.json
    ``records``, ``stems`` their folder names (summary.json's ``folders``); prep ``entries`` (when at hand) add
    footprint attributes and heights."""
    from lidarmap.export.cityjson import AerialBuilding
    from lidarmap.export.gltf import aerial_glb_building

    by_id = {e.id: e for e in entries}
    for record in records:
        e = by_id.get(record["id"])
        mesh = trimesh.load(building_dir(Path(out_dir), stems[record["id"]]) / "mesh.ply", process=False)
        attributes = {"points": record.get("output_points"), "planes": record.get("planes")}
        if e is not None:
            attributes.update({**e.properties, "height_source": e.height_source})
        yield aerial_glb_building(AerialBuilding(
            record["id"], None if e is None else e.footprint, math.nan if e is None else e.ground_z,
            math.nan if e is None else e.height, mesh.vertices, mesh.faces, attributes), record)


def write_run_glb(out_dir: str | Path, records: Sequence[dict[str, Any]], stems: dict[str, str],
                  entries: Sequence[Any] = (), crs_wkt: str = "") -> Path:
    """``OUT/buildings.glb``: a run's meshes for viewers (glTF 2.0, local origin; :mod:`lidarmap.export.gltf`)."""
    from lidarmap.export.gltf import write_glb

    return write_glb(Path(out_dir) / "buildings.glb", run_glb_buildings(out_dir, records, stems, entries), crs_wkt,
                     title=RUN_GLB_TITLE)


#: Title of a run's glb (asset extras).
RUN_GLB_TITLE = "lidarmap aerial reconstruction"


def check_stage_names(stages: Iterable[str]) -> tuple[str, ...]:
    """Stage names from a comma list or sequence (CLI ``--stages densify,flatten``); "" / "none" = no stage."""
    if isinstance(stages, str):
        stages = [s.strip() for s in stages.split(",")]
    names = tuple(s for s in stages if s and s != "none")
    bad = [s for s in names if s not in STAGES]
    if bad:
        raise ConfigError(f"unknown stage(s) {', '.join(bad)} (known: {', '.join(STAGES)})")
    return names


__all__ += ["building_dir", "building_fingerprint", "finished", "write_building", "check_stage_names",
            "building_mask", "check_out_dir", "densify_cloud", "flatten_cloud", "building_voxels", "STAGE_FUNCTIONS"]
__all__ += ["RUN_GLB_TITLE", "run_folders", "run_glb_buildings", "write_run_glb"]


def stream_tiles(paths: Sequence[str | Path], footprints: Footprints, params: PrepParams | None = None,
                 crs: str | CRS | None = None, progress: Callable[[int], None] | None = None,
                 work_dir: str | Path | None = None) -> SpooledPrep:
    """Stream any number of tiles (chunks of ``params.chunk_points``) into a spool of the points kept per footprint.

    ``crs`` is used for tiles without a CRS record; footprints in another CRS are reprojected to the tiles'. Raises
    :class:`InputError` / :class:`CRSError` naming the file for unreadable tiles, CRS conflicts and footprints that miss
    the points (see :func:`lidarmap.aerial.prep.spool_chunks`).
    """
    params = params or PrepParams()
    tiles = scan_tiles(paths, crs)
    return spool_chunks(read_tiles(tiles, params.chunk_points, crs), footprints, tiles.crs, tiles.bounds, tiles.name,
                        [str(p) for p in tiles.paths], params, progress, work_dir)


def prep_tiles(paths: Sequence[str | Path], footprints: Footprints, params: PrepParams | None = None,
               crs: str | CRS | None = None, progress: Callable[[int], None] | None = None) -> PrepResult:
    """:func:`stream_tiles` in memory, every building loaded (see :class:`SpooledPrep` for bounded memory)."""
    spooled = stream_tiles(paths, footprints, params, crs, progress)
    try:
        return spooled.materialise()
    finally:
        spooled.close()
