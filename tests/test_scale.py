"""Scale: the spool that bounds memory, tasks on dask (local cluster on loopback, a worker killed mid-task), results
that depend neither on the tiling nor on where the tasks ran, failures reported per building."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import cloudpickle
import numpy as np
import pytest
from distributed import LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from lidarmap.aerial.pipeline import PipelineConfig, RunParams, run_pipeline
from lidarmap.aerial.prep import PrepParams
from lidarmap.errors import InputError
from lidarmap.executor import TaskFailure, map_tasks
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las, write_las
from lidarmap.io.spool import ColumnSpool
from lidarmap.sim import SimParams, simulate

# the task functions and the plugin below travel to the worker processes by value (tests/ is not importable there)
cloudpickle.register_pickle_by_value(sys.modules[__name__])

DATA_FILES = ("points.laz", "voxels.npz", "voxels.vox", "mesh.ply", "mesh.obj", "mesh_voxels.ply")


# ----------------------------------------------------------------------------------------------------------------------
# The spool


@pytest.mark.parametrize("on_disk", [False, True])
def test_spool_returns_each_keys_rows_in_insertion_order(tmp_path: Path, on_disk: bool) -> None:
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 7, 10_000)
    xyz = rng.normal(size=(10_000, 3))
    label = np.arange(10_000, dtype=np.int32)
    spool = ColumnSpool(7, tmp_path / "spool" if on_disk else None, buffer_rows=1_500)
    for start in range(0, 10_000, 1_000):  # 10 adds, a run written every second add
        spool.add(keys[start:start + 1_000], {"xyz": xyz[start:start + 1_000], "label": label[start:start + 1_000]})
    if on_disk:
        assert len(list((tmp_path / "spool").glob("run*"))) == 5  # memory held one buffer at a time
    for k in range(7):
        got = spool.get(k)
        np.testing.assert_array_equal(got["label"], label[keys == k])
        np.testing.assert_array_equal(got["xyz"], xyz[keys == k])
    both = spool.get_many([3, 1], ["label"])["label"]
    np.testing.assert_array_equal(both, np.concatenate([label[keys == 3], label[keys == 1]]))
    np.testing.assert_array_equal(spool.counts, np.bincount(keys, minlength=7))
    with pytest.raises(ValueError, match="columns"):
        spool.add(keys[:2], {"xyz": xyz[:2]})
    spool.close()
    assert not (tmp_path / "spool").exists()


# ----------------------------------------------------------------------------------------------------------------------
# Tasks on dask


def _double_or_fail(payload: tuple[int, str]) -> int:
    value, marker = payload
    if value == 3:
        raise InputError("bad data in task 3")
    return 2 * value


def _kill_worker_once(marker: str) -> None:
    if not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(1)  # the worker process dies mid-task, without any cleanup


class KillOnce(WorkerPlugin):
    """Kills the first worker that starts executing a task (once per marker file)."""

    def __init__(self, marker: str):
        self.marker = marker

    def transition(self, key, start, finish, **kwargs) -> None:  # noqa: ANN001 - dask's signature
        if finish == "executing":
            _kill_worker_once(self.marker)


@pytest.fixture()
def loopback_cluster():
    """A 2-process cluster on loopback, used through its address as a remote scheduler would be (one per test: a
    killed worker is not restarted)."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      host="127.0.0.1") as cluster:
        yield cluster


def test_map_tasks_survives_a_killed_worker_and_reports_failing_tasks(loopback_cluster, tmp_path: Path) -> None:
    from distributed import Client

    marker = str(tmp_path / "killed")
    with Client(loopback_cluster.scheduler_address) as client:
        client.register_plugin(KillOnce(marker), name=f"kill-once-{tmp_path.name}")
        try:
            results = dict(map_tasks(_double_or_fail, [(v, marker) for v in range(8)], client=client))
        finally:
            client.unregister_worker_plugin(f"kill-once-{tmp_path.name}")
    assert os.path.exists(marker)  # a worker did die mid-task
    assert results.pop(3) == TaskFailure("bad data in task 3")
    assert results == {v: 2 * v for v in range(8) if v != 3}  # nothing lost
    serial = dict(map_tasks(_double_or_fail, [(v, marker) for v in range(8)]))
    assert serial[3] == TaskFailure("bad data in task 3") and serial[5] == 10


# ----------------------------------------------------------------------------------------------------------------------
# The aerial pipeline at scale


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("city")
    simulate(out, SimParams(seed=5, buildings=3, campaigns=0))
    return out


