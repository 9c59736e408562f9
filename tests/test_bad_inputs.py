"""The corpus of bad inputs (issue 15): LAS/LAZ files, footprints, trajectories, configs, maps, output folders and
options, each driven through the command line (in process).

Every case must end with exit code 2 (3: a map locked by another writer), exactly one line on stderr that names the
file (or the option) and the problem, no traceback, no output left behind and nothing deleted or changed: the case's
folder (inputs, the user's files, an earlier output) is byte-identical afterwards. ``rc 1 "internal error"`` is for
real bugs only, so it fails every case here. docs/errors.md states how many cases there are.

After the corpus, the behaviours the issue asked for on inputs that are not refused: unusable footprints listed,
colliding and over-long ids kept apart, stale spools removed, hidden folders of the user never deleted.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import shapely
from conftest import run_cli_in_process as run
from pyproj import CRS
from shapely.geometry import box, mapping

from lidarmap.core import PointCloud
from lidarmap.io.las import write_las
from lidarmap.io.outdir import MARKER, read_marker
from lidarmap.io.voxels import read_voxels

UTM = CRS.from_epsg(32632)
X0, Y0 = 500000.0, 5800000.0
# byte offsets in a LAS 1.2-1.4 public header block
SCALE_AT, OFFSET_AT, BOUNDS_AT = 131, 155, 179


@pytest.fixture(scope="module", autouse=True)
def command_built_once():
    """Typer rebuilds the click command tree on every call (0.1 s, a third of a case): build it once here."""
    import typer.main

    original = typer.main.get_command
    built: dict[int, object] = {}

    def get_command(app):
        if id(app) not in built:
            built[id(app)] = original(app)
        return built[id(app)]

    typer.main.get_command = get_command
    yield
    typer.main.get_command = original


# ----------------------------------------------------------------------------------------------------------------------
# Inputs: tiny and built once


def _feature(fid: object, geometry: dict | None, **props: object) -> dict:
    return {"type": "Feature", "properties": {"id": fid, **props}, "geometry": geometry}


def _geojson(path: Path, features: list[dict], crs: str | None = "EPSG:32632") -> Path:
    doc: dict = {"type": "FeatureCollection", "features": features}
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    path.write_text(json.dumps(doc))
    return path


def _box(x0: float, y0: float, x1: float, y1: float) -> dict:
    return mapping(box(X0 + x0, Y0 + y0, X0 + x1, Y0 + y1))


def _aerial(folder: Path) -> tuple[Path, Path]:
    """600 points over 40 m x 20 m: ground and two 12 m box buildings ('a' and 'b')."""
    rng = np.random.default_rng(0)
    n = 600
    xy = rng.uniform([0, 0], [40, 20], size=(n, 2))
    z = np.full(n, 10.0) + rng.normal(0, 0.02, n)
    cls = np.full(n, 2, np.uint8)
    for poly in (box(2, 2, 18, 18), box(22, 2, 38, 18)):
        inside = shapely.contains_xy(poly, xy[:, 0], xy[:, 1])
        z[inside] = 22.0
        cls[inside] = 6
    cloud = PointCloud(np.column_stack([xy + [X0, Y0], z]), {"classification": cls}, UTM)
    write_las(folder / "tile.las", cloud)
    laz = write_las(folder / "tile.laz", cloud)
    fps = _geojson(folder / "fp.geojson", [_feature("a", _box(2, 2, 18, 18)), _feature("b", _box(22, 2, 38, 18))])
    return laz, fps


def _mobile(folder: Path) -> tuple[Path, Path, Path]:
    """3000 points of one 10 m x 10 m x 8 m building's façade and the street, 60 s of driving along it."""
    rng = np.random.default_rng(1)
    n = 3000
    wall = np.arange(n) < n // 2
    x = rng.uniform(0, 10, n)
    y = np.where(wall, 0.0, rng.uniform(-8, 0, n))
    z = np.where(wall, rng.uniform(0, 8, n), 0.0)
    t = np.sort(rng.uniform(0, 60, n)) + 1000
    cloud = PointCloud(np.column_stack([x + X0, y + Y0, z + 10]),
                       {"classification": np.where(wall, 6, 2).astype(np.uint8), "gps_time": t}, UTM)
    laz = write_las(folder / "mls.laz", cloud)
    times = (np.arange(0, 600.5) / 10 + 1000).tolist()
    rows = ["time,x,y,z"] + [f"{s!r},{X0 - 5 + (s - 1000) / 3!r},{Y0 - 5!r},12.0" for s in times]
    trajectory = folder / "traj.csv"
    trajectory.write_text("\n".join(rows) + "\n")
    fps = _geojson(folder / "mfp.geojson", [_feature("h", _box(0, 0, 10, 10))])
    return laz, trajectory, fps


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The good inputs every case starts from, a map after one campaign, a prep output (read-only for the cases)."""
    folder = tmp_path_factory.mktemp("world")
    laz, fps = _aerial(folder)
    mls, trajectory, mfps = _mobile(folder)
    paths = {"dir": folder, "laz": laz, "las": folder / "tile.las", "fp": fps, "mls": mls, "traj": trajectory,
             "mfp": mfps, "map": folder / "city.lmap", "prep": folder / "prep"}
    code, _, err = run("map", "update", paths["map"], "--points", mls, "--trajectory", trajectory,
                       "--footprints", mfps)
    assert code == 0, err
    code, _, err = run("prep", laz, "-f", fps, "-o", paths["prep"], "--min-height", "0")
    assert code == 0, err
    paths["state"] = snapshot(folder)  # type: ignore[assignment]
    return paths


# ----------------------------------------------------------------------------------------------------------------------
# Making bad files


def _patch(src: Path, dst: Path, at: int, fmt: str, *values: float) -> Path:
    data = bytearray(src.read_bytes())
    struct.pack_into(fmt, data, at, *values)
    dst.write_bytes(bytes(data))
    return dst


def _truncated(src: Path, dst: Path, keep: float = 0.5) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[:int(len(data) * keep)])
    return dst


def _no_crs(w: dict[str, Path], t: Path) -> Path:
    from lidarmap.io.las import read_las

    cloud = read_las(w["laz"])
    return write_las(t / "nocrs.laz", PointCloud(cloud.xyz, cloud.attrs, None))


def _other_crs(w: dict[str, Path], t: Path) -> Path:
    from lidarmap.io.las import read_las

    cloud = read_las(w["laz"])
    return write_las(t / "other.laz", PointCloud(cloud.xyz, cloud.attrs, CRS.from_epsg(32631)))


def _empty_las(w: dict[str, Path], t: Path) -> Path:
    return write_las(t / "empty.laz", PointCloud(np.zeros((0, 3)), {"classification": np.zeros(0, np.uint8)}, UTM))


#: Bad point files: name -> (make(world, tmp) -> path, text the error must hold besides the file name).
LAS_FILES: dict[str, tuple[Callable[[dict, Path], Path], str]] = {
    "missing": (lambda w, t: t / "nope.laz", "file not found"),
    "empty file": (lambda w, t: _touch(t / "zero.laz"), "empty file"),
    "folder": (lambda w, t: _mkdir(t / "dir.laz"), "is a "),  # "is a folder" (ours), "is a directory" (click's)
    "text": (lambda w, t: _write(t / "junk.laz", b"not a point cloud at all"), "not a valid LAS/LAZ file"),
    "bad signature": (lambda w, t: _patch(w["las"], t / "sig.las", 0, "4s", b"LASX"), "not a valid LAS/LAZ file"),
    "truncated las": (lambda w, t: _truncated(w["las"], t / "half.las"), ""),
    "truncated laz": (lambda w, t: _truncated(w["laz"], t / "half.laz"), ""),
    "header only": (lambda w, t: _truncated(w["las"], t / "head.las", 0.02), ""),
    "nan scale": (lambda w, t: _patch(w["las"], t / "nan.las", SCALE_AT, "<d", float("nan")), "NaN/inf scale"),
    "zero scale": (lambda w, t: _patch(w["las"], t / "zero.las", SCALE_AT + 8, "<d", 0.0), "zero scale"),
    "absurd scale": (lambda w, t: _patch(w["las"], t / "huge.las", SCALE_AT, "<d", 1e300), "beyond"),
    "absurd offset": (lambda w, t: _patch(w["las"], t / "far.las", OFFSET_AT + 16, "<d", 1e300), "beyond"),
    "inf offset": (lambda w, t: _patch(w["las"], t / "inf.las", OFFSET_AT, "<d", float("inf")), "NaN/inf"),
    "points outside bounds": (lambda w, t: _patch(w["las"], t / "bounds.las", BOUNDS_AT + 32, "<dd", 11.0, 9.0),
                              "outside the header bounds"),
    "no crs": (_no_crs, "no CRS"),
}


def _touch(path: Path) -> Path:
    path.write_bytes(b"")
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


#: Bad footprint files (GeoJSON): name -> (make(tmp) -> path, text of the error).
FOOTPRINTS: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing": (lambda t: t / "nope.geojson", "file not found"),
    "not json": (lambda t: _write(t / "bad.geojson", b"{not json"), "not valid JSON"),
    "not utf-8": (lambda t: _write(t / "latin.geojson", b'{"type": "FeatureCollection", "name": "caf\xe9"}'),
                  "not valid JSON"),
    "a list": (lambda t: _write(t / "list.geojson", b"[1, 2]"), "not a GeoJSON FeatureCollection"),
    "no features": (lambda t: _geojson(t / "none.geojson", []), "no polygon footprints"),
    "only nulls": (lambda t: _geojson(t / "null.geojson", [_feature("n", None)]), "null geometry"),
    "only points": (lambda t: _geojson(t / "pts.geojson", [_feature("p", {"type": "Point",
                                                                           "coordinates": [X0, Y0]})]),
                    "Point geometry"),
    "only zero area": (lambda t: _geojson(t / "flat.geojson", [_feature("z", {
        "type": "Polygon", "coordinates": [[[X0, Y0], [X0 + 1, Y0], [X0 + 2, Y0], [X0, Y0]]]})]), "zero area"),
    "only nan": (lambda t: _geojson(t / "nan.geojson", [_feature("z", {
        "type": "Polygon", "coordinates": [[[X0, Y0], [float("nan"), Y0], [X0 + 2, Y0 + 2], [X0, Y0]]]})]),
                 "NaN or infinite vertex"),
    "malformed coordinates": (lambda t: _geojson(t / "mal.geojson", [_feature("m", {
        "type": "Polygon", "coordinates": [[1, 2]]})]), "feature 0: invalid geometry"),
    "crs without name": (lambda t: _write(t / "crs.geojson", json.dumps(
        {"type": "FeatureCollection", "crs": {"type": "name"}, "features": []}).encode()), "no properties.name"),
    "unknown crs": (lambda t: _geojson(t / "ucrs.geojson", [_feature("a", _box(2, 2, 18, 18))], "urn:nowhere"),
                    "unknown CRS"),
    "far away": (lambda t: _geojson(t / "far.geojson", [_feature("a", mapping(box(0, 0, 10, 10)))]),
                 "footprints do not overlap"),
}

#: Bad trajectories for ``map update``: name -> (make(world, tmp) -> path, text of the error).
TRAJECTORIES: dict[str, tuple[Callable[[dict, Path], Path], str]] = {
    "missing": (lambda w, t: t / "nope.csv", "file not found"),
    "empty": (lambda w, t: _write(t / "empty.csv", b"\n"), "empty trajectory file"),
    "no time column": (lambda w, t: _write(t / "cols.csv", b"t,x,y,z\n0,1,2,3\n1,2,3,4\n"), "lacks column(s) time"),
    "one row": (lambda w, t: _write(t / "one.csv", b"time,x,y,z\n0,1,2,3\n"), "at least two rows"),
    "not numbers": (lambda w, t: _write(t / "text.csv", b"time,x,y,z\n0,1,2,3\nnow,1,2,3\n"),
                    "unreadable trajectory row"),
    "nan": (lambda w, t: _write(t / "nan.csv", b"time,x,y,z\n0,1,2,3\n1,nan,2,3\n"), "NaN or infinite"),
    "times go back": (lambda w, t: _write(t / "back.csv", b"time,x,y,z\n0,1,2,3\n2,1,2,3\n1,1,2,3\n"),
                      "not strictly increasing"),
    "40 s hole": (lambda w, t: _hole(w, t, 40.0), "40.0 s hole in the trajectory"),
    "other times": (lambda w, t: _shifted(w, t), "lie outside the trajectory"),
}


def _trajectory_rows(w: dict[str, Path]) -> list[list[float]]:
    lines = w["traj"].read_text().splitlines()[1:]
    return [[float(v) for v in line.split(",")] for line in lines]


def _hole(w: dict[str, Path], t: Path, seconds: float) -> Path:
    rows = [r for r in _trajectory_rows(w) if not 1020 < r[0] < 1020 + seconds]
    path = t / f"hole{seconds:g}.csv"
    path.write_text("time,x,y,z\n" + "\n".join(",".join(map(repr, r)) for r in rows) + "\n")
    return path


def _shifted(w: dict[str, Path], t: Path) -> Path:
    path = t / "late.csv"
    path.write_text("time,x,y,z\n" + "\n".join(",".join(map(repr, [r[0] + 1e5, *r[1:]]))
                                               for r in _trajectory_rows(w)) + "\n")
    return path


#: Bad config files: name -> (TOML bytes or None for a folder / a missing file, text of the error).
CONFIGS: dict[str, tuple[bytes | None, str]] = {
    "unknown table": (b"[prepp]\nbuffer = 1\n", "unknown config table(s) prepp"),
    "unknown facade table": (b"[facadee]\nx = 1\n", "unknown config table(s) facadee"),
    "not utf-8": (b"[prep]\n# caf\xe9\nbuffer = 1\n", "not UTF-8"),
    "invalid toml": (b"[prep\nbuffer = 1\n", "invalid TOML"),
    "missing": (None, "config file not found"),
}

CONFIG_COMMANDS = {
    "prep": lambda w, t: ["prep", w["laz"], "-f", w["fp"], "-o", t / "out"],
    "run": lambda w, t: ["run", w["laz"], "-f", w["fp"], "-o", t / "out"],
    "map update": lambda w, t: ["map", "update", t / "new.lmap", "--points", w["mls"], "--trajectory", w["traj"],
                                "--footprints", w["mfp"]],
    "voxelize": lambda w, t: ["voxelize", w["laz"], "-o", t / "out"],
}


# ----------------------------------------------------------------------------------------------------------------------
# The corpus: case id -> make(world, tmp) -> (argv, needles that the one line must hold)

Case = Callable[[dict, Path], tuple[list, list[str]]]
CASES: dict[str, Case] = {}


def _las_case(command: str, defect: str) -> Case:
    make, text = LAS_FILES[defect]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        bad = make(w, t)
        argv = {"prep": ["prep", bad, "-f", w["fp"], "-o", t / "out"],
                "run": ["run", bad, "-f", w["fp"], "-o", t / "out"],
                "voxelize": ["voxelize", bad, "-o", t / "out"],
                "map update": ["map", "update", t / "new.lmap", "--points", bad, "--trajectory", w["traj"],
                               "--footprints", w["mfp"]]}[command]
        return argv, [bad.name, text]
    return case


for _command in ("prep", "run", "voxelize", "map update"):
    for _defect in LAS_FILES:
        if not (_command == "voxelize" and _defect == "no crs"):  # voxels need no CRS
            CASES[f"las/{_command}/{_defect}"] = _las_case(_command, _defect)


def _footprint_case(command: str, defect: str) -> Case:
    make, text = FOOTPRINTS[defect]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        bad = make(t)
        argv = {"prep": ["prep", w["laz"], "-f", bad, "-o", t / "out"],
                "run": ["run", w["laz"], "-f", bad, "-o", t / "out"],
                "map update": ["map", "update", t / "new.lmap", "--points", w["mls"], "--trajectory", w["traj"],
                               "--footprints", bad]}[command]
        return argv, [bad.name, text]
    return case


for _command in ("prep", "run", "map update"):
    for _defect in FOOTPRINTS:
        CASES[f"footprints/{_command}/{_defect}"] = _footprint_case(_command, _defect)


def _trajectory_case(defect: str) -> Case:
    make, text = TRAJECTORIES[defect]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        bad = make(w, t)
        return ["map", "update", t / "new.lmap", "--points", w["mls"], "--trajectory", bad, "--footprints",
                w["mfp"]], [bad.name, text]
    return case


for _defect in TRAJECTORIES:
    CASES[f"trajectory/{_defect}"] = _trajectory_case(_defect)


def _config_case(command: str, defect: str) -> Case:
    data, text = CONFIGS[defect]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        path = t / "config.toml"
        if data is not None:
            path.write_bytes(data)
        return [*CONFIG_COMMANDS[command](w, t), "--config", path], ["config.toml", text]
    return case


for _command in CONFIG_COMMANDS:
    for _defect in CONFIGS:
        CASES[f"config/{_command}/{_defect}"] = _config_case(_command, _defect)


def _config_value_case(command: str, toml: str, *needles: str) -> Case:
    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        (t / "config.toml").write_text(toml)
        return [*CONFIG_COMMANDS[command](w, t), "--config", t / "config.toml"], ["config.toml", *needles]
    return case


CASES["config/prep/unknown key"] = _config_value_case("prep", "[prep]\nbufer = 3\n", "unknown option 'bufer'")
CASES["config/prep/wrong type"] = _config_value_case("prep", "[prep]\nbuffer = 'wide'\n", "expected float")
CASES["config/prep/negative buffer"] = _config_value_case("prep", "[prep]\nbuffer = -1\n", "buffer")
CASES["config/run/bad stage"] = _config_value_case("run", "[run]\nstages = ['melt']\n", "stages")
CASES["config/map update/bad workers"] = _config_value_case("map update", "[update]\nworkers = -2\n", "workers")
CASES["config/map update/bad gap"] = _config_value_case("map update", "[update]\ntrajectory_max_gap = 0\n",
                                                        "trajectory_max_gap")


# maps ---------------------------------------------------------------------------------------------------------------


def _damaged_map(w: dict, t: Path) -> Path:
    """A copy of the map whose facade_versions table's first page is overwritten: the schema still opens."""
    path = t / "damaged.lmap"
    shutil.copyfile(w["map"], path)
    with sqlite3.connect(path) as conn:
        page = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'facade_versions'").fetchone()[0]
        size = conn.execute("PRAGMA page_size").fetchone()[0]
    conn.close()
    data = bytearray(path.read_bytes())
    data[(page - 1) * size:page * size] = b"\xab" * size
    path.write_bytes(bytes(data))
    return path


