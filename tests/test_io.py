"""I/O: LAS/LAZ round trips, CRS handling, footprints, trajectories, info, bad input through the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
from pyproj import CRS
from shapely.geometry import Polygon

from lidarmap.core import PointCloud, Trajectory
from lidarmap.errors import CRSError, InputError
from lidarmap.io.footprints import check_overlap, read_footprints, write_geojson_wgs84
from lidarmap.io.info import las_info
from lidarmap.io.las import iter_las, read_las, write_las
from lidarmap.io.trajectory import read_trajectory, write_trajectory

UTM32 = CRS.from_epsg(32632)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarmap", *args], capture_output=True, text=True, timeout=120)


def make_cloud(n: int = 500, seed: int = 0, rgb: bool = True) -> PointCloud:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([500000, 5800000, 40], [500100, 5800100, 70], size=(n, 3))
    attrs = {
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "return_number": np.ones(n, np.uint8),
        "number_of_returns": np.ones(n, np.uint8),
        "classification": rng.choice([1, 2, 6], n).astype(np.uint8),
        "gps_time": np.sort(rng.uniform(1e5, 1e5 + 100, n)),
        "scan_angle": rng.uniform(-20, 20, n).astype(np.float32),
        "point_source_id": np.full(n, 3, np.uint16),
        "distance": rng.normal(size=n).astype(np.float32),
    }
    if rgb:
        for c in ("red", "green", "blue"):
            attrs[c] = rng.integers(0, 65535, n).astype(np.uint16)
    return PointCloud(xyz, attrs, UTM32, extra_dims=["distance"])


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("rgb", [True, False])
def test_write_read_round_trip(tmp_path: Path, suffix: str, rgb: bool) -> None:
    cloud = make_cloud(rgb=rgb)
    out = write_las(tmp_path / f"c{suffix}", cloud)
    back = read_las(out)
    assert np.abs(back.xyz - cloud.xyz).max() <= 0.0005 + 1e-9  # 1 mm grid: half a unit at most
    for name in ("intensity", "classification", "gps_time", "point_source_id", "distance"):
        np.testing.assert_array_equal(back.attrs[name], cloud.attrs[name])
    np.testing.assert_allclose(back.attrs["scan_angle"], cloud.attrs["scan_angle"], atol=0.0031)
    assert back.extra_dims == ["distance"]
    assert back.crs is not None and back.crs.to_epsg() == 32632
    assert back.has_rgb == rgb
    header = laspy.open(out).header
    assert (header.version.major, header.version.minor) == (1, 4)


@pytest.mark.parametrize("fmt,version", [(0, "1.2"), (1, "1.2"), (2, "1.2"), (3, "1.2"), (4, "1.3"), (5, "1.3"),
                                         (6, "1.4"), (7, "1.4"), (8, "1.4"), (9, "1.4"), (10, "1.4")])
def test_reads_every_point_format(tmp_path: Path, fmt: int, version: str) -> None:
    header = laspy.LasHeader(point_format=fmt, version=version)
    header.scales, header.offsets = [0.01] * 3, [1000, 2000, 0]
    header.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
    las = laspy.LasData(header)
    n = 50
    las.x, las.y, las.z = 1000 + np.arange(n), 2000 + np.arange(n) * 2.0, np.linspace(0, 10, n)
    las.classification = np.full(n, 6)
    las["reflectance"] = np.linspace(-1, 1, n).astype(np.float32)
    path = tmp_path / f"f{fmt}.laz"
    las.write(path)
    cloud = read_las(path, crs="EPSG:2154")
    assert len(cloud) == n
    np.testing.assert_allclose(cloud.xyz[:, 1], 2000 + np.arange(n) * 2.0)
    np.testing.assert_array_equal(cloud.attrs["classification"], 6)
    np.testing.assert_allclose(cloud.attrs["reflectance"], np.linspace(-1, 1, n), rtol=1e-6)
    assert cloud.crs.to_epsg() == 2154
    assert ("gps_time" in cloud.attrs) == (fmt not in (0, 2))
    assert ("red" in cloud.attrs) == (fmt in (2, 3, 5, 7, 8, 10))


def test_streaming_matches_whole_read(montpellier_tiles: list[Path]) -> None:
    path = montpellier_tiles[0]
    whole = read_las(path)
    chunks = list(iter_las(path, chunk_size=10_000))
    assert len(chunks) == -(-len(whole) // 10_000)
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in chunks]), whole.xyz)
    assert whole.crs.to_epsg() == 2154


def test_real_file_round_trip_keeps_crs_and_points(tmp_path: Path, montpellier_tiles: list[Path]) -> None:
    cloud = read_las(montpellier_tiles[1])
    back = read_las(write_las(tmp_path / "m.laz", cloud))
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=1e-6)
    np.testing.assert_array_equal(back.attrs["classification"], cloud.attrs["classification"])
    assert back.crs.to_epsg() == 2154


def test_crs_override_only_when_missing(delft_laz: Path, montpellier_tiles: list[Path]) -> None:
    assert read_las(delft_laz).crs is None  # AHN extract has no CRS record
    assert read_las(delft_laz, crs="28992").crs.to_epsg() == 28992
    with pytest.raises(CRSError, match="declares CRS .* but --crs"):
        read_las(montpellier_tiles[0], crs="EPSG:28992")
    with pytest.raises(CRSError, match="unknown CRS"):
        read_las(montpellier_tiles[0], crs="EPSG:999999")


def test_refuses_nan_coordinates(tmp_path: Path) -> None:
    cloud = make_cloud(10)
    cloud.xyz[3, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_las(tmp_path / "bad.laz", cloud)
    assert not (tmp_path / "bad.laz").exists()
    assert not list(tmp_path.iterdir())  # no temp file left behind either


def test_info_on_real_file(montpellier_tiles: list[Path]) -> None:
    info = las_info(montpellier_tiles[0])
    cloud = read_las(montpellier_tiles[0])
    assert info["point_count"] == len(cloud)
    assert info["crs"]["epsg"] == 2154
    assert sum(info["classes"].values()) == len(cloud)
    assert info["classes"]["6"] == int(np.count_nonzero(cloud.attrs["classification"] == 6))
    np.testing.assert_allclose(info["bounds"]["min"], cloud.xyz.min(axis=0))
    assert 10 < info["density"] < 60  # IGN LiDAR HD: tens of points per m2
    assert info["gps_time"]["min"] <= info["gps_time"]["max"]


def test_info_cli_json(montpellier_tiles: list[Path]) -> None:
    result = run_cli("info", str(montpellier_tiles[0]), "--json")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert {"point_count", "crs", "bounds", "classes"} <= set(data)


# ---------------------------------------------------------------- bad input through the CLI
def _truncated(tmp_path: Path, src: Path) -> Path:
    out = tmp_path / "truncated.laz"
    out.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    return out


def _damaged_tail(src: Path) -> bytes:
    data = bytearray(src.read_bytes())
    data[-2000:] = np.random.default_rng(0).integers(0, 256, 2000, dtype=np.uint8).tobytes()
    return bytes(data)


@pytest.mark.parametrize("case,expected", [
    ("missing", "file not found"),
    ("empty", "empty file"),
    ("garbage", "not a valid LAS/LAZ file"),
    ("truncated", "truncated"),
    ("chunk_table", "corrupt LAZ file"),
])
def test_bad_las_gives_one_line_error(tmp_path: Path, montpellier_tiles: list[Path], case: str, expected: str) -> None:
    def written(name: str, data: bytes) -> Path:
        (tmp_path / name).write_bytes(data)
        return tmp_path / name

    path = {
        "missing": lambda: tmp_path / "nope.laz",
        "empty": lambda: written("empty.laz", b""),
        "garbage": lambda: written("g.laz", b"LASF" + bytes(range(200))),
        "truncated": lambda: _truncated(tmp_path, montpellier_tiles[0]),
        # a damaged chunk count made lazrs allocate ~40 GB and abort the process (no Python exception)
        "chunk_table": lambda: written("chunks.laz", _damaged_tail(montpellier_tiles[0])),
    }[case]()
    result = run_cli("info", str(path))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert str(path.name) in lines[0] and expected in lines[0]
    assert "Traceback" not in result.stderr


def test_unknown_option_is_one_line(sample_c: Path) -> None:
    result = run_cli("info", str(sample_c), "--no-such-option")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "No such option" in result.stderr


# ---------------------------------------------------------------- footprints
def test_delft_footprints_legacy_crs(delft_footprints: Path) -> None:
    fp = read_footprints(delft_footprints, id_field="bag_pand_id")
    assert fp.crs.to_epsg() == 28992
    assert len(fp) == 160
    assert fp.ids[0] == "503100000018603"
    assert fp.properties[0]["bgt_status"] == "bestaand"
    x0, y0, x1, y1 = fp.bounds
    assert 84000 < x0 < x1 < 86000 and 447000 < y0 < y1 < 448000


def test_footprint_id_falls_back_to_index(delft_footprints: Path) -> None:
    fp = read_footprints(delft_footprints, id_field="no_such_field")
    assert fp.ids[:3] == ["0", "1", "2"]


def test_wgs84_footprints_reprojected_to_known_coordinates(tmp_path: Path) -> None:
    # The RD New (EPSG:28992) false origin (155000, 463000) is the Amersfoort tower, 52.15517440 N 5.38720621 E.
    lon, lat, d = 5.38720621, 52.15517440, 1e-4
    doc = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {"id": "tower"},
           "geometry": {"type": "Polygon", "coordinates": [[[lon - d, lat - d], [lon + d, lat - d], [lon + d, lat + d],
                                                            [lon - d, lat + d], [lon - d, lat - d]]]}}]}
    path = tmp_path / "f.geojson"
    path.write_text(json.dumps(doc))
    fp = read_footprints(path, crs=CRS.from_epsg(28992))
    centre = fp.polygons[0].centroid
    assert abs(centre.x - 155000) < 2.0 and abs(centre.y - 463000) < 2.0  # datum shift without grids: ~1 m


def test_geojson_write_read_round_trip_mm(tmp_path: Path) -> None:
    square = Polygon([(500010.0, 5800010.0), (500030.0, 5800010.0), (500030.0, 5800025.0), (500010.0, 5800025.0)])
    path = write_geojson_wgs84(tmp_path / "fp.geojson", [square], [{"id": "b1", "height": 12.0}], UTM32)
    doc = json.loads(path.read_text())
    assert "crs" not in doc  # RFC 7946: WGS84 implied
    lon, lat = doc["features"][0]["geometry"]["coordinates"][0][0]
    assert 8.9 < lon < 9.1 and 52.3 < lat < 52.4
    back = read_footprints(path, crs=UTM32)
    np.testing.assert_allclose(np.asarray(back.polygons[0].exterior.coords), np.asarray(square.exterior.coords),
                               atol=1e-3)
    assert back.ids == ["b1"] and back.properties[0]["height"] == 12.0


def test_footprints_missing_the_points_name_both_boxes(delft_footprints: Path) -> None:
    fp = read_footprints(delft_footprints)
    with pytest.raises(InputError, match=r"do not overlap.*footprints bbox \[84.*points bbox \[0\.00"):
        check_overlap(fp, (0.0, 0.0, 10.0, 10.0), "tile.laz")


def test_bad_footprint_files(tmp_path: Path) -> None:
    (tmp_path / "x.geojson").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_footprints(tmp_path / "x.geojson")
    (tmp_path / "y.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    with pytest.raises(InputError, match="no polygon footprints"):
        read_footprints(tmp_path / "y.geojson")
    (tmp_path / "z.geojson").write_text(json.dumps({"type": "FeatureCollection", "crs": {
        "type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::999999"}}, "features": []}))
    with pytest.raises(CRSError, match="unknown CRS"):
        read_footprints(tmp_path / "z.geojson")


# ---------------------------------------------------------------- trajectories
def test_trajectory_round_trip_and_interpolation(tmp_path: Path) -> None:
    t = np.linspace(100.0, 110.0, 11)
    xyz = np.column_stack([500000 + 10 * (t - 100), np.full_like(t, 5800000.0), np.full_like(t, 42.5)])
    traj = Trajectory(t, xyz, rpy=np.zeros((11, 3)))
    back = read_trajectory(write_trajectory(tmp_path / "t.csv", traj))
    np.testing.assert_array_equal(back.time, t)
    np.testing.assert_array_equal(back.xyz, xyz)
    pos = back.position_at(np.array([100.0, 103.25, 110.0]))
    np.testing.assert_allclose(pos[:, 0], [500000.0, 500032.5, 500100.0])
    with pytest.raises(InputError, match="outside the trajectory"):
        back.position_at(np.array([99.0, 105.0]))


def test_bad_trajectory_files(tmp_path: Path) -> None:
    cases = {
        "empty.csv": ("", "empty trajectory"),
        "cols.csv": ("time,x,y\n1,2,3\n2,3,4\n", "lacks column"),
        "nan.csv": ("time,x,y,z\n1,2,3,nan\n2,3,4,5\n", "NaN"),
        "order.csv": ("time,x,y,z\n2,2,3,4\n1,3,4,5\n", "strictly increasing"),
        "text.csv": ("time,x,y,z\n1,a,3,4\n2,3,4,5\n", "unreadable"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=message) as info:
            read_trajectory(tmp_path / name)
        assert name in str(info.value)


def test_bad_config_names_the_file_and_keeps_table_names(tmp_path: Path) -> None:
    config = tmp_path / "my.toml"
    config.write_text("[simulate]\nbogus = 1\n")
    result = run_cli("simulate", str(tmp_path / "out"), "--config", str(config))
    assert result.returncode == 2
    line = result.stderr.strip()
    assert "\n" not in line and line.startswith(f"error: {config}:")
    assert "unknown option 'bogus' in [simulate]" in line  # "[simulate]" is text, not rich markup
    assert not (tmp_path / "out").exists()
