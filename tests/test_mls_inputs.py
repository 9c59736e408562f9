"""Mobile-mapping data as published (issue 16): PLY / text readers, bad inputs, and ``map update`` through the CLI
from a PLY campaign with per-point origins, with an estimated sensor path, and without footprints, scored against
the simulator's truth (a dev seed, never an evaluation seed)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import one_line_error
from conftest import run_cli_in_process as run
from shapely.geometry import Polygon

from lidarmap.core import Trajectory
from lidarmap.facade.sensors import (
    PulseClock,
    SensorParams,
    estimate_path,
    ground_points,
    origin_knots,
    path_times,
    path_trajectory,
    profile_slopes,
    with_height,
)
from lidarmap.io.ply import iter_ply
from lidarmap.io.points import read_points
from lidarmap.io.xyz import iter_text
from lidarmap.sim.plyout import write_points_ply

SEED = 6  # dev seed



def _columns(n: int = 50) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {"x": 500000.0 + rng.random(n) * 100 + 1e-7 * np.arange(n), "y": 5800000.0 + rng.random(n) * 100,
            "z": rng.random(n) * 30, "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "classification": rng.integers(0, 10, n).astype(np.uint8), "gps_time": 40000 + np.arange(n) * 1e-4,
            "x_origin": 500000.0 + np.arange(n) * 0.01, "y_origin": np.full(n, 5800050.0),
            "z_origin": np.full(n, 2.5)}


def _check(cloud, cols: dict[str, np.ndarray]) -> None:
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([cols["x"], cols["y"], cols["z"]]))
    for name in ("intensity", "classification", "gps_time", "x_origin"):
        np.testing.assert_array_equal(cloud.attrs[name], cols[name])
    assert cloud.attrs["intensity"].dtype == np.uint16 and cloud.attrs["x_origin"].dtype == np.float64


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_in_chunks(tmp_path, binary) -> None:
    cols = _columns()
    path = write_points_ply(tmp_path / "c.ply", cols, ["crs EPSG:32632"], binary=binary)
    chunks = list(iter_ply(path, chunk_size=7))
    assert [len(c) for c in chunks] == [7] * 7 + [1]
    cloud = read_points(path)
    _check(cloud, cols)
    assert cloud.crs.to_epsg() == 32632


def test_big_endian_ply_and_other_elements_after_the_vertices(tmp_path) -> None:
    cols = _columns(20)
    dtype = np.dtype([(k, ">" + np.asarray(v).dtype.str[1:]) for k, v in cols.items()])
    rec = np.empty(20, dtype)
    for k, v in cols.items():
        rec[k] = v
    types = {"f8": "double", "u2": "ushort", "u1": "uchar"}
    header = ["ply", "format binary_big_endian 1.0", "element vertex 20",
              *[f"property {types[dtype[k].str[1:]]} {k}" for k in cols], "element face 1",
              "property list uchar int vertex_indices", "end_header"]
    path = tmp_path / "be.ply"
    path.write_bytes(("\n".join(header) + "\n").encode() + rec.tobytes() + b"\x03" + np.arange(3, dtype=">i4").tobytes())
    _check(read_points(path), cols)


def test_text_columns_from_spec_header_and_count(tmp_path) -> None:
    cols = _columns(30)
    csv = tmp_path / "a.csv"
    table = np.column_stack([cols["x"], cols["y"], cols["z"], cols["gps_time"], cols["intensity"]])
    np.savetxt(csv, table, fmt="%.17g", delimiter=",", header="X,Y,Z,GPSTime,scalar_Intensity", comments="")
    cloud = read_points(csv)
    np.testing.assert_array_equal(cloud.xyz[:, 0], cols["x"])
    np.testing.assert_array_equal(cloud.attrs["gps_time"], cols["gps_time"])
    assert cloud.attrs["intensity"].dtype == np.uint16
    txt = tmp_path / "b.txt"
    np.savetxt(txt, table, fmt="%.17g", header="scanner export", comments="# ")
    chunks = list(iter_text(txt, chunk_size=8, columns="x,y,z,_,reflectance"))
    assert [len(c) for c in chunks] == [8, 8, 8, 6]
    assert set(chunks[0].attrs) == {"intensity"}
    sem3d = tmp_path / "s.txt"  # Semantic3D: x y z intensity r g b, signed intensity
    np.savetxt(sem3d, np.column_stack([table[:, :3], np.full(30, -1200), np.full((30, 3), 200)]), fmt="%.6f")
    cloud = read_points(sem3d)
    assert cloud.attrs["intensity_raw"][0] == -1200 and cloud.attrs["red"][0] == 200


def _ascii_ply(tmp_path: Path, name: str, rows: list[str], count: int | None = None,
               props: str = "property double x\nproperty double y\nproperty double z\nproperty uchar class") -> Path:
    path = tmp_path / name
    n = len(rows) if count is None else count
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex {n}\n{props}\nend_header\n" + "\n".join(rows) + "\n")
    return path


def _binary(tmp_path: Path, name: str, cols: dict, count_delta: int = 0) -> Path:
    path = write_points_ply(tmp_path / name, cols, [], binary=True)
    data = path.read_bytes()
    n = len(cols["x"])
    path.write_bytes(data.replace(f"element vertex {n}\n".encode(), f"element vertex {n + count_delta}\n".encode()))
    return path


def _without(cols: dict, name: str) -> dict:
    return {k: v for k, v in cols.items() if k != name}


def _with_nan(cols: dict) -> dict:
    out = dict(cols)
    out["y"] = cols["y"].copy()
    out["y"][3] = np.nan
    return out


BAD = {
    "missing z": (lambda t: _binary(t, "noz.ply", _without(_columns(10), "z")), [], "lacks z"),
    "count too high": (lambda t: _binary(t, "trunc.ply", _columns(10), 2), [],
                       "truncated: header promises 12 vertices, file holds 10"),
    "count too low": (lambda t: _binary(t, "low.ply", _columns(10), -2), [], "more bytes after them"),
    "mixed types": (lambda t: _ascii_ply(t, "mixed.ply", ["1 2 3 4", "1 2 3 1.5"]), [],
                    "mixed types: property 'class' is declared uint8 but vertex 2 holds 1.5"),
    "text in numbers": (lambda t: _ascii_ply(t, "word.ply", ["1 2 3 4", "1 two 3 4"]), [], "unreadable value"),
    "ascii truncated": (lambda t: _ascii_ply(t, "short.ply", ["1 2 3 4"], count=3), [],
                        "truncated: header promises 3 vertices, file holds 1"),
    "nan": (lambda t: _binary(t, "nan.ply", _with_nan(_columns(10))), [], "NaN or infinite coordinates (point 3)"),
    "not ply": (lambda t: (t / "fake.ply").write_text("hello\n") and t / "fake.ply", [], "not a PLY file"),
    "spec mismatch": (lambda t: (t / "p.xyz").write_text("1 2 3 4\n5 6 7 8\n") and t / "p.xyz", ["--columns", "x,y,z"],
                      "column spec names 3 columns (x,y,z) but rows hold 4 values"),
    "spec without x": (lambda t: (t / "q.xyz").write_text("1 2 3\n") and t / "q.xyz", ["--columns", "a,y,z"],
                       "column spec 'a,y,z' lacks x"),
    "no spec, odd count": (lambda t: (t / "r.xyz").write_text("1 2 3 4 5\n") and t / "r.xyz", [],
                           "rows hold 5 values and there is no header line"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_point_files_give_one_line_naming_the_file(tmp_path, case) -> None:
    make, extra, needle = BAD[case]
    path = make(tmp_path)
    code, _, err = run("info", path, *extra)
    one_line_error(code, err, path.name, needle)


def test_origin_knots_reproduce_every_origin() -> None:
    t = np.arange(10_000) / 1000.0
    origins = np.column_stack([5 * t, np.sin(t), np.full_like(t, 2.5)])
    index, knots = origin_knots(100, origins, 0.01)
    assert len(knots) < len(origins) / 10  # a smooth path needs few knots
    track = Trajectory(time=index, xyz=knots)
    assert np.abs(track.position_at(100 + np.arange(10_000.0)) - origins).max() <= 0.01


# ----------------------------------------------------------------------------------------------------------------------
# map update through the CLI on a simulated PLY campaign


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """One building (+ the construction lot) scanned once, as PLY with origins and GPS time; variants of the same
    campaign without origins (estimated path from GPS time) and without anything (estimated path from geometry)."""
    from lidarmap.sim import SimParams, load_truth, simulate

    out = tmp_path_factory.mktemp("mls")
    simulate(out, SimParams(seed=SEED, buildings=1, campaigns=1, mls_format="ply", mls_origins=True))
    cloud = read_points(out / "mls_1.ply")
    base = {"x": cloud.xyz[:, 0], "y": cloud.xyz[:, 1], "z": cloud.xyz[:, 2],
            "classification": cloud.attrs["classification"]}
    write_points_ply(out / "bare.ply", base, ["crs EPSG:32632"])
    return out, load_truth(out)


def _score(map_path: Path, truth) -> tuple[float, list[str], object]:
    from lidarmap.facade.eval import evaluate_facades
    from lidarmap.map.store import MapStore

    with MapStore.open(map_path) as store:
        building_map = store.load()
    truth_fp = {str(b.id): Polygon(b.footprint) for b in truth.buildings}
    renamed = []
    for b in building_map.buildings.values():  # buildings found from the points: named by the truth they overlap
        best = max(truth_fp, key=lambda k: truth_fp[k].intersection(b.footprint).area)
        renamed.append(dataclasses.replace(b, building_id=best) if truth_fp[best].intersects(b.footprint) else b)
    score = evaluate_facades(renamed, truth, 1)
    return score["window"]["f1"], sorted(str(b.building_id) for b in renamed), building_map


def _history_sensors(map_path: Path) -> str:
    from lidarmap.map.store import MapStore

    with MapStore.open(map_path) as store:
        return store.history()[-1][0].summary["sensors"]


def test_update_from_ply_with_origins_matches_the_truth(scene, tmp_path) -> None:
    out, truth = scene
    path = tmp_path / "o.lmap"
    code, _, err = run("map", "update", path, "--points", out / "mls_1.ply", "-f", out / "footprints.geojson")
    assert code == 0, err
    f1, ids, _ = _score(path, truth)
    assert f1 >= 0.9 and ids == ["1", "2"]
    assert _history_sensors(path) == "origins"


def test_update_without_trajectory_or_origins_estimates_the_path(scene, tmp_path) -> None:
    out, truth = scene
    traj = Trajectory  # the true trajectory, to measure the estimate against
    from lidarmap.io.trajectory import read_trajectory

    true = read_trajectory(out / "trajectory_1.csv")
    cloud = read_points(out / "mls_1.ply")
    params = SensorParams()
    path_est = estimate_path(cloud.xyz, cloud.attrs["classification"], params)
    across = path_trajectory(path_est).position_at(path_times(path_est, cloud.xyz[:, :2]))
    ground = ground_points(cloud.xyz, cloud.attrs["classification"], params.cell)
    slopes = profile_slopes(path_est, ground, params)
    clock = PulseClock(with_height(path_est, ground, slopes, params), slopes)
    estimate = clock.trajectory([cloud]).position_at(clock(0, cloud))  # what map update does with bare.ply
    assert len(clock.slopes) == 1 and abs(np.degrees(np.arctan(clock.slopes[0]))) < 2.0  # a profiler across
    error = np.linalg.norm(estimate - true.position_at(cloud.attrs["gps_time"]), axis=1)
    before = np.linalg.norm(across - true.position_at(cloud.attrs["gps_time"]), axis=1)
    assert np.median(error) < 0.5 and np.median(error) <= np.median(before) + 0.05, (np.median(error),
                                                                                     np.median(before))
    assert isinstance(true, traj)
    path = tmp_path / "e.lmap"
    code, _, err = run("map", "update", path, "--points", out / "bare.ply", "-f", out / "footprints.geojson")
    assert code == 0, err
    f1, _, building_map = _score(path, truth)
    assert f1 >= 0.9
    campaign = building_map.campaigns[-1]
    assert campaign.summary["sensors"] == "estimated from the cloud" and campaign.summary["noise_factor"] == 2.0
    assert campaign.source == "bare.ply [estimated from the cloud]"  # what map history shows


def test_update_without_footprints_finds_the_buildings_and_joins_footprints_given_later(scene, tmp_path) -> None:
    out, truth = scene
    path = tmp_path / "n.lmap"
    code, _, err = run("map", "update", path, "--points", out / "mls_1.ply")
    assert code == 0, err
    f1, ids, building_map = _score(path, truth)
    assert f1 >= 0.9 and ids == ["1", "2"]  # every building of the footprint run
    found = sorted(building_map.buildings)
    assert all(bid.startswith("p") for bid in found)
    # footprints given with the next campaign join the buildings found before (ids kept, footprint replaced)
    code, _, err = run("map", "update", path, "--points", out / "bare.ply", "-f", out / "footprints.geojson")
    assert code == 0, err
    _, _, joined = _score(path, truth)
    assert sorted(joined.buildings) == found
    assert sorted(b.attributes["footprint_id"] for b in joined.buildings.values()) == ["1", "2"]
    doc = json.loads((out / "footprints.geojson").read_text())
    assert len(doc["features"]) == 2