def _sqlite_not_map(w: dict, t: Path) -> Path:
    path = t / "other.sqlite"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE t (x)")
    conn.close()
    return path


def _newer_map(w: dict, t: Path) -> Path:
    path = t / "newer.lmap"
    shutil.copyfile(w["map"], path)
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE schema_version SET version = version + 100")
    conn.close()
    return path


MAPS: dict[str, tuple[Callable[[dict, Path], Path], str]] = {
    "missing": (lambda w, t: t / "nope.lmap", "map not found"),
    "not a map": (lambda w, t: _write(t / "fp.lmap", w["fp"].read_bytes()), "not a lidarmap map"),
    "empty file": (lambda w, t: _touch(t / "zero.lmap"), "not a lidarmap map"),
    "a folder": (lambda w, t: _mkdir(t / "dir.lmap"), "is a directory"),
    "other sqlite": (_sqlite_not_map, "without lidarmap tables"),
    "newer schema": (_newer_map, "is newer than this lidarmap supports"),
    "damaged page": (_damaged_map, "damaged map"),
}
MAP_COMMANDS = {"show": lambda t: [], "history": lambda t: [], "export": lambda t: ["-o", t / "out.city.json"],
                "render": lambda t: ["-o", t / "renders"]}


def _map_case(command: str, defect: str) -> Case:
    make, text = MAPS[defect]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        path = make(w, t)
        return ["map", command, path, *MAP_COMMANDS[command](t)], [path.name, text]
    return case


