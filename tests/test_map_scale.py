"""``lidarmap map update`` at scale: the mobile campaign streamed through a spool (never read whole), buildings on
dask workers or a remote scheduler, the same map whatever the chunking or the workers, a failing building reported
and left as stored while the others are committed.

A small simulated city (2 buildings + a construction site, 2 campaigns); maps are compared through their CityJSON
export, byte for byte. Commands run in-process through the console entry point, as in tests/test_map_cli.py.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
from conftest import run_cli_in_process as run

from lidarmap.map.store import MapStore


def campaign_args(sim, i: int) -> list[object]:
    return ["--points", sim.mls[i - 1], "--trajectory", sim.trajectories[i - 1], "--footprints", sim.footprints]


def update(path: Path, sim, i: int, *extra: object) -> str:
    code, out, err = run("map", "update", path, *campaign_args(sim, i), *extra)
    assert code == 0, err
    return out


def export(path: Path) -> bytes:
    target = path.with_suffix(".city.json")
    code, _, err = run("map", "export", path, "-o", target)
    assert code == 0, err
    return target.read_bytes()


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from lidarmap.sim import SimParams, simulate

    return simulate(tmp_path_factory.mktemp("sim"), SimParams(seed=3, buildings=2, campaigns=2))


@pytest.fixture(scope="module")
def serial(sim, tmp_path_factory):
    """The serial reference: the map file after campaign 1 and the exports after campaigns 1 and 2."""
    folder = tmp_path_factory.mktemp("serial")
    path = folder / "city.lmap"
    update(path, sim, 1)
    first = export(path)
    shutil.copyfile(path, folder / "after1.lmap")
    update(path, sim, 2)
    return {"map1": folder / "after1.lmap", "map2": path, "export1": first, "export2": export(path)}


def test_workers_and_a_remote_scheduler_give_the_serial_map(sim, serial, tmp_path) -> None:
    from distributed import LocalCluster

    path = tmp_path / "city.lmap"
    update(path, sim, 1, "--workers", "2")  # buildings extracted on a LocalCluster of 2 processes
    assert export(path) == serial["export1"]
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      host="127.0.0.1") as cluster:  # an existing cluster, reached through its address only
        update(path, sim, 2, "--scheduler", cluster.scheduler_address)  # buildings refined there
    assert export(path) == serial["export2"]


def test_tiny_chunks_stream_through_the_spool_and_give_the_same_map(sim, serial, tmp_path, monkeypatch) -> None:
    import lidarmap.io.las
    from lidarmap.io.spool import ColumnSpool

    def whole_file(*args, **kwargs):
        raise AssertionError("a mobile campaign must be streamed, never read whole")

    monkeypatch.setattr(lidarmap.io.las, "read_las", whole_file)
    added: list[int] = []
    on_disk: list[tuple[Path, int]] = []
    add, flush = ColumnSpool.add, ColumnSpool.flush

    def spy_add(spool: ColumnSpool, keys, columns) -> None:
        added.append(len(keys))
        add(spool, keys, columns)

    def spy_flush(spool: ColumnSpool) -> None:
        flush(spool)
        on_disk.append((spool.folder, len(list(spool.folder.glob("run*")))))

    monkeypatch.setattr(ColumnSpool, "add", spy_add)
    monkeypatch.setattr(ColumnSpool, "flush", spy_flush)
    config = tmp_path / "update.toml"
    config.write_text("[update]\nchunk_points = 60000\ncell = 10.0\n")
    path = tmp_path / "maps" / "city.lmap"
    path.parent.mkdir()
    update(path, sim, 1, "--config", config)
    assert len(added) == -(-sim.mls_points[0] // 60000) and max(added) == 60000  # chunk by chunk
    folder, runs = on_disk[-1]
    assert runs == len(added) and folder.parent.parent == path.parent  # one run per chunk, on disk beside the map
    assert sorted(p.name for p in path.parent.iterdir()) == ["city.lmap", "city.lmap.lock"]  # spool removed
    assert export(path) == serial["export1"]
    update(path, sim, 2, "--config", config)
    assert export(path) == serial["export2"]


@pytest.mark.parametrize("group_size", [0.0, 1000.0])
def test_one_building_per_task_or_one_task_for_all_gives_the_same_map(sim, serial, tmp_path, monkeypatch,
                                                                      group_size) -> None:
    import lidarmap.map.update

    members: list[list[str]] = []
    real = lidarmap.map.update.group_task

    def spy(job, *shared, **kwargs):
        members.append([m.building_id for m in job.members])
        return real(job, *shared, **kwargs)

    monkeypatch.setattr(lidarmap.map.update, "group_task", spy)
    config = tmp_path / "update.toml"
    config.write_text(f"[update]\ngroup_size = {group_size}\n")
    path = tmp_path / "city.lmap"
    update(path, sim, 1, "--config", config)
    assert export(path) == serial["export1"]
    update(path, sim, 2, "--config", config)
    assert export(path) == serial["export2"]
    buildings = sorted(b for group in members for b in group)
    assert len(buildings) >= 6 and len(set(buildings)) >= 3  # 2 campaigns x (2 buildings + the site)
    if group_size:
        assert len(members) == 2  # one task per campaign, sharing one context
    else:
        assert all(len(group) == 1 for group in members)


def _doc(m) -> str:
    from lidarmap.export.cityjson import map_to_cityjson

    return json.dumps(map_to_cityjson(dataclasses.replace(m, campaigns=[])), sort_keys=True)


def test_height_rule_ground_gives_the_same_map_in_one_chunk_and_in_many(sim) -> None:
    """Without classes, ground comes from the lowest points of 2 m cells around each point: gathered chunk by
    chunk, it must give exactly the ground (and the map) of the whole campaign at once."""
    from lidarmap.facade.params import FacadeParams
    from lidarmap.io.footprints import read_footprints
    from lidarmap.io.las import read_las
    from lidarmap.io.trajectory import read_trajectory
    from lidarmap.map.model import BuildingMap
    from lidarmap.map.refine import RefineParams
    from lidarmap.map.update import (
        CampaignSource,
        UpdateParams,
        cloud_source,
        fuse_campaign,
    )

    cloud = read_las(sim.mls[0])
    del cloud.attrs["classification"]
    trajectory = read_trajectory(sim.trajectories[0])
    footprints = read_footprints(sim.footprints, crs=cloud.crs)
    args = (trajectory, footprints, FacadeParams(), RefineParams(), 1, 0)
    whole = cloud_source(cloud)
    step = 70_000
    chunked = CampaignSource(lambda: (cloud.subset(slice(a, a + step)) for a in range(0, len(cloud), step)),
                             whole.lo, whole.hi, len(cloud), cloud.crs, cloud.source)
    one = fuse_campaign(BuildingMap(crs_wkt=""), whole, *args).map
    many = fuse_campaign(BuildingMap(crs_wkt=""), chunked, *args, update=UpdateParams(chunk_points=step, cell=10.0))
    assert one.buildings and _doc(many.map) == _doc(one)


def _building(path: Path, bid: str) -> str:
    """One building of a map as CityJSON text (its own vertex list, so buildings of two maps compare)."""
    from lidarmap.export.cityjson import map_to_cityjson

    with MapStore.open(path) as store:
        m = store.load()
    return json.dumps(map_to_cityjson(dataclasses.replace(m, buildings={bid: m.buildings[bid]}, campaigns=[])),
                      sort_keys=True)


def test_a_failing_building_is_reported_kept_as_stored_and_the_others_committed(sim, serial, tmp_path,
                                                                                   monkeypatch) -> None:
    import lidarmap.map.update

    path = tmp_path / "city.lmap"
    shutil.copyfile(serial["map1"], path)
    with MapStore.open(path) as store:
        before = store.load()
    victim = sorted(before.buildings)[0]
    real = lidarmap.map.update.building_task

    def flaky(job, *shared):
        if job.building_id == victim:
            raise ValueError("simulated bad data")
        return real(job, *shared)

    monkeypatch.setattr(lidarmap.map.update, "building_task", flaky)
    out = update(path, sim, 2)
    assert f"failed {victim}: ValueError: simulated bad data (kept as stored)" in out
    assert "1 building(s) failed" in out
    with MapStore.open(path) as store:
        after = store.load()
        campaign = store.campaigns()[-1]
    assert campaign.campaign_id == 2 and campaign.summary["failed"] == {victim: "ValueError: simulated bad data"}
    assert _building(path, victim) == _building(serial["map1"], victim)  # as stored after campaign 1
    others = [bid for bid in after.buildings if bid != victim]
    assert others and all(_building(path, bid) == _building(serial["map2"], bid) for bid in others)


def test_a_campaign_whose_every_building_fails_is_refused(sim, serial, tmp_path, monkeypatch) -> None:
    import lidarmap.map.update

    def broken(job, *shared):
        raise RuntimeError("a bug")

    monkeypatch.setattr(lidarmap.map.update, "building_task", broken)
    path = tmp_path / "city.lmap"
    shutil.copyfile(serial["map1"], path)
    before = path.read_bytes()
    code, out, err = run("map", "update", path, *campaign_args(sim, 2))
    assert code == 2 and "the task of every building failed" in err and "RuntimeError: a bug" in err, err
    assert path.read_bytes() == before  # not marked applied: the campaign can be applied once fixed


def test_update_table_of_the_config(sim, tmp_path) -> None:
    from lidarmap.map.update import UpdateParams

    assert (UpdateParams().workers, UpdateParams().scheduler, UpdateParams().chunk_points,
            UpdateParams().group_size) == (1, "", 2_000_000, 60.0)
    for text, needle in (("[update]\nbogus = 1\n", "unknown option 'bogus' in [update]"),
                         ("[update]\ngroup_size = -1.0\n", "group_size must be >= 0"),
                         ("[update]\nworkers = 0\n", "workers must be at least 1"),
                         ("[update]\nscheduler = 'host:1'\n", "must look like tcp://HOST:PORT")):
        config = tmp_path / "bad.toml"
        config.write_text(text)
        code, _, err = run("map", "update", tmp_path / "new.lmap", *campaign_args(sim, 1), "--config", config)
        assert code == 2 and needle in err and "bad.toml" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "new.lmap").exists()
