"""The aerial pipeline end to end (``lidarmap run``): tiles + footprints -> one folder of results per building.

::

    prep (merge tiles, split per footprint)
      -> segmentation, once over every kept point (each building sees its neighbours as context)
      -> per building: densify / flatten (order configurable) -> voxelize (majority label) -> meshes
      -> OUT/buildings/<id>/, OUT/summary.json, OUT/buildings.city.json

Per building (``OUT/buildings/<id>/``, see docs/pipeline.md): ``points.laz`` (the building's area: every input point
in input order with its new class and ``building_probability``, building points moved by flattening, removed
outliers as class 7, then the new points of densification with the LAS ``synthetic`` flag), ``voxels.npz`` +
``voxels.vox`` (building voxels, majority label), ``mesh.ply`` + ``mesh.obj`` (CRS, double precision), the other
mesh kind as ``mesh_<kind>.ply``, and ``building.json`` (statistics and the fingerprint), written last: a folder
without it does not exist (each folder is written to a temporary folder and renamed into place).

Resumable: a building whose ``building.json`` carries the current fingerprint (its input points, the model, every
parameter) is skipped. Deterministic: every building draws its random numbers from (seed, building id), and
segmentation from the seed, so serial, distributed (dask) and resumed runs write the same results.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from pyproj import CRS

from lidarmap import __version__
from lidarmap.densify import DensifyParams, densify
from lidarmap.errors import ConfigError, InputError
from lidarmap.flatten import FlattenParams, flatten_points
from lidarmap.io.atomic import atomic_dir, write_text_atomic
from lidarmap.io.footprints import Footprints
from lidarmap.io.las import write_las
from lidarmap.io.pointcloud import PointCloud
from lidarmap.mesh import MeshParams, surface_mesh, voxel_mesh, write_mesh
from lidarmap.prep import BuildingPoints, PrepParams, PrepResult, building_file_name, prep_tiles
from lidarmap.segment.features import BUILDING_CLASS
from lidarmap.segment.predict import PredictParams, apply_classes, predict
from lidarmap.voxel import VoxelGrid, VoxelParams, voxelize, write_vox, write_voxels

__all__ = ["RunParams", "PipelineConfig", "BuildingOutput", "RunResult", "process_building", "run_pipeline",
           "segment_buildings", "building_seed", "NOISE_CLASS", "STAGES"]

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
    workers (1): worker processes on this machine (dask.distributed LocalCluster); 1 = everything in this process.
    scheduler (""): address of a running dask scheduler (e.g. "tcp://10.0.0.5:8786") for multi-machine runs;
        overrides ``workers``. Workers compute, this process writes, so only this machine needs the output folder.
    seed (0): seeds segmentation and every building's random draws.
    """

    section = "run"

    stages: tuple[str, ...] = ("densify", "flatten")
    method: str = "pointnet2"
    model: str = ""
    union: bool = True
    min_points: int = 50
    mesh: str = "surface"
    mesh_voxel_size: float = 0.5
    workers: int = 1
    scheduler: str = ""
    seed: int = 0

    def __post_init__(self) -> None:
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


def building_seed(seed: int, building_id: str) -> int:
    """The seed of one building: the same for a building whatever else is in the run, and on every machine."""
    return int(np.random.SeedSequence([seed, zlib.crc32(str(building_id).encode("utf-8"))]).generate_state(1)[0])


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
        cloud, stage_stats = STAGE_FUNCTIONS[stage](cloud, params, seed)
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
    meshes = _meshes(cloud.xyz[building], None if rgb is None else rgb[building], bp, config, cloud.crs)
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
            crs: CRS | None) -> dict[str, trimesh.Trimesh]:
    fine = voxelize(xyz, None, rgb, dataclasses.replace(config.voxel, size=config.run.mesh_voxel_size,
                                                         keep_labels=()), crs=crs)
    ground = bp.ground_z if math.isfinite(bp.ground_z) else None
    return {"surface": surface_mesh(xyz, config.mesh, footprint=bp.footprint, ground_z=ground, rgb=rgb),
            "voxels": voxel_mesh(fine, config.mesh)}


# ----------------------------------------------------------------------------------------------------------------------
# Writing and resuming