for _command in MAP_COMMANDS:
    for _defect in MAPS:
        if _command == "history" and _defect == "damaged page":
            continue  # history reads only the campaigns table, which the damage leaves whole
        CASES[f"map/{_command}/{_defect}"] = _map_case(_command, _defect)


def _update_existing(make: Callable[[dict, Path], Path], text: str) -> Case:
    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        path = make(w, t)
        trajectory = t / "traj2.csv"  # another campaign than the map's (its files' bytes differ)
        trajectory.write_text(w["traj"].read_text() + "\n")
        return ["map", "update", path, "--points", w["mls"], "--trajectory", trajectory, "--footprints", w["mfp"]], \
            [path.name, text]
    return case


CASES["map/update/not a map"] = _update_existing(*MAPS["not a map"])
CASES["map/update/damaged page"] = _update_existing(*MAPS["damaged page"])
CASES["map/update/newer schema"] = _update_existing(*MAPS["newer schema"])
CASES["map/update/campaign applied again"] = lambda w, t: (
    ["map", "update", shutil.copyfile(w["map"], t / "again.lmap"), "--points", w["mls"], "--trajectory", w["traj"],
     "--footprints", w["mfp"]], ["again.lmap", "campaign already applied"])


# output folders -----------------------------------------------------------------------------------------------------