@pytest.fixture(scope="module")
def serial_run(city: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "out"
    run_pipeline([city / "als.laz"], read_footprints(city / "footprints.geojson"), out)
    return out


def _same_buildings(a: Path, b: Path, exact: tuple[str, ...] = DATA_FILES) -> None:
    """Byte-identical files ``exact``; the others (double-precision meshes) equal to 1e-6 m."""
    import trimesh

    names = sorted(p.name for p in (a / "buildings").iterdir())
    assert names and names == sorted(p.name for p in (b / "buildings").iterdir())
    for name in names:
        for data in DATA_FILES:
            fa, fb = a / "buildings" / name / data, b / "buildings" / name / data
            if data in exact:
                assert fa.read_bytes() == fb.read_bytes(), f"{name}/{data}"
            else:
                ma, mb = trimesh.load(fa, process=False), trimesh.load(fb, process=False)
                np.testing.assert_array_equal(ma.faces, mb.faces)
                np.testing.assert_allclose(ma.vertices, mb.vertices, rtol=0, atol=1e-6)


def test_results_do_not_depend_on_tile_edges_or_chunks(city: Path, serial_run: Path, tmp_path: Path) -> None:
    cloud = read_las(city / "als.laz")
    mid = np.median(cloud.xyz[:, :2], axis=0)  # cuts through the buildings of the middle of the city
    tiles = []
    for i, east in enumerate((False, True)):
        for j, north in enumerate((False, True)):
            inside = ((cloud.xyz[:, 0] >= mid[0]) == east) & ((cloud.xyz[:, 1] >= mid[1]) == north)
            tiles.append(write_las(tmp_path / f"tile_{i}{j}.laz", cloud.subset(np.flatnonzero(inside)[::-1])))
    config = PipelineConfig(prep=PrepParams(chunk_points=7_919))
    result = run_pipeline(tiles[::-1], read_footprints(city / "footprints.geojson"), tmp_path / "tiled", config)
    assert result.prep.points_read == len(cloud) and not result.failed
    # each tile decodes its integer coordinates with its own LAS offset: the same points to the last bits (the
    # point files, stored at 1 mm, are byte-identical), double-precision mesh vertices to ~1e-9 m
    _same_buildings(serial_run, tmp_path / "tiled", exact=("points.laz", "voxels.npz", "voxels.vox"))


def test_a_remote_scheduler_with_a_killed_worker_writes_the_serial_results(city: Path, serial_run: Path,
                                                                            loopback_cluster, tmp_path: Path) -> None:
    from distributed import Client

    marker = str(tmp_path / "killed")
    with Client(loopback_cluster.scheduler_address) as client:
        client.register_plugin(KillOnce(marker), name="kill-once-run")
        try:
            config = PipelineConfig(run=RunParams(scheduler=loopback_cluster.scheduler_address))
            result = run_pipeline([city / "als.laz"], read_footprints(city / "footprints.geojson"),
                                  tmp_path / "remote", config)
        finally:
            client.unregister_worker_plugin("kill-once-run")
    assert os.path.exists(marker) and not result.failed
    _same_buildings(serial_run, tmp_path / "remote")


def test_a_scheduler_without_workers_is_a_one_line_error_not_a_hang(city: Path, tmp_path: Path, monkeypatch) -> None:
    from conftest import run_cli_in_process

    import lidarmap.executor as distributed

    monkeypatch.setattr(distributed, "WORKERS_TIMEOUT_S", 1)
    with LocalCluster(n_workers=0, processes=True, dashboard_address=None, host="127.0.0.1") as empty:
        code, _, err = run_cli_in_process("run", city / "als.laz", "-f", city / "footprints.geojson",
                                          "-o", tmp_path / "out", "--scheduler", empty.scheduler_address)
    assert code != 0 and "Traceback" not in err
    assert f"the dask scheduler at {empty.scheduler_address} has no workers (waited 1 s)" in err
    assert len(err.strip().splitlines()) == 1
    assert not list((tmp_path / "out").glob("buildings/*/building.json"))  # nothing half-written


def test_a_failing_building_is_reported_and_the_others_are_written(city: Path, tmp_path: Path, monkeypatch) -> None:
    import lidarmap.aerial.pipeline as pipeline

    real = pipeline.process_building

    def broken(bp, probability, config):
        if bp.id == "2":
            raise ValueError("simulated bad data")
        return real(bp, probability, config)

    monkeypatch.setattr(pipeline, "process_building", broken)
    result = run_pipeline([city / "als.laz"], read_footprints(city / "footprints.geojson"), tmp_path / "out")
    assert result.failed == {"2": "ValueError: simulated bad data"}
    assert "2" not in result.processed and len(result.processed) >= 2
    assert not (tmp_path / "out" / "buildings" / "2").exists()
    summary = (tmp_path / "out" / "summary.json").read_text()
    assert "simulated bad data" in summary
    monkeypatch.setattr(pipeline, "process_building", real)
    again = run_pipeline([city / "als.laz"], read_footprints(city / "footprints.geojson"), tmp_path / "out")
    assert again.processed == ["2"] and not again.failed  # the rerun resumes: only the failed building


def test_streamed_cityjson_shares_the_vertices_of_touching_buildings(tmp_path: Path) -> None:
    import json

    import trimesh
    from shapely.geometry import box

    from lidarmap.export.cityjson import AerialBuilding, write_aerial_cityjson
    from lidarmap.export.validate import validate_cityjson

    def block(x0: float) -> AerialBuilding:  # 10 m x 8 m x 6 m row houses sharing the wall at x0 + 10
        mesh = trimesh.creation.box(extents=(10, 8, 6))
        mesh.apply_translation((85000 + x0 + 5, 447000 + 4, 3))
        return AerialBuilding(id=f"b{x0:g}", footprint=box(85000 + x0, 447000, 85010 + x0, 447008), ground_z=0.0,
                              height=6.0, mesh_vertices=np.asarray(mesh.vertices), mesh_faces=np.asarray(mesh.faces),
                              attributes={"x0": x0})

    path = write_aerial_cityjson(tmp_path / "c.city.json", (block(x) for x in (0, 10, 20)), "", (85000, 447000, 0))
    doc = json.loads(path.read_text())
    assert validate_cityjson(doc) == []  # also: no vertex listed twice
    vertices = np.asarray(doc["vertices"]) * 0.001 + np.array([85000, 447000, 0])
    assert len(vertices) == 16  # 3 boxes x 8 corners, 2 shared walls x 4 corners merged
    lod2 = doc["CityObjects"]["b10"]["geometry"][1]
    corners = vertices[np.unique(np.concatenate([np.ravel(r) for s in lod2["boundaries"][0] for r in s]))]
    np.testing.assert_allclose(corners.min(axis=0), [85010, 447000, 0])
    np.testing.assert_allclose(corners.max(axis=0), [85020, 447008, 6])
    assert doc["metadata"]["geographicalExtent"] == [85000, 447000, 0, 85030, 447008, 6]