def building_dir(out_dir: Path, building_id: str) -> Path:
    """``OUT/buildings/<id>``, the id made safe for file names."""
    return out_dir / "buildings" / building_file_name(building_id).removesuffix(".laz")


def building_fingerprint(bp: BuildingPoints, config: PipelineConfig, model_digest: str) -> str:
    """Digest of everything a building's results depend on: its points and attributes, the model, the parameters."""
    h = hashlib.sha256()
    h.update(json.dumps({"lidarmap": __version__, "model": model_digest, "params": config.result_params(),
                         "footprint": bp.footprint.wkb_hex, "ground_z": bp.ground_z}, sort_keys=True,
                        default=str).encode())
    h.update(np.ascontiguousarray(bp.cloud.xyz).tobytes())
    for name in sorted(bp.cloud.attrs):
        h.update(name.encode())
        h.update(np.ascontiguousarray(bp.cloud.attrs[name]).tobytes())
    return h.hexdigest()


def finished(out_dir: Path, building_id: str, fingerprint: str) -> dict[str, Any] | None:
    """The stats of a building finished by an earlier run with the same fingerprint, else ``None``."""
    path = building_dir(out_dir, building_id) / "building.json"
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if record.get("fingerprint") == fingerprint else None


def write_building(out_dir: Path, output: BuildingOutput, fingerprint: str, mesh_kind: str) -> dict[str, Any]:
    """Write one building's folder whole (temporary folder renamed into place); returns its building.json record."""
    record = {"id": output.id, "fingerprint": fingerprint, "mesh": mesh_kind, **output.stats}
    with atomic_dir(building_dir(out_dir, output.id)) as tmp:
        write_las(tmp / "points.laz", output.cloud)
        write_voxels(tmp / "voxels.npz", output.voxels)
        if len(output.voxels.ijk):
            write_vox(tmp / "voxels.vox", output.voxels)
        main = output.meshes[mesh_kind]
        write_mesh(tmp / "mesh.ply", main)
        write_mesh(tmp / "mesh.obj", main)
        for kind, mesh in output.meshes.items():
            if kind != mesh_kind:
                write_mesh(tmp / f"mesh_{kind}.ply", mesh)
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
    """What a run did: per building its building.json record (processed now or earlier), failures with reasons."""

    out_dir: Path
    records: list[dict[str, Any]]
    processed: list[str]
    skipped: list[str]
    failed: dict[str, str]
    dropped: dict[str, str]
    prep: PrepResult
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


def segment_buildings(buildings: Sequence[BuildingPoints], model: Any, params: PredictParams,
                      report: Callable[[int, int], None] | None = None) -> list[np.ndarray]:
    """Building probability of every point of every building, from one pass over all of them together.

    The buildings' points are disjoint (each point belongs to one footprint), so their union is the kept cloud:
    windows see across building borders, as on the merged tiles (more context than one building alone).
    """
    if not buildings:
        return []
    merged = PointCloud.concatenate([b.cloud for b in buildings])
    prob = predict(merged, model, params, report)
    return np.split(prob, np.cumsum([len(b.cloud) for b in buildings])[:-1])


def _compute(job: tuple[BuildingPoints, np.ndarray, PipelineConfig]) -> BuildingOutput | str:
    """One building on a worker: its output, or the one-line reason it failed."""
    bp, probability, config = job
    try:
        return process_building(bp, probability, config)
    except InputError as exc:
        return exc.problem


def _map(jobs: list[tuple[BuildingPoints, np.ndarray, PipelineConfig]], run: RunParams
         ) -> Iterator[tuple[int, BuildingOutput | str]]:
    """(job number, result) of every job: in this process, or on dask workers (results in completion order)."""
    if run.workers == 1 and not run.scheduler:
        for number, job in enumerate(jobs):
            yield number, _compute(job)
        return
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None if run.scheduler else LocalCluster(n_workers=run.workers, threads_per_worker=1, processes=True,
                                                      dashboard_address=None)
    try:
        with Client(run.scheduler or cluster) as client:
            futures = {client.submit(_compute, job, pure=False): number for number, job in enumerate(jobs)}
            for future in as_completed(futures):
                yield futures[future], future.result()
    finally:
        if cluster is not None:
            cluster.close()