def _users_folder(t: Path, *files: str) -> Path:
    """A folder of the user's: a thesis, a subfolder, and the given (lidarmap-looking) files."""
    folder = t / "proj"
    (folder / "docs").mkdir(parents=True)
    (folder / "docs" / "thesis.tex").write_text("years of work\n")
    for name in files:
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text("{}\n")
    return folder


def _marked(t: Path, kind: str, name: str = "marked") -> Path:
    folder = t / name
    folder.mkdir()
    (folder / MARKER).write_text(json.dumps({"kind": kind, "lidarmap": "0", "written": ["x"]}))
    return folder


FOLDERS: dict[str, Case] = {
    "prep into a folder with a prep.json": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", _users_folder(t, "prep.json")], ["proj", "not written by lidarmap"]),
    "prep into a folder with buildings/": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", _users_folder(t, "buildings/a.laz", "buildings.csv")],
        ["proj", "not written by lidarmap"]),
    "run into a folder with summary.json": lambda w, t: (
        ["run", w["laz"], "-f", w["fp"], "-o", _users_folder(t, "summary.json", "buildings/a/building.json")],
        ["proj", "not written by lidarmap"]),
    "run into a prep output": lambda w, t: (
        ["run", w["laz"], "-f", w["fp"], "-o", _marked(t, "prep")], ["marked", "holds a lidarmap prep output"]),
    "prep into a run output": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", _marked(t, "run")], ["marked", "holds a lidarmap run output"]),
    "voxelize into a prep output": lambda w, t: (
        ["voxelize", w["laz"], "-o", _marked(t, "prep")], ["marked", "holds a lidarmap prep output"]),
    "demo into the user's folder": lambda w, t: (
        ["demo", "-o", _users_folder(t, "lidarmap-demo.txt")], ["proj", "not written by lidarmap"]),
    "demo into a run output": lambda w, t: (["demo", "-o", _marked(t, "run")], ["marked", "run output"]),
    "prep output is a file": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", _write(t / "out", b"x")], ["out", "is a file"]),
    "run output is a file": lambda w, t: (
        ["run", w["laz"], "-f", w["fp"], "-o", _write(t / "out", b"x")], ["out", "is a file"]),
    "prep missing parent": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", t / "no" / "out"], [f"{t / 'no'}", "parent folder"]),
    "run missing parent": lambda w, t: (
        ["run", w["laz"], "-f", w["fp"], "-o", t / "no" / "out"], [f"{t / 'no'}", "parent folder"]),
    "voxelize missing parent": lambda w, t: (
        ["voxelize", w["laz"], "-o", t / "no" / "out"], [f"{t / 'no'}", "parent folder"]),
    "prep into a read-only folder": lambda w, t: (
        ["prep", w["laz"], "-f", w["fp"], "-o", "/sys/kernel/lidarmap-out"], ["/sys/kernel", "cannot write"]),
    "voxelize into a read-only folder": lambda w, t: (
        ["voxelize", w["laz"], "-o", "/sys/kernel/lidarmap-out"], ["/sys/kernel", "cannot write"]),
    "run into a read-only folder": lambda w, t: (
        ["run", w["laz"], "-f", w["fp"], "-o", "/sys/kernel/lidarmap-out"], ["/sys/kernel/lidarmap-out"]),
    "map update in a read-only folder": lambda w, t: (
        ["map", "update", "/sys/kernel/city.lmap", "--points", w["mls"], "--trajectory", w["traj"],
         "--footprints", w["mfp"]], ["/sys/kernel"]),
}


