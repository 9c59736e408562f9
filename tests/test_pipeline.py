"""The aerial pipeline (``lidarmap run`` and the stage commands) on a small simulated city and synthetic points."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
import trimesh
from pyproj import CRS

from lidarmap.aerial.densify import DensifyParams
from lidarmap.aerial.flatten import FlattenParams
from lidarmap.aerial.pipeline import (
    NOISE_CLASS,
    PipelineConfig,
    RunParams,
    building_voxels,
    densify_cloud,
    flatten_cloud,
    run_pipeline,
)
from lidarmap.aerial.voxel import VoxelParams
from lidarmap.core import PointCloud
from lidarmap.export.validate import validate_cityjson
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las, write_las
from lidarmap.io.voxels import read_voxels
from lidarmap.sim import SimParams, load_truth, simulate

DATA_FILES = ("points.laz", "voxels.npz", "voxels.vox", "mesh.ply", "mesh.obj", "mesh_voxels.ply")


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarmap", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("city")
    simulate(out, SimParams(seed=3, buildings=2, campaigns=0))
    return out


@pytest.fixture(scope="module")
def first_run(city: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("run") / "out"
    result = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o", str(out))
    return out, result


def test_run_writes_every_building_whole(city: Path, first_run) -> None:
    out, result = first_run
    assert result.returncode == 0, result.stderr
    truth = load_truth(city)
    existing = [b for b in truth.buildings if b.status == "existing"]
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary["processed"]) == sorted(str(b.id) for b in existing)
    assert list(summary["dropped_footprints"].values()) == ["under construction (status='under construction')"]
    for b in existing:
        folder = out / "buildings" / str(b.id)
        assert all((folder / name).exists() for name in DATA_FILES)
        record = json.loads((folder / "building.json").read_text())
        assert record["watertight"] == {"surface": True, "voxels": True}
        assert not list((out / "buildings").glob(".*"))  # no temporary folders left


def test_points_keep_every_input_point_and_flag_new_ones(city: Path, first_run) -> None:
    out, _ = first_run
    points = read_las(out / "buildings" / "1" / "points.laz")
    record = json.loads((out / "buildings" / "1" / "building.json").read_text())
    synthetic = points.attrs["synthetic"].astype(bool)
    assert len(points) == record["points"] + record["new_points"] and synthetic.sum() == record["new_points"]
    assert np.all(synthetic[record["points"]:]) and not synthetic[:record["points"]].any()  # input first, in order
    assert np.all(points.attrs["classification"][synthetic] == 6)
    prob = points.attrs["building_probability"]
    assert prob.dtype == np.float32 and np.all((prob >= 0) & (prob <= 1))
    # densification doubles the building points (ratio 2), give or take the outliers and openings it leaves
    building = np.sum(points.attrs["classification"][~synthetic] == 6)
    assert 0.7 * building <= record["new_points"] <= 1.3 * building


def test_meshes_are_in_the_crs_in_double_precision_and_close_to_the_truth(city: Path, first_run) -> None:
    out, _ = first_run
    truth = {b.id: b for b in load_truth(city).buildings}
    raw = (out / "buildings" / "1" / "mesh.ply").read_bytes()
    assert b"property double x" in raw[:400]
    mesh = trimesh.load(out / "buildings" / "1" / "mesh.ply", process=False)
    obj = trimesh.load(out / "buildings" / "1" / "mesh.obj", process=False)
    assert np.array_equal(np.asarray(mesh.vertices), np.asarray(obj.vertices))
    assert mesh.is_watertight and mesh.volume > 0
    solid = truth[1].mesh()
    # the reconstruction's volume and extent match the true building (UTM coordinates: metres from ~500 km)
    assert abs(mesh.volume - solid.volume) / solid.volume < 0.15
    assert np.allclose(mesh.bounds[:, :2], solid.bounds[:, :2], atol=1.0)
    assert abs(mesh.bounds[1, 2] - solid.bounds[1, 2]) < 0.5


def test_voxels_keep_size_origin_and_crs(first_run) -> None:
    out, _ = first_run
    grid = read_voxels(out / "buildings" / "1" / "voxels.npz")
    assert grid.size == 1.0 and np.all(grid.label == 1) and "32632" in (grid.crs.to_string() or "")
    assert np.allclose(grid.origin / grid.size, np.round(grid.origin / grid.size))


def test_cityjson_validates_with_both_lods(first_run) -> None:
    out, _ = first_run
    doc = json.loads((out / "buildings.city.json").read_text())
    assert validate_cityjson(doc) == []
    building = doc["CityObjects"]["1"]
    assert [g["lod"] for g in building["geometry"]] == ["1", "2.2"]
    kinds = {s["type"] for s in building["geometry"][1]["semantics"]["surfaces"]}
    assert kinds == {"GroundSurface", "RoofSurface", "WallSurface"}
    assert building["attributes"]["status"] == "existing" and building["attributes"]["measuredHeight"] > 3


def test_run_writes_a_geopackage_of_every_footprint(city: Path, first_run) -> None:
    pyogrio = pytest.importorskip("pyogrio", reason="pyogrio is in the test extra")
    out, _ = first_run
    info = pyogrio.read_info(out / "buildings.gpkg")
    assert info["crs"] == "EPSG:32632" and info["geometry_type"] == "MultiPolygon"
    _, _, wkb, columns = pyogrio.raw.read(out / "buildings.gpkg")
    row = {name: list(values) for name, values in zip(info["fields"], columns)}
    footprints = read_footprints(city / "footprints.geojson").to_crs(CRS.from_user_input(info["crs"]))
    assert row["id"] == footprints.ids  # every footprint, in input order, dropped ones too
    assert all(shapely.from_wkb(w).equals(p) for w, p in zip(wkb, footprints.polygons))
    summary = json.loads((out / "summary.json").read_text())
    dropped = summary["dropped_footprints"]
    assert row["status"] == ["dropped" if i in dropped else "ok" for i in row["id"]]
    assert row["reason"] == [dropped.get(i) for i in row["id"]]
    records = {r["id"]: r for r in summary["records"]}
    for k, building_id in enumerate(row["id"]):
        if building_id in records:
            points = read_las(out / "buildings" / building_id / "points.laz")
            assert row["output_points"][k] == records[building_id]["output_points"] == len(points)
            assert row["z_max"][k] == pytest.approx(points.xyz[:, 2].max(), abs=1e-3)
            assert row["z_min"][k] < row["ground_z"][k] + 1 < row["z_max"][k]


def test_second_run_resumes_and_a_changed_parameter_recomputes(city: Path, first_run, tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    shutil.copytree(first_run[0], out)
    before = {n: (out / "buildings" / "1" / n).read_bytes() for n in DATA_FILES}
    again = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o", str(out), "--json")
    assert again.returncode == 0, again.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["processed"] == [] and len(summary["skipped_finished"]) == 2
    doc = json.loads(again.stdout)  # --json: nothing but one object on stdout
    assert doc["processed"] == [] and doc["skipped"] == summary["skipped_finished"]
    assert doc["dropped"] == summary["dropped_footprints"] and doc["failed"] == {}
    assert doc["outputs"]["geopackage"] == str(out / "buildings.gpkg") and (out / "buildings.gpkg").is_file()
    records = {r["id"]: r for r in summary["records"]}
    assert all(b["output_points"] == records[b["id"]]["output_points"] for b in doc["buildings"])
    assert all((out / "buildings" / "1" / n).read_bytes() == before[n] for n in DATA_FILES)
    config = tmp_path / "c.toml"
    config.write_text("[voxel]\nsize = 0.5\n")
    third = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o", str(out),
                    "--config", str(config))
    assert third.returncode == 0, third.stderr
    assert len(json.loads((out / "summary.json").read_text())["processed"]) == 2
    assert read_voxels(out / "buildings" / "1" / "voxels.npz").size == 0.5


def test_serial_and_distributed_runs_write_the_same_results(city: Path, first_run, tmp_path: Path) -> None:
    out, _ = first_run
    fps = read_footprints(city / "footprints.geojson")
    run_pipeline([city / "als.laz"], fps, tmp_path / "dask", PipelineConfig(run=RunParams(workers=2)))
    for b in ("1", "2"):
        for name in DATA_FILES:
            assert (tmp_path / "dask" / "buildings" / b / name).read_bytes() == \
                (out / "buildings" / b / name).read_bytes(), name


def test_stage_order_is_configurable(city: Path, tmp_path: Path) -> None:
    fps = read_footprints(city / "footprints.geojson")
    config = PipelineConfig(run=RunParams(stages=("flatten", "densify")))
    result = run_pipeline([city / "als.laz"], fps, tmp_path / "fd", config)
    points = read_las(tmp_path / "fd" / "buildings" / "1" / "points.laz")
    synthetic = points.attrs["synthetic"].astype(bool)
    # flattening ran first: only input points sit on planes; the new points of the later densification have none
    assert np.all(points.attrs["plane_id"][synthetic] == -1) and np.any(points.attrs["plane_id"][~synthetic] >= 0)
    assert result.records[0]["planes"] > 0


def test_a_building_with_too_few_points_fails_clearly(city: Path, tmp_path: Path) -> None:
    fps = read_footprints(city / "footprints.geojson")
    result = run_pipeline([city / "als.laz"], fps, tmp_path / "few",
                          PipelineConfig(run=RunParams(min_points=100_000, stages=())))
    assert result.records == [] and set(result.failed) == {"1", "2"}
    assert "fewer than min_points = 100000" in result.failed["1"]
    cli = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o", str(tmp_path / "c"),
                  "--stages", "none", "--config", str(_toml(tmp_path, "[run]\nmin_points = 100000\n")))
    assert cli.returncode == 2 and "no building could be reconstructed" in cli.stderr
    assert "fewer than min_points" in cli.stdout and "Traceback" not in cli.stderr


def _toml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "run.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("args,expected", [
    (["--stages", "densify,paint"], "unknown stage(s) paint"),
    (["--method", "magic"], "method must be one of pointnet2, baseline"),
    (["--mesh", "clay"], "mesh must be one of surface, voxels"),
    (["--workers", "0"], "workers must be at least 1"),
    (["--scheduler", "10.0.0.5"], "scheduler address '10.0.0.5' must look like tcp://HOST:PORT"),
])
def test_run_refuses_bad_options_in_one_line(city: Path, tmp_path: Path, args: list[str], expected: str) -> None:
    result = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o",
                     str(tmp_path / "o"), *args)
    assert result.returncode == 2 and expected in result.stderr
    assert result.stderr.strip().count("\n") == 0 and not (tmp_path / "o").exists()


def test_run_refuses_a_foreign_output_folder(city: Path, tmp_path: Path) -> None:
    (tmp_path / "mine.txt").write_text("precious")
    result = run_cli("run", str(city / "als.laz"), "-f", str(city / "footprints.geojson"), "-o", str(tmp_path))
    assert result.returncode == 2 and "was not written by lidarmap" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


# ----------------------------------------------------------------------------------------------------------------------
# Stage adapters on synthetic points


def _roof_and_ground(seed: int = 0) -> PointCloud:
    """A noisy 12 m x 10 m flat roof at 10 m (class 6) over ground (class 2), 1 point per 0.25 m², CRS-sized."""
    rng = np.random.default_rng(seed)
    roof = np.column_stack([rng.uniform(0, 12, 480), rng.uniform(0, 10, 480), 10 + rng.normal(0, 0.03, 480)])
    ground = np.column_stack([rng.uniform(-5, 17, 300), rng.uniform(-5, 15, 300), rng.normal(0, 0.02, 300)])
    xyz = np.vstack([roof, ground]) + [500000.0, 5800000.0, 40.0]
    classes = np.r_[np.full(480, 6), np.full(300, 2)].astype(np.uint8)
    rgb = np.r_[np.tile([[200, 40, 40]], (480, 1)), np.tile([[90, 90, 90]], (300, 1))].astype(np.uint16) * 257
    return PointCloud(xyz=xyz, attrs={"classification": classes, "red": rgb[:, 0], "green": rgb[:, 1],
                                      "blue": rgb[:, 2], "intensity": np.arange(780, dtype=np.uint16)})


def test_densify_cloud_keeps_input_points_and_appends_building_points() -> None:
    cloud = _roof_and_ground()
    dense, stats = densify_cloud(cloud, DensifyParams(), seed=1)
    n = len(cloud)
    assert np.array_equal(dense.xyz[:n], cloud.xyz)  # every input point, in order, untouched
    assert stats["new_points"] == len(dense) - n > 300
    new = dense.attrs["synthetic"][n:].astype(bool)
    assert new.all() and np.all(dense.attrs["classification"][n:] == 6)
    assert np.all(np.abs(dense.xyz[n:, 2] - 50.0) < 0.15)  # on the roof, not on the ground
    assert np.all(dense.rgb8()[n:] == [200, 40, 40])  # colour of a constant-colour roof carried over exactly
    removed = dense.attrs["classification"][:n] == NOISE_CLASS
    assert removed.sum() == stats["outliers_removed"] and np.all(cloud.attrs["classification"][removed] == 6)


def test_flatten_cloud_moves_only_building_points_onto_their_plane() -> None:
    cloud = _roof_and_ground()
    flat, stats = flatten_cloud(cloud, FlattenParams(), seed=0)
    roof = cloud.attrs["classification"] == 6
    assert np.array_equal(flat.xyz[~roof], cloud.xyz[~roof])
    assert stats["planes"] == 1 and np.all(flat.attrs["plane_id"][~roof] == -1)
    on = flat.attrs["plane_id"] >= 0
    assert on.sum() > 0.95 * roof.sum()
    assert np.std(flat.xyz[on, 2]) < 0.1 * np.std(cloud.xyz[on, 2])  # 3 cm noise flattened


def test_building_voxels_use_the_true_majority() -> None:
    # a voxel with 3 ground points and 2 building points is not building; one with 2 building and 1 noise is
    xyz = np.array([[0.1, 0.1, 0.1]] * 5 + [[1.5, 0.5, 0.5]] * 3) + [500000.0, 5800000.0, 40.0]
    classes = np.array([2, 2, 2, 6, 6, 6, 6, NOISE_CLASS], np.uint8)
    grid = building_voxels(PointCloud(xyz=xyz, attrs={"classification": classes}), VoxelParams(size=1.0))
    assert len(grid.ijk) == 1 and grid.count.tolist() == [2]


def test_stage_commands_chain_on_a_file(tmp_path: Path) -> None:
    write_las(tmp_path / "b.laz", _roof_and_ground())
    steps = [("densify", "d"), ("flatten", "f")]
    src = tmp_path / "b.laz"
    for command, folder in steps:
        result = run_cli(command, str(src), "-o", str(tmp_path / folder))
        assert result.returncode == 0, result.stderr
        src = tmp_path / folder / "b.laz"
    assert (tmp_path / "f" / "b.planes.json").exists()
    assert run_cli("voxelize", str(src), "-o", str(tmp_path / "v"), "--size", "2").returncode == 0
    assert read_voxels(tmp_path / "v" / "b.voxels.npz").size == 2.0
    result = run_cli("mesh", str(src), "-o", str(tmp_path / "m"), "--method", "both")
    assert result.returncode == 0, result.stderr
    mesh = trimesh.load(tmp_path / "m" / "b.surface.ply", process=False)
    assert mesh.is_watertight and abs(mesh.bounds[1, 2] - 50.0) < 0.2
    assert (tmp_path / "m" / "b.voxels.obj").exists()


def test_stage_command_without_building_points_is_one_line(tmp_path: Path) -> None:
    cloud = _roof_and_ground()
    cloud.attrs["classification"][:] = 2
    write_las(tmp_path / "ground.laz", cloud)
    result = run_cli("flatten", str(tmp_path / "ground.laz"), "-o", str(tmp_path / "out"))
    assert result.returncode == 2 and result.stderr.strip().count("\n") == 0
    assert "ground.laz: only 0 building (class 6) points" in result.stderr and not (tmp_path / "out").exists()


def test_mesh_footprint_choice_needs_overlap(tmp_path: Path) -> None:
    write_las(tmp_path / "b.laz", _roof_and_ground())
    far = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {"id": "x"}, "geometry":
           shapely.geometry.mapping(shapely.box(0, 0, 1, 1))}]}
    (tmp_path / "far.geojson").write_text(json.dumps(far))
    result = run_cli("mesh", str(tmp_path / "b.laz"), "-o", str(tmp_path / "m"), "-f", str(tmp_path / "far.geojson"))
    assert result.returncode == 2 and "no footprint contains any of the building points" in result.stderr
