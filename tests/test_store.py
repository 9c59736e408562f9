"""The map store (lidarmap.map.store): exact round trips, history (as_of), one-transaction commits that survive a killed
process, the writer lock, schema versions and one-line errors for files that are not maps.

Maps are synthetic (no simulator): two buildings with every kind of content (frames at 30°, layers, a window, a door,
a structure with a hole, an unknown region with ε = ∞, NaN and -0.0 values, evidence grids of several dtypes, a roof
plane, a multi-part footprint, unicode ids and attributes).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pickle
import sqlite3
import struct
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
from pyproj import CRS
from shapely.geometry import MultiPolygon, Polygon, box

from lidarmap.errors import InputError, LidarmapError, MapLockedError
from lidarmap.facade.model import (
    Element,
    ElementKind,
    Facade,
    FacadeEvidence,
    FacadeFrame,
    Layer,
)
from lidarmap.map.model import Building, BuildingMap, Campaign, RoofPlane
from lidarmap.map.store import (
    SCHEMA_VERSION,
    MapStore,
    campaign_fingerprint,
    lock_path_for,
    writer_lock,
)

CRS_WKT = CRS.from_epsg(32632).to_wkt()
ORIGIN = np.array([500123.456789012, 5800321.123456789, 41.5])
U30 = np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0)), 0.0])


# ----------------------------------------------------------------------------------------------------------------------
# Synthetic maps


def _evidence(seed: int, shape=(40, 60)) -> FacadeEvidence:
    rng = np.random.default_rng(seed)
    return FacadeEvidence(cell=0.1, s0=-0.05, t0=-0.55,
                          window_votes=rng.integers(0, 4, shape).astype(np.int16),
                          object_votes=rng.integers(0, 3, shape).astype(np.uint8),
                          seen=rng.random(shape) < 0.8)


def _facade_a(window_width: float = 1.2, evidence_seed: int = 1, campaigns=(1,)) -> Facade:
    campaigns = list(campaigns)
    structure = Polygon([(8.0, 5.0), (11.5, 5.0), (11.5, 6.2), (8.0, 6.2)], [[(9.0, 5.3), (10.0, 5.3), (10.0, 5.9)]])
    return Facade(
        facade_id=0, frame=FacadeFrame(ORIGIN, U30), sigma=0.0123, extent=(-0.0, 18.2, -0.5, 12.25),
        layers=[Layer(0, mu=-0.3, sigma=0.011, weight=0.1, n_points=500, campaigns=campaigns),
                Layer(1, mu=0.0, sigma=0.009, weight=0.9, n_points=20000, campaigns=campaigns),
                Layer(2, mu=0.95, sigma=float("nan"), weight=1e-300, n_points=3, campaigns=campaigns)],
        elements=[
            Element(0, ElementKind.WINDOW, box(1.5, 3.5, 1.5 + window_width, 4.9), 1, 0.0762, 0, campaigns),
            Element(1, ElementKind.DOOR, box(16.5, 0.0, 17.7, 2.2), 0, 0.1353, 210, campaigns),
            Element(2, ElementKind.STRUCTURE, structure, 2, 0.998, 1500, campaigns),
            Element(3, ElementKind.UNKNOWN, Polygon([(4.0, 0.0), (6.2, 0.0), (6.2, 2.7), (4.0, 2.7)]), None,
                    float("inf"), 0, campaigns),
        ],
        main_layer=1, n_points=22503, footprint_edge=3, campaigns=campaigns, evidence=_evidence(evidence_seed))


def _facade_bare() -> Facade:
    frame = FacadeFrame(ORIGIN + [18.2 * U30[0], 18.2 * U30[1], 0.0], np.array([-U30[1], U30[0], 0.0]))
    return Facade(facade_id=1, frame=frame, sigma=float("nan"), extent=(0.0, 10.0, 0.0, 12.25), n_points=40,
                  campaigns=[1])


def _roof(offset: float = -45.6) -> RoofPlane:
    return RoofPlane(plane_id=0, normal=np.array([0.1, -0.2, math.sqrt(1 - 0.05)]), offset=offset,
                     outline=box(500100.0, 5800300.0, 500115.0, 5800312.0), sigma=0.02, n_points=900, campaigns=[1])


def map_v1() -> BuildingMap:
    a = Building("A", Polygon([(500100, 5800300), (500120, 5800300), (500120, 5800315), (500100, 5800315)],
                              [[(500105, 5800305), (500108, 5800305), (500108, 5800308)]]),
                 {"height": 12.5, "status": "existing", "missing": float("nan"), "nested": {"k": [1, 2]}, "zero": -0.0},
                 facades=[_facade_a(), _facade_bare()], roofs=[_roof()])
    b = Building("B/2 ü", MultiPolygon([box(500200, 5800300, 500210, 5800310), box(500220, 5800300, 500225, 5800305)]),
                 {"name": "Hôtel de Ville"})
    return BuildingMap(CRS_WKT, {"A": a, "B/2 ü": b})


def map_v2() -> BuildingMap:
    """v1 after campaign 2: window widened, layer 0 gone, new evidence, an attribute changed, building C added."""
    m = map_v1()
    a = m.buildings["A"]
    a.attributes["status"] = "renovated"
    a.facades[0] = _facade_a(window_width=1.3, evidence_seed=2, campaigns=(1, 2))
    del a.facades[0].layers[0]
    m.buildings["C"] = Building("C", box(500300, 5800300, 500310, 5800310), {})
    return m


def map_v3() -> BuildingMap:
    """v2 after campaign 3: building B removed, the roof plane refitted."""
    m = map_v2()
    del m.buildings["B/2 ü"]
    m.buildings["A"].roofs = [_roof(offset=-45.625)]
    return m


def campaign(cid: int, fingerprint: str | None = None) -> Campaign:
    return Campaign(campaign_id=cid, kind="mobile", source=f"mls_{cid}.laz", fingerprint=fingerprint or f"fp{cid}",
                    n_points=1000 * cid, created=f"2024-05-0{cid}T10:00:00+00:00", summary={"windows": cid})


def with_campaigns(m: BuildingMap, *cids: int) -> BuildingMap:
    m.campaigns = [campaign(c) for c in cids]
    return m


def commit(store: MapStore, m: BuildingMap, cid: int) -> dict:
    with_campaigns(m, *range(1, cid + 1))
    return store.commit(m, m.campaigns[-1])


# ----------------------------------------------------------------------------------------------------------------------
# Exact comparison


def _same_float(a: float, b: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return struct.pack("<d", a) == struct.pack("<d", b)  # -0.0 != 0.0 here


def assert_identical(a: Any, b: Any, where: str = "map") -> None:
    """Field by field, floats bit for bit (NaN == NaN), arrays with dtype, geometries by WKB."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for field in dataclasses.fields(a):
            assert_identical(getattr(a, field.name), getattr(b, field.name), f"{where}.{field.name}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, where
        if a.dtype.kind == "f":
            assert all(_same_float(x, y) for x, y in zip(a.ravel().tolist(), b.ravel().tolist())), where
        else:
            assert a.tobytes() == b.tobytes(), where
    elif isinstance(a, shapely.Geometry):
        assert shapely.to_wkb(a) == shapely.to_wkb(b), where
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for key in a:
            assert_identical(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_identical(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert isinstance(b, float) and _same_float(a, b), f"{where}: {a!r} != {b!r}"
    else:
        assert type(a) is type(b) and a == b, f"{where}: {a!r} != {b!r}"


@pytest.fixture
def store(tmp_path: Path):
    s = MapStore.create(tmp_path / "city.lmap", CRS_WKT)
    yield s
    s.close()


# ----------------------------------------------------------------------------------------------------------------------
# Round trip and history


def test_round_trip_every_field_exact(store: MapStore, tmp_path: Path) -> None:
    m = map_v1()
    commit(store, m, 1)
    assert_identical(store.load(), m)
    with MapStore.open(tmp_path / "city.lmap") as again:  # a new connection reads the file, not a cache
        loaded = again.load()
    assert_identical(loaded, m)
    facade = loaded.buildings["A"].facades[0]
    assert math.copysign(1.0, facade.extent[0]) == -1.0  # -0.0 kept
    assert math.isinf(facade.elements[3].uncertainty) and facade.elements[3].is_unknown
    assert math.isnan(facade.layers[2].sigma) and facade.layers[2].weight == 1e-300
    assert facade.evidence.window_votes.dtype == np.int16 and facade.evidence.seen.dtype == bool


def test_as_of_reproduces_every_earlier_state(store: MapStore) -> None:
    changes = [commit(store, v, cid) for cid, v in ((1, map_v1()), (2, map_v2()), (3, map_v3()))]
    assert_identical(store.load(as_of=1), with_campaigns(map_v1(), 1))
    assert_identical(store.load(as_of=2), with_campaigns(map_v2(), 1, 2))
    assert_identical(store.load(as_of=3), with_campaigns(map_v3(), 1, 2, 3))
    assert_identical(store.load(), with_campaigns(map_v3(), 1, 2, 3))
    assert changes[0]["buildings"] == {"added": 2, "updated": 0, "removed": 0}
    assert changes[0]["elements"] == {"added": 4, "updated": 0, "removed": 0}
    # campaign 2: façade 0 rewritten (campaigns), layer 0 removed, layers 1-2 and all 4 elements updated, new evidence
    assert changes[1] == {"buildings": {"added": 1, "updated": 1, "removed": 0},
                          "facades": {"added": 0, "updated": 1, "removed": 0},
                          "layers": {"added": 0, "updated": 2, "removed": 1},
                          "elements": {"added": 0, "updated": 4, "removed": 0},
                          "evidence": {"added": 0, "updated": 1, "removed": 0},
                          "roofs": {"added": 0, "updated": 0, "removed": 0}}
    assert changes[2]["buildings"] == {"added": 0, "updated": 0, "removed": 1}
    assert changes[2]["roofs"] == {"added": 0, "updated": 1, "removed": 0}
    assert [(c.campaign_id, ch) for c, ch in store.history()] == list(zip((1, 2, 3), changes))
    # unchanged rows are not rewritten: façade 1 of A has one version over three campaigns
    rows = store.conn.execute("SELECT COUNT(*) FROM facade_versions v JOIN facades f ON f.id = v.facade "
                              "WHERE f.facade_id = 1").fetchone()[0]
    assert rows == 1
    with pytest.raises(LidarmapError, match=r"no campaign 4 in this map \(campaigns: 1, 2, 3\)"):
        store.load(as_of=4)


def test_reapplied_old_or_stale_campaigns_are_refused(store: MapStore) -> None:
    commit(store, map_v1(), 1)
    m = with_campaigns(map_v2(), 1, 2)
    m.campaigns[-1] = campaign(2, fingerprint="fp1")
    with pytest.raises(LidarmapError, match="campaign already applied: fingerprint fp1… matches campaign 1"):
        store.commit(m, m.campaigns[-1])
    with pytest.raises(LidarmapError, match="campaign id 1 is not newer than the map's latest campaign 1"):
        store.commit(with_campaigns(map_v2(), 1), campaign(1, "other"))
    stale = with_campaigns(map_v2(), 2)  # loaded before campaign 1 was committed by someone else
    with pytest.raises(MapLockedError, match=r"the map changed since it was loaded \(campaign\(s\) 1 committed"):
        store.commit(stale, stale.campaigns[-1])
    assert store.has_fingerprint("fp1") and not store.has_fingerprint("fp2")
    assert_identical(store.load(), with_campaigns(map_v1(), 1))  # refused commits wrote nothing


def test_fingerprint_is_the_bytes_of_points_then_trajectory(tmp_path: Path) -> None:
    points, traj = tmp_path / "p.laz", tmp_path / "t.csv"
    points.write_bytes(b"LASF" + bytes(range(256)) * 10)
    traj.write_text("time,x,y,z\n0,1,2,3\n1,2,3,4\n")
    fp = campaign_fingerprint(points, traj)
    assert fp == campaign_fingerprint(points, traj, chunk=7)  # independent of the read size
    assert fp != campaign_fingerprint(points) != campaign_fingerprint(traj)
    traj.write_text("time,x,y,z\n0,1,2,3\n1,2,3,5\n")
    assert campaign_fingerprint(points, traj) != fp
    with pytest.raises(InputError, match="nope.laz: file not found"):
        campaign_fingerprint(tmp_path / "nope.laz")


# ----------------------------------------------------------------------------------------------------------------------
# Crash safety and concurrency (separate processes)

_CHILD_PRELUDE = """
import os, pickle, signal, sys, time
import lidarmap.map.store as st
"""


def _child(tmp_path: Path, body: str, *args: str) -> subprocess.Popen:
    script = tmp_path / "child.py"
    script.write_text(_CHILD_PRELUDE + textwrap.dedent(body))
    return subprocess.Popen([sys.executable, str(script), *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _big_map(cid: int) -> BuildingMap:
    """v2 with large incompressible evidence grids: the commit writes megabytes, more than the page cache holds."""
    m = with_campaigns(map_v2(), *range(1, cid + 1))
    rng = np.random.default_rng(5)
    for i in range(6):
        f = _facade_a(campaigns=(1, cid))
        f.facade_id = 10 + i
        f.evidence = FacadeEvidence(0.1, 0.0, 0.0, rng.integers(0, 2**31, (300, 300)).astype(np.int32),
                                    rng.integers(0, 255, (300, 300)).astype(np.uint8), rng.random((300, 300)) < 0.5)
        m.buildings["A"].facades.append(f)
    return m


def test_process_killed_mid_commit_leaves_the_previous_map(store: MapStore, tmp_path: Path) -> None:
    path = store.path
    commit(store, map_v1(), 1)
    store.close()
    before = with_campaigns(map_v1(), 1)
    (tmp_path / "new.pkl").write_bytes(pickle.dumps(_big_map(2)))
    child = _child(tmp_path, """
        new_map = pickle.loads(open(sys.argv[2], "rb").read())
        store = st.MapStore.open(sys.argv[1])
        store.conn.execute("PRAGMA cache_size = 2")  # spill the open transaction's pages into the WAL file
        calls = []
        insert = st._insert_version
        def insert_then_die(*args):
            insert(*args)
            calls.append(1)
            if len(calls) == 60:  # half-way: the campaign row, versions and 3 of 7 evidence grids, not committed
                os.kill(os.getpid(), signal.SIGKILL)
        st._insert_version = insert_then_die
        store.commit(new_map, new_map.campaigns[-1])
        print("committed")
    """, str(path), str(tmp_path / "new.pkl"))
    out, err = child.communicate(timeout=60)
    assert child.returncode == -9, (out, err)
    assert "committed" not in out
    wal = path.with_name(path.name + "-wal")
    assert wal.exists() and wal.stat().st_size > 500_000  # the uncommitted evidence pages really reached the disk
    with MapStore.open(path) as reopened:
        assert reopened.conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert_identical(reopened.load(), before)
        assert [c.campaign_id for c in reopened.campaigns()] == [1]
        big = _big_map(2)
        reopened.commit(big, big.campaigns[-1])  # campaign 2 was never applied: it can be now
        assert_identical(reopened.load(), big)


def test_second_writer_is_refused_while_the_first_holds_the_lock(store: MapStore, tmp_path: Path) -> None:
    commit(store, map_v1(), 1)
    child = _child(tmp_path, """
        with st.writer_lock(sys.argv[1]):
            print("locked", flush=True)
            sys.stdin.readline()
    """, str(store.path))
    try:
        assert child.stdout.readline().strip() == "locked"
        m = with_campaigns(map_v2(), 1, 2)
        with pytest.raises(MapLockedError, match=r"city.lmap: another process is updating this map \(lock "
                                                 r"city.lmap.lock is held\)"):
            store.commit(m, m.campaigns[-1])
        with pytest.raises(MapLockedError):
            with writer_lock(store.path):
                pass
        assert_identical(store.load(), with_campaigns(map_v1(), 1))  # readers are not blocked
    finally:
        child.communicate("\n", timeout=30)
    assert child.returncode == 0
    assert lock_path_for(store.path).exists()  # kept beside an existing map
    with writer_lock(tmp_path / "never-made.lmap"):
        assert lock_path_for(tmp_path / "never-made.lmap").exists()
    assert not lock_path_for(tmp_path / "never-made.lmap").exists()  # removed: there is no map
    store.commit(m, m.campaigns[-1])  # the lock is free again
    assert [c.campaign_id for c in store.campaigns()] == [1, 2]


def test_open_sqlite_write_transaction_refuses_a_commit_after_the_busy_timeout(tmp_path: Path) -> None:
    path = tmp_path / "city.lmap"
    MapStore.create(path, CRS_WKT).close()
    with MapStore.open(path) as first:
        commit(first, map_v1(), 1)
    child = _child(tmp_path, """
        import sqlite3
        conn = sqlite3.connect(sys.argv[1], isolation_level=None)
        conn.execute("BEGIN IMMEDIATE")
        conn.execute("UPDATE meta SET value = 'x' WHERE key = 'created'")  # written, not committed
        print("writing", flush=True)
        sys.stdin.readline()
        conn.execute("ROLLBACK")
    """, str(path))
    try:
        assert child.stdout.readline().strip() == "writing"
        with MapStore.open(path, busy_timeout=0.2) as second:
            assert_identical(second.load(), with_campaigns(map_v1(), 1))  # the committed state, not the open one
            m = with_campaigns(map_v2(), 1, 2)
            with pytest.raises(MapLockedError, match="another process is writing this map .database is locked."):
                second.commit(m, m.campaigns[-1])
    finally:
        child.communicate("\n", timeout=30)
    with MapStore.open(path) as third:
        assert [c.campaign_id for c in third.campaigns()] == [1]


# ----------------------------------------------------------------------------------------------------------------------
# Opening: versions, files that are not maps, creation


def test_newer_schema_version_is_refused(store: MapStore) -> None:
    store.close()
    with sqlite3.connect(store.path) as conn:
        conn.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    conn.close()
    with pytest.raises(InputError) as err:
        MapStore.open(store.path)
    assert str(err.value) == (f"{store.path}: map schema version {SCHEMA_VERSION + 1} is newer than this lidarmap "
                              f"supports ({SCHEMA_VERSION}); upgrade lidarmap")


@pytest.mark.parametrize("case,message", [
    ("missing", "map not found"),
    ("folder", "not a lidarmap map (not a file)"),
    ("text", "not a lidarmap map (not an SQLite database)"),
    ("empty", "not a lidarmap map (not an SQLite database)"),
    ("other-sqlite", "not a lidarmap map (an SQLite database without lidarmap tables)"),
    ("foreign-schema", "not a lidarmap map (no lidarmap schema version)"),
])
def test_files_that_are_not_maps(tmp_path: Path, case: str, message: str) -> None:
    path = tmp_path / "x.lmap"
    if case == "folder":
        path.mkdir()
    elif case == "text":
        path.write_text("time,x,y,z\n")
    elif case == "empty":
        path.write_bytes(b"")
    elif case in ("other-sqlite", "foreign-schema"):
        with sqlite3.connect(path) as conn:
            conn.execute("CREATE TABLE points (x REAL)")
            if case == "foreign-schema":
                conn.execute("CREATE TABLE schema_version (version INTEGER)")
                conn.execute("CREATE TABLE meta (key TEXT, value TEXT)")
                conn.execute("INSERT INTO schema_version VALUES (1)")
        conn.close()
    with pytest.raises(InputError) as err:
        MapStore.open(path)
    assert str(err.value) == f"{path}: {message}"
    assert "\n" not in str(err.value)


def test_create_is_atomic_refuses_existing_and_checks_the_crs(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "city.lmap"
    with MapStore.create(path, CRS_WKT) as s:
        assert s.schema_version == SCHEMA_VERSION and CRS.from_user_input(s.crs_wkt).to_epsg() == 32632
        assert s.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert s.load().buildings == {} and s.next_campaign_id() == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["city.lmap"]  # no temporary file left
    assert path.stat().st_mode & 0o777 == 0o666 & ~_umask()
    with pytest.raises(InputError, match="city.lmap: map already exists"):
        MapStore.create(path, CRS_WKT)
    with pytest.raises(LidarmapError, match="cannot create a map with an unknown CRS"):
        MapStore.create(tmp_path / "b.lmap", "EPSG:999999")
    with MapStore.open(path) as s:
        other = with_campaigns(map_v1(), 1)
        other.crs_wkt = CRS.from_epsg(25832).to_wkt()
        with pytest.raises(LidarmapError, match="the map is in 'WGS 84 / UTM zone 32N' but the new map's CRS differs"):
            s.commit(other, other.campaigns[-1])


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_campaign_summary_and_attributes_survive_as_json(store: MapStore) -> None:
    m = with_campaigns(map_v1(), 1)
    m.campaigns[0].summary = {"windows": np.int64(3), "files": {"points": "ü.laz"}, "ratio": 0.25}
    store.commit(m, m.campaigns[0])
    assert store.campaigns()[0].summary == {"windows": 3, "files": {"points": "ü.laz"}, "ratio": 0.25}
    assert json.loads(store.conn.execute("SELECT changes FROM campaigns").fetchone()[0])["roofs"]["added"] == 1