def _users_file_in_marked(kind: str, name: str) -> Callable[[Path], Path]:
    """A ``kind`` output folder where the user put a file of the name the next ``kind`` would write."""
    def make(t: Path) -> Path:
        out = _marked(t, kind, "ours")
        (out / name).write_bytes(b"the user's own file")
        return out
    return make


#: The other commands that write a folder: name -> argv before the folder, argv after it, the name of its first output.
FOLDER_COMMANDS: dict[str, tuple[Callable[[dict], list], list, str]] = {
    "map render": (lambda w: ["map", "render", w["map"], "-o"], ["--width", "300"], "h_facade00.png"),
    "segment predict": (lambda w: ["segment", "predict", w["laz"], "-o"], ["--method", "baseline"], "tile.laz"),
    "simulate": (lambda w: ["simulate"], ["--buildings", "1", "--campaigns", "0"], "als.laz"),
}
KINDS = {"map render": "render", "segment predict": "segment-predict", "simulate": "simulate"}


def _folder_case(command: str, make: Callable[[Path], Path], needles: Callable[[Path], list[str]]) -> Case:
    before, after, _ = FOLDER_COMMANDS[command]

    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        return [*before(w), make(t), *after], needles(t)
    return case


for _command, (_, _, _first) in FOLDER_COMMANDS.items():
    FOLDERS[f"{_command} into the user's folder"] = _folder_case(
        _command, lambda t, f=_first: _users_folder(t, f), lambda t: ["proj", "not written by lidarmap"])
    FOLDERS[f"{_command} into a run output"] = _folder_case(
        _command, lambda t: _marked(t, "run"), lambda t: ["marked", "holds a lidarmap run output"])
    FOLDERS[f"{_command} over a file of the user's"] = _folder_case(
        _command, _users_file_in_marked(KINDS[_command], _first), lambda t, f=_first: ["ours", f,
                                                                                     "not written by lidarmap"])
    FOLDERS[f"{_command} output is a file"] = _folder_case(
        _command, lambda t: _write(t / "out", b"x"), lambda t: ["out", "is a file"])
    FOLDERS[f"{_command} missing parent"] = _folder_case(
        _command, lambda t: t / "no" / "out", lambda t: [f"{t / 'no'}", "parent folder"])
    FOLDERS[f"{_command} into a read-only folder"] = _folder_case(
        _command, lambda t: Path("/sys/kernel/lidarmap-out"), lambda t: ["/sys/kernel", "cannot write"])
for _name, _case in FOLDERS.items():
    CASES[f"folder/{_name}"] = _case


def _same_stem(command: str) -> Case:
    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        for sub in ("A", "B"):
            (t / sub).mkdir()
            shutil.copyfile(w["laz"], t / sub / "points.laz")
        return [command, t / "A" / "points.laz", t / "B" / "points.laz", "-o", t / "out"], \
            ["A/points.laz", "B/points.laz", "same name"]
    return case


for _command in ("densify", "flatten", "voxelize", "mesh"):
    CASES[f"folder/{_command} of two points.laz"] = _same_stem(_command)


def _users_file_in_output(w: dict, t: Path) -> tuple[list, list[str]]:
    """A voxelize output folder where the user put a file of the name the next voxelize would write."""
    out = _marked(t, "voxelize", "vox")
    (out / "tile.voxels.npz").write_bytes(b"the user's own file")
    return ["voxelize", w["laz"], "-o", out], ["vox", "tile.voxels.npz", "not written by lidarmap"]


CASES["folder/voxelize over a file of the user's"] = _users_file_in_output


# options ------------------------------------------------------------------------------------------------------------