def check_out_dir(out_dir: str | Path) -> Path:
    """Refuse an output path that is a file, or a non-empty folder that holds no earlier run (nothing to resume)."""
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise InputError("output exists and is not a folder", out)
        if any(out.iterdir()) and not ((out / "summary.json").exists() or (out / "buildings").is_dir()):
            raise InputError("output folder is not empty and holds no earlier run to resume; choose another -o", out)
    return out


def run_pipeline(tiles: Sequence[str | Path], footprints: Footprints, out_dir: str | Path,
                 config: PipelineConfig = PipelineConfig(), crs: str | CRS | None = None,
                 report: Report | None = None) -> RunResult:
    """The whole aerial pipeline; ``report(step, done, total)`` follows progress ("read", "segment", "buildings")."""
    started = time.perf_counter()
    out = check_out_dir(out_dir)
    run = config.run
    segment_params = dataclasses.replace(config.segment, union=run.union, seed=run.seed)
    prep = prep_tiles(tiles, footprints, config.prep, crs,
                      progress=(lambda n: report("read", n, 0)) if report else None)
    model, model_digest = load_segmenter(run)
    prints = [building_fingerprint(b, config, model_digest) for b in prep.buildings]
    earlier = [finished(out, b.id, fp) for b, fp in zip(prep.buildings, prints)]
    todo = [i for i, rec in enumerate(earlier) if rec is None]
    records: dict[int, dict[str, Any]] = {i: rec for i, rec in enumerate(earlier) if rec is not None}
    failed: dict[str, str] = {}
    if todo:
        # every building is segmented, done or not, so each one sees the same context in every run
        probs = segment_buildings(prep.buildings, model, segment_params,
                                  (lambda d, t: report("segment", d, t)) if report else None)
        jobs = [(prep.buildings[i], probs[i], config) for i in todo]
        for done, (number, result) in enumerate(_map(jobs, run), 1):
            i = todo[number]
            if isinstance(result, str):
                failed[prep.buildings[i].id] = result
            else:
                records[i] = write_building(out, result, prints[i], run.mesh)
            if report:
                report("buildings", done, len(todo))
    ordered = [records[i] for i in sorted(records)]
    result = RunResult(out_dir=out, records=ordered, processed=[prep.buildings[i].id for i in todo
                                                                if i in records],
                       skipped=[prep.buildings[i].id for i, rec in enumerate(earlier) if rec is not None],
                       failed=failed, dropped=dict(prep.dropped), prep=prep, seconds=time.perf_counter() - started)
    _write_summary(out, result, config)
    _write_cityjson(out, result)
    return result


def _write_summary(out: Path, result: RunResult, config: PipelineConfig) -> None:
    prep = result.prep
    summary = {
        "lidarmap": __version__, "tiles": prep.sources, "crs": None if prep.crs is None else prep.crs.to_wkt(),
        "points_read": prep.points_read, "points_kept": prep.points_kept, "buildings": len(result.records),
        "processed": result.processed, "skipped_finished": result.skipped, "failed": result.failed,
        "dropped_footprints": result.dropped, "seconds": round(result.seconds, 3),
        "params": config.result_params(), "records": result.records,
    }
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=_json_default))


def _write_cityjson(out: Path, result: RunResult) -> None:
    from lidarmap.export.cityjson import AerialBuilding, aerial_to_cityjson, write_cityjson

    by_id = {b.id: b for b in result.prep.buildings}
    entries = []
    for record in result.records:
        bp = by_id[record["id"]]
        mesh = trimesh.load(building_dir(out, bp.id) / "mesh.ply", process=False)
        attributes = {**bp.properties, "lidarmap_points": record["output_points"],
                      "lidarmap_building_points": record["building_points"], "lidarmap_voxels": record["voxels"],
                      "lidarmap_height_source": bp.height_source}
        entries.append(AerialBuilding(id=bp.id, footprint=bp.footprint, ground_z=bp.ground_z, height=bp.height,
                                      mesh_vertices=np.asarray(mesh.vertices, dtype=np.float64),
                                      mesh_faces=np.asarray(mesh.faces), attributes=attributes))
    crs_wkt = result.prep.crs.to_wkt() if result.prep.crs is not None else ""
    write_cityjson(out / "buildings.city.json", aerial_to_cityjson(entries, crs_wkt))


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