def _options(*argv: object, needles: tuple[str, ...]) -> Case:
    def case(w: dict, t: Path) -> tuple[list, list[str]]:
        names = {"LAZ": w["laz"], "FP": w["fp"], "OUT": t / "out", "MLS": w["mls"], "TRAJ": w["traj"],
                 "MFP": w["mfp"], "MAP": t / "new.lmap"}
        return [names.get(a, a) if isinstance(a, str) else a for a in argv], list(needles)
    return case


RUN = ("run", "LAZ", "-f", "FP", "-o", "OUT")
PREP = ("prep", "LAZ", "-f", "FP", "-o", "OUT")
UPDATE = ("map", "update", "MAP", "--points", "MLS", "--trajectory", "TRAJ", "--footprints", "MFP")
OPTIONS: dict[str, Case] = {
    "run --seed -1": _options(*RUN, "--seed", "-1", needles=("--seed",)),
    "densify --seed -1": _options("densify", "LAZ", "-o", "OUT", "--seed", "-1", needles=("--seed",)),
    "flatten --seed -1": _options("flatten", "LAZ", "-o", "OUT", "--seed", "-1", needles=("--seed",)),
    "map update --seed -1": _options(*UPDATE, "--seed", "-1", needles=("--seed",)),
    "demo --seed -1": _options("demo", "-o", "OUT", "--seed", "-1", needles=("--seed",)),
    "run --stages melt": _options(*RUN, "--stages", "melt", needles=("unknown stage(s) melt",)),
    "run --method magic": _options(*RUN, "--method", "magic", needles=("method must be one of",)),
    "run --mesh lego": _options(*RUN, "--mesh", "lego", needles=("mesh must be one of",)),
    "run --scheduler nowhere": _options(*RUN, "--scheduler", "nowhere", needles=("tcp://",)),
    "run --voxel-size 0": _options(*RUN, "--voxel-size", "0", needles=("size",)),
    "run --model missing": _options(*RUN, "--method", "baseline", "--model", "OUT", needles=("out",)),
    "run --crs bogus": _options(*RUN, "--crs", "EPSG:999999", needles=("EPSG:999999",)),
    "prep --buffer nan": _options(*PREP, "--buffer", "nan", needles=("buffer must be a finite number",)),
    "prep --crs conflicting": _options(*PREP, "--crs", "EPSG:28992", needles=("tile.laz", "--crs")),
    "prep --seed": _options(*PREP, "--seed", "1", needles=("No such option: --seed",)),
    "mesh --method lego": _options("mesh", "LAZ", "-o", "OUT", "--method", "lego", needles=("unknown --method",)),
    "flatten --method lego": _options("flatten", "LAZ", "-o", "OUT", "--method", "lego", needles=("method",)),
    "densify --ratio 0": _options("densify", "LAZ", "-o", "OUT", "--ratio", "0", needles=("ratio",)),
    "voxelize --size -1": _options("voxelize", "LAZ", "-o", "OUT", "--size", "-1", needles=("size",)),
    "voxelize same input twice": _options("voxelize", "LAZ", "LAZ", "-o", "OUT", needles=("tile.laz", "twice")),
    "map update --aerial and --points": _options(*UPDATE, "--aerial", "LAZ", needles=("--aerial",)),
}
for _name, _case in OPTIONS.items():
    CASES[f"option/{_name}"] = _case


# ----------------------------------------------------------------------------------------------------------------------
# Running the corpus


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (bytes) and folder (None) under ``folder``."""
    state: dict[str, bytes | None] = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs:
            state[os.path.relpath(os.path.join(root, name), folder)] = None
        for name in files:
            path = os.path.join(root, name)
            state[os.path.relpath(path, folder)] = Path(path).read_bytes()
    return state


def test_the_corpus_has_more_than_100_cases() -> None:
    assert len(CASES) > 100


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input(world: dict[str, Path], tmp_path: Path, name: str) -> None:
    argv, needles = CASES[name](world, tmp_path)
    before = snapshot(tmp_path)
    code, _, err = run(*argv)
    lines = err.strip().splitlines()
    assert code == 2, f"exit {code}: {err}"
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    after = snapshot(tmp_path)
    # nothing deleted or changed; nothing new but the advisory lock file kept beside an existing map
    maps = {f"{k}.lock" for k, v in before.items() if v and v.startswith(b"SQLite format 3\0")}
    assert {k: v for k, v in after.items() if k not in maps} == before


def test_the_shared_inputs_are_untouched(world: dict[str, Path]) -> None:
    """After the corpus (this file's order): no case changed the good inputs, the map or the prep output."""
    assert snapshot(world["dir"]) == world["state"]
    assert read_marker(world["prep"])["kind"] == "prep" and "prep.json" in read_marker(world["prep"])["written"]


# ----------------------------------------------------------------------------------------------------------------------
# Inputs that are not refused: what they must do instead


def test_prep_replaces_only_what_it_wrote(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert run("prep", world["laz"], "-f", world["fp"], "-o", out, "--min-height", "0")[0] == 0
    (out / "docs").mkdir()
    (out / "docs" / "thesis.tex").write_text("years of work\n")
    (out / "notes.txt").write_text("mine\n")
    victim = tmp_path / "victim.txt"
    victim.write_text("outside\n")
    marker = json.loads((out / MARKER).read_text())
    (out / MARKER).write_text(json.dumps({**marker, "written": [*marker["written"], "../victim.txt", "/etc"]}))
    only_a = _geojson(tmp_path / "a.geojson", [_feature("a", _box(2, 2, 18, 18))])
    code, _, err = run("prep", world["laz"], "-f", only_a, "-o", out, "--min-height", "0")
    assert code == 0, err
    assert sorted(p.name for p in (out / "buildings").iterdir()) == ["a.laz"]  # the earlier b.laz went
    assert (out / "docs" / "thesis.tex").read_text() == "years of work\n" and (out / "notes.txt").exists()
    assert victim.exists()  # a marker never points outside its folder
    assert read_marker(out)["written"] == ["buildings", "buildings.csv", "frame.json", "prep.json"]


def test_prep_lists_unusable_footprints_and_repairs_self_intersecting_ones(world: dict[str, Path],
                                                                          tmp_path: Path) -> None:
    bow_tie = {"type": "Polygon", "coordinates": [[[X0 + 2, Y0 + 2], [X0 + 18, Y0 + 18], [X0 + 18, Y0 + 2],
                                                   [X0 + 2, Y0 + 18], [X0 + 2, Y0 + 2]]]}
    fps = _geojson(tmp_path / "mixed.geojson", [
        _feature("bow", bow_tie), _feature("b", _box(22, 2, 38, 18)), _feature("null", None),
        _feature("point", {"type": "Point", "coordinates": [X0, Y0]}),
        _feature("empty", {"type": "Polygon", "coordinates": []}),
        _feature("flat", {"type": "Polygon", "coordinates": [[[X0, Y0], [X0 + 1, Y0], [X0 + 2, Y0], [X0, Y0]]]}),
        _feature("nan", {"type": "Polygon", "coordinates": [[[X0, Y0], [float("nan"), Y0], [X0, Y0 + 1],
                                                             [X0, Y0]]]})])
    code, _, err = run("prep", world["laz"], "-f", fps, "-o", tmp_path / "out", "--min-height", "0")
    assert code == 0 and err == "", err
    summary = json.loads((tmp_path / "out" / "prep.json").read_text())
    assert summary["dropped"] == {"null": "null geometry", "point": "Point geometry, not a polygon",
                                  "empty": "empty geometry", "flat": "zero area", "nan": "NaN or infinite vertex"}
    assert summary["repaired"] == ["bow"]
    index = (tmp_path / "out" / "buildings.csv").read_text().splitlines()
    assert [row.split(",")[0] for row in index[1:]] == ["bow", "b"]


#: Ids that collide once made file-safe, and two long ones that share their first 299 characters.
HOSTILE_IDS = ["a/b", "a\nb", "a_b", "A_B", "..", "", ".", "x" * 299 + "1", "x" * 299 + "2"]


def _many_buildings(folder: Path) -> tuple[Path, Path]:
    """Nine 6 m x 6 m box buildings (one per hostile id) on a 3 x 3 grid, 150 points each, on ground."""
    rng = np.random.default_rng(2)
    xyz, cls, features = [], [], []
    for k, fid in enumerate(HOSTILE_IDS):
        x0, y0 = 10.0 * (k % 3), 10.0 * (k // 3)
        roof = rng.uniform([x0 + 0.2, y0 + 0.2], [x0 + 5.8, y0 + 5.8], size=(150, 2))
        ground = rng.uniform([x0 - 2, y0 - 2], [x0 + 8, y0 + 8], size=(60, 2))
        ground = ground[~shapely.contains_xy(box(x0, y0, x0 + 6, y0 + 6), ground[:, 0], ground[:, 1])]
        xyz += [np.column_stack([roof, np.full(len(roof), 20.0)]), np.column_stack([ground, np.full(len(ground),
                                                                                                    10.0)])]
        cls += [np.full(len(roof), 6, np.uint8), np.full(len(ground), 2, np.uint8)]
        features.append(_feature(fid, _box(x0, y0, x0 + 6, y0 + 6)))
    features.append(_feature("nothing", None))
    cloud = PointCloud(np.concatenate(xyz) + [X0, Y0, 0], {"classification": np.concatenate(cls)}, UTM)
    return write_las(folder / "many.laz", cloud), _geojson(folder / "many.geojson", features)


def test_run_keeps_colliding_and_long_ids_apart_and_resumes_them(tmp_path: Path) -> None:
    laz, fps = _many_buildings(tmp_path)
    out = tmp_path / "run"
    args = ["run", laz, "-f", fps, "-o", out, "--method", "baseline", "--stages", "none", "--mesh", "voxels"]
    code, _, err = run(*args)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    folders = summary["folders"]
    assert sorted(folders) == sorted(HOSTILE_IDS) and len(set(folders.values())) == len(HOSTILE_IDS)
    assert sorted(summary["processed"]) == sorted(HOSTILE_IDS)
    assert summary["dropped_footprints"]["nothing"] == "null geometry"
    for fid, folder in folders.items():
        record = json.loads((out / folder / "building.json").read_text())
        assert record["id"] == fid and record["folder"] == folder
        assert len(Path(folder).name) <= 100
    assert folders["a/b"] == "buildings/a_b" and folders["a\nb"] == "buildings/a_b_2"
    assert folders[".."] == "buildings/building" and folders[""] == "buildings/building_2"
    assert folders["x" * 299 + "1"] != folders["x" * 299 + "2"]
    code, _, err = run(*args)  # resumed: every building found finished, none recomputed
    assert code == 0, err
    again = json.loads((out / "summary.json").read_text())
    assert again["processed"] == [] and sorted(again["skipped_finished"]) == sorted(HOSTILE_IDS)


def test_stage_command_rerun_replaces_its_outputs_and_keeps_the_users(world: dict[str, Path],
                                                                      tmp_path: Path) -> None:
    out = tmp_path / "vox"
    assert run("voxelize", world["laz"], "-o", out)[0] == 0
    (out / "mine.txt").write_text("mine\n")
    code, _, err = run("voxelize", world["laz"], "-o", out, "--size", "2")
    assert code == 0, err
    assert (out / "mine.txt").read_text() == "mine\n"
    assert read_voxels(out / "tile.voxels.npz").size == 2.0
    assert read_marker(out) == {"kind": "voxelize", "lidarmap": read_marker(out)["lidarmap"],
                                "written": ["tile.vox", "tile.voxels.npz"]}


def test_update_removes_stale_spools_and_warns_of_trajectory_holes(world: dict[str, Path], tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "city.lmap"
    shutil.copyfile(world["map"], path)
    stale = tmp_path / ".city.lmap.spool-k1ll3d"
    (stale / "points").mkdir(parents=True)
    (stale / "points" / "0.npy").write_bytes(b"\0" * 4100)
    other = tmp_path / ".other.lmap.spool-abc"  # another map's: not ours to remove
    other.mkdir()
    hole = _hole(world, tmp_path, 3.0)
    with caplog.at_level("WARNING", logger="lidarmap.io.trajectory"):
        code, _, err = run("map", "update", path, "--points", world["mls"], "--trajectory", hole, "--footprints",
                           world["mfp"])
    assert code == 0, err
    assert not stale.exists() and other.exists()
    warnings = [r.getMessage() for r in caplog.records if r.name == "lidarmap.io.trajectory"]
    assert len(warnings) == 1 and "hole3.csv" in warnings[0] and "3.0 s hole" in warnings[0], warnings
    assert "\n" not in warnings[0]


def test_a_later_demo_clears_only_what_the_earlier_one_wrote(tmp_path: Path) -> None:
    """The demo's folder handling (lidarmap.cli.demo._prepare), without the minutes of a whole demo."""
    from lidarmap.cli.demo import DEMO_OUTPUTS, _prepare

    out = tmp_path / "demo"
    _prepare(out)
    assert read_marker(out)["kind"] == "demo" and set(read_marker(out)["written"]) == set(DEMO_OUTPUTS)
    (out / "city").mkdir()
    (out / "city" / "als.laz").write_bytes(b"old")
    (out / "renders").mkdir()
    (out / "notes.txt").write_text("mine\n")
    (out / "mine").mkdir()
    _prepare(out)
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "mine", "notes.txt"]


def test_rerender_replaces_only_its_own_pngs(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "renders"
    assert run("map", "render", world["map"], "-o", out, "--width", "300")[0] == 0
    pngs = read_marker(out)["written"]
    assert pngs == ["h_facade00.png"]
    first = (out / pngs[0]).read_bytes()
    (out / "mine.txt").write_text("mine\n")
    (out / "z_facade00.png").write_bytes(b"the user's picture")
    marker = json.loads((out / MARKER).read_text())  # as if an earlier render had a façade this one has not
    (out / "gone_facade03.png").write_bytes(b"old render")
    (out / MARKER).write_text(json.dumps({**marker, "written": [*marker["written"], "gone_facade03.png"]}))
    code, _, err = run("map", "render", world["map"], "-o", out, "--width", "400")
    assert code == 0, err
    assert (out / "mine.txt").read_text() == "mine\n" and (out / "z_facade00.png").read_bytes() == b"the user's picture"
    assert not (out / "gone_facade03.png").exists()  # the earlier render's, and not part of this one
    assert (out / pngs[0]).read_bytes() != first  # replaced (another width)
    assert read_marker(out)["written"] == pngs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["renders"]  # no temporary folder left beside it


def test_a_render_failing_partway_leaves_nothing(world: dict[str, Path], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A disk that fills up after the first PNG: no PNG left behind, an earlier render untouched."""
    import errno

    from lidarmap.export import render

    earlier = tmp_path / "earlier"
    assert run("map", "render", world["map"], "-o", earlier, "--width", "300")[0] == 0
    (earlier / "mine.txt").write_text("mine\n")
    original = render.render_facade

    def full_disk(facade, path, *args, **kwargs):
        original(facade, path, *args, **kwargs)  # the PNG is written, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(render, "render_facade", full_disk)
    before = snapshot(tmp_path)
    for out in (tmp_path / "new", earlier):
        code, _, err = run("map", "render", world["map"], "-o", out, "--width", "400")
        assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, err
        assert snapshot(tmp_path) == before  # no new folder, no temporary one, no PNG changed


def test_predict_again_replaces_only_its_own_files(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "seg"
    args = ["--method", "baseline"]
    assert run("segment", "predict", world["laz"], "-o", out, *args)[0] == 0
    first = (out / "tile.laz").read_bytes()
    (out / "mine.txt").write_text("mine\n")
    other = shutil.copyfile(world["laz"], tmp_path / "other.laz")
    code, _, err = run("segment", "predict", world["laz"], other, "-o", out, *args)
    assert code == 0, err
    assert (out / "tile.laz").read_bytes() == first  # replaced by the same result (deterministic)
    assert (out / "mine.txt").read_text() == "mine\n"
    assert read_marker(out)["kind"] == "segment-predict"
    assert read_marker(out)["written"] == ["other.laz", "tile.laz"]
    code, _, err = run("segment", "predict", world["prep"], "-o", out, *args)  # a prep folder: OUT/prep/
    assert code == 0, err
    assert read_marker(out)["written"] == ["other.laz", "prep", "tile.laz"]  # earlier outputs stay (like stages)
    assert sorted(p.name for p in (out / "prep" / "buildings").iterdir()) == ["a.laz", "b.laz"]


def test_simulate_again_replaces_the_earlier_simulation_and_keeps_the_users(tmp_path: Path) -> None:
    out = tmp_path / "city"
    code, _, err = run("simulate", out, "--seed", "5", "--buildings", "1", "--campaigns", "1")
    assert code == 0, err
    assert (out / "mls_1.laz").exists() and "mls_1.laz" in read_marker(out)["written"]
    (out / "notes.txt").write_text("mine\n")
    code, _, err = run("simulate", out, "--seed", "5", "--buildings", "1", "--campaigns", "0")
    assert code == 0, err
    assert not (out / "mls_1.laz").exists() and not (out / "trajectory_1.csv").exists()  # the earlier campaign's
    assert (out / "notes.txt").read_text() == "mine\n"
    assert read_marker(out)["written"] == ["als.laz", "footprints.geojson", "truth"]
