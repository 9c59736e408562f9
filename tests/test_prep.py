"""Preprocessing: point -> footprint assignment, tile merging, filters, outputs, CRS handling, CLI errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
from pyproj import CRS
from shapely.geometry import Polygon, box

from lidarmap.aerial.pipeline import prep_tiles
from lidarmap.aerial.prep import (
    FootprintIndex,
    PrepParams,
    assign_points,
    canonical_order,
    prep_cloud,
)
from lidarmap.core import Footprints, PointCloud
from lidarmap.errors import ConfigError, CRSError, InputError
from lidarmap.frame import LocalFrame
from lidarmap.io.footprints import read_footprints, write_geojson_wgs84
from lidarmap.io.las import read_las, write_las
from lidarmap.io.prepdir import read_prep_index, write_prep

UTM32 = CRS.from_epsg(32632)
RD = "EPSG:28992"
X0, Y0 = 500000.0, 5800000.0


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarmap", *args], capture_output=True, text=True, timeout=300)


# ----------------------------------------------------------------------------------------------------------------
# Synthetic scenes
# ----------------------------------------------------------------------------------------------------------------


def box_scene(seed: int = 0) -> tuple[PointCloud, Footprints]:
    """Ground over 60 m x 40 m plus two box buildings (12 m and 2 m high) and a construction site (8 m)."""
    rng = np.random.default_rng(seed)
    n = 24_000
    xy = rng.uniform([0, 0], [60, 40], size=(n, 2))
    z = np.full(n, 10.0) + rng.normal(0, 0.02, n)
    cls = np.full(n, 2, np.uint8)
    boxes = [(box(5, 5, 20, 20), 12.0), (box(25, 5, 35, 15), 2.0), (box(40, 5, 55, 20), 8.0)]
    for poly, height in boxes:
        inside = shapely.contains_xy(poly, xy[:, 0], xy[:, 1])
        z[inside] = 10.0 + height
        cls[inside] = 6
    rgb = rng.integers(0, 65536, size=(n, 3)).astype(np.uint16)
    attrs = {"classification": cls, "intensity": rng.integers(0, 4000, n).astype(np.uint16),
             "return_number": np.ones(n, np.uint8), "number_of_returns": np.ones(n, np.uint8),
             "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    cloud = PointCloud(np.column_stack([xy + [X0, Y0], z]), attrs, UTM32, source="scene")
    polys = np.array([shapely.affinity.translate(p, X0, Y0) for p, _ in boxes], dtype=object)
    props = [{"id": "tall", "status": "existing"}, {"id": "low", "status": "existing"},
             {"id": "site", "status": "Under  Construction"}]
    return cloud, Footprints(["tall", "low", "site"], polys, props, UTM32)


def write_geojson_crs(path: Path, fps: Footprints, epsg: int, extra: list[dict] | None = None) -> Path:
    """Footprints as GeoJSON with a legacy ``crs`` member (coordinates as they are)."""
    features = [{"type": "Feature", "properties": {**p, **(extra[i] if extra else {})},
                 "geometry": shapely.geometry.mapping(g)} for i, (g, p) in enumerate(zip(fps.polygons, fps.properties))]
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": f"EPSG:{epsg}"}},
           "features": features}
    path.write_text(json.dumps(doc))
    return path


# ----------------------------------------------------------------------------------------------------------------
# Assignment
# ----------------------------------------------------------------------------------------------------------------


def test_assignment_matches_shapely_nearest() -> None:
    """Random points around touching and overlapping polygons with a hole: nearest footprint and distance exact."""
    rng = np.random.default_rng(1)
    ring = box(0, 0, 10, 10).difference(box(3, 3, 6, 6))  # a courtyard: its points are 0-3 m from the walls
    polys = [ring, box(10, 0, 20, 8), box(18, 6, 30, 12), Polygon([(0, 14), (12, 30), (-8, 22)])]
    xy = rng.uniform([-8, -8], [36, 36], size=(20_000, 2))
    index, distance = assign_points(xy, polys, 4.0)
    tree = shapely.STRtree(polys)
    (pt, fp), d = tree.query_nearest(shapely.points(xy), max_distance=4.0, return_distance=True, all_matches=True)
    expected = np.full(len(xy), np.inf)
    np.minimum.at(expected, pt, d)
    np.testing.assert_allclose(distance[np.isfinite(expected)], expected[np.isfinite(expected)], atol=1e-9)
    assert np.all(index[~np.isfinite(expected)] == -1)
    ties = {(p, f) for p, f in zip(pt.tolist(), fp.tolist())}
    assigned = np.flatnonzero(index >= 0)
    assert all((p, index[p]) in ties for p in assigned.tolist())
    inside_both = shapely.contains_xy(polys[1], xy[:, 0], xy[:, 1]) & shapely.contains_xy(polys[2], xy[:, 0],
                                                                                            xy[:, 1])
    assert inside_both.any() and np.all(index[inside_both] == 1)  # overlap: the first footprint wins
    courtyard = shapely.contains_xy(box(3, 3, 6, 6), xy[:, 0], xy[:, 1])
    assert np.all(index[courtyard] == 0) and np.all(distance[courtyard] > 0)


def test_index_refuses_distances_beyond_its_reach() -> None:
    index = FootprintIndex([box(0, 0, 1, 1)], 2.0)
    with pytest.raises(ValueError, match="exceeds the index reach"):
        index.assign(np.zeros((1, 2)), max_distance=3.0)


@pytest.fixture(scope="module")
def delft() -> tuple[PointCloud, Footprints]:
    from conftest import shared_file

    cloud = read_las(shared_file("ahn3_delft/ahn3_cropped_1.laz"), crs=RD)
    fps = read_footprints(shared_file("ahn3_delft/footprints_bgt_EPSG28992.geojson"), id_field="bag_pand_id")
    return cloud, fps


def test_delft_split_one_building_per_point(delft: tuple[PointCloud, Footprints]) -> None:
    cloud, fps = delft
    result = prep_cloud(cloud, fps, PrepParams(chunk_points=200_000))
    assert 100 <= len(result.buildings) <= 160
    # every point in at most one building: no coordinate appears twice across building files
    xyz = np.concatenate([b.cloud.xyz for b in result.buildings])
    assert len(np.unique(xyz, axis=0)) == len(xyz) == result.points_kept
    # the points strictly inside a known footprint all land in that building, and nothing else inside it does
    by_id = {b.id: b for b in result.buildings}
    checked = 0
    for i, fid in enumerate(fps.ids):
        if fid not in by_id:
            continue
        inside = shapely.contains_xy(fps.polygons[i], cloud.xyz[:, 0], cloud.xyz[:, 1])
        others = np.zeros(len(cloud), bool)
        for j in range(i):  # overlapping earlier footprints would win
            others |= shapely.contains_xy(fps.polygons[j], cloud.xyz[:, 0], cloud.xyz[:, 1])
        own = cloud.xyz[inside & ~others]
        building = by_id[fid]
        got = set(map(tuple, building.cloud.xyz[building.distance == 0]))
        assert set(map(tuple, own)) <= got
        assert building.points_inside == len(got)
        checked += 1
        if checked == 5:
            break
    assert checked == 5
    assert all(b.distance.max() <= 5.0 + 1e-9 for b in result.buildings)


def test_delft_footprints_in_wgs84_are_reprojected(tmp_path: Path, delft: tuple[PointCloud, Footprints]) -> None:
    cloud, fps = delft
    sub = fps.subset(np.arange(40))
    wgs = read_footprints(write_geojson_wgs84(tmp_path / "wgs.geojson", list(sub.polygons), sub.properties,
                                              sub.crs), id_field="bag_pand_id")
    assert wgs.crs.to_epsg() == 4326
    window = cloud.subset((cloud.xyz[:, 0] < 84880) & (cloud.xyz[:, 1] > 447470))
    direct = prep_cloud(window, sub)
    reprojected = prep_cloud(window, wgs)
    assert [b.id for b in reprojected.buildings] == [b.id for b in direct.buildings]
    moved = sum(abs(len(a) - len(b)) for a, b in zip(direct.buildings, reprojected.buildings))
    assert moved <= 0.001 * direct.points_kept  # sub-millimetre differences of the round trip at most


# ----------------------------------------------------------------------------------------------------------------
# Filters, merge, outputs
# ----------------------------------------------------------------------------------------------------------------


def test_construction_and_low_buildings_are_dropped() -> None:
    cloud, fps = box_scene()
    result = prep_cloud(cloud, fps)
    assert [b.id for b in result.buildings] == ["tall"]
    assert result.dropped["site"].startswith("under construction")
    assert result.dropped["low"].startswith("lower than 3 m (2.00 m")
    tall = result.buildings[0]
    assert tall.height_source == "points" and tall.height == pytest.approx(12.0, abs=0.1)
    # the points near the dropped site are gone, not handed to the tall building
    assert tall.cloud.xyz[:, 0].max() < X0 + 20 + 5 + 1e-9
    # configurable: another status field/value list, footprint heights, no minimum
    fps.properties[1]["height"] = "3,5"  # a numeric string with a decimal comma counts
    keep_all = prep_cloud(cloud, fps, PrepParams(status_field="phase", min_height=0.0))
    assert [b.id for b in keep_all.buildings] == ["tall", "low", "site"]
    low = keep_all.buildings[1]
    assert (low.height, low.height_source) == (3.5, "footprint")
    custom = prep_cloud(cloud, fps, PrepParams(excluded_statuses=("existing",)))
    assert [b.id for b in custom.buildings] == ["site"]


def test_rgb_quantised_to_8_bits_and_frame_maps_back_exactly(tmp_path: Path) -> None:
    cloud, fps = box_scene()
    result = prep_cloud(cloud, fps, PrepParams(rotation_deg=30.0))
    tall = result.buildings[0]
    rgb = np.stack([tall.cloud.attrs[c] for c in ("red", "green", "blue")], axis=1)
    assert np.all(rgb % 257 == 0) and rgb.max() <= 65535
    source = cloud.subset(np.isin(cloud.xyz[:, 0], tall.cloud.xyz[:, 0]))
    source = source.subset(canonical_order({"xyz": source.xyz, **source.attrs}))  # prep's point order
    np.testing.assert_array_equal(tall.cloud.xyz, source.xyz)
    np.testing.assert_array_equal(tall.rgb8(), source.rgb8())  # v16 // 257, exactly
    out = write_prep(tmp_path / "prep", result)
    frame_doc = json.loads((out / "frame.json").read_text())
    frame = LocalFrame.from_json(json.dumps(frame_doc))
    assert frame.rotation_deg == 30.0 and CRS.from_wkt(frame_doc["crs"]).to_epsg() == 32632
    back = read_las(out / "buildings" / "tall.laz")
    local = frame.to_local(back.xyz)
    assert np.all(local.min(axis=0) > -60) and np.abs(local).max() < 100  # small numbers: float32-safe
    np.testing.assert_allclose(frame.to_crs(local), back.xyz, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.xyz, tall.cloud.xyz, atol=0.0005 + 1e-9)


def test_tiles_merged_while_streaming_equal_one_cloud(tmp_path: Path) -> None:
    """A building cut by tile borders comes out whole and the same, whatever the tiling and chunk size."""
    cloud, fps = box_scene()
    x = cloud.xyz[:, 0] - X0
    tiles = []
    for k, (lo, hi) in enumerate([(0, 12), (12, 30), (30, 61)]):  # the tall building spans the first two tiles
        tiles.append(write_las(tmp_path / f"tile_{k}.laz", cloud.subset((x >= lo) & (x < hi))))
    whole = prep_cloud(PointCloud.concatenate([read_las(t) for t in tiles]), fps, PrepParams(min_height=0.0))
    merged = prep_tiles(tiles, fps, PrepParams(min_height=0.0, chunk_points=1_000))
    assert merged.points_read == len(cloud)
    assert [b.id for b in merged.buildings] == [b.id for b in whole.buildings]
    for a, b in zip(merged.buildings, whole.buildings):  # same points in the same (canonical) order
        np.testing.assert_array_equal(a.cloud.xyz, b.cloud.xyz)
        for name in b.cloud.attrs:
            np.testing.assert_array_equal(a.cloud.attrs[name], b.cloud.attrs[name])
        assert (a.height, a.ground_z) == (b.height, b.ground_z)
    tall = merged.buildings[0].cloud.xyz[:, 0] - X0
    assert tall.min() < 12 < tall.max()  # points from both tiles


def test_tiles_in_different_crs_are_refused(tmp_path: Path) -> None:
    cloud, fps = box_scene()
    a = write_las(tmp_path / "a.laz", cloud)
    b = write_las(tmp_path / "b.laz", PointCloud(cloud.xyz, cloud.attrs, CRS.from_epsg(32631)))
    with pytest.raises(CRSError, match="differs from 'WGS 84 / UTM zone 32N' of a.laz; all tiles must share one CRS"):
        prep_tiles([a, b], fps)
    with pytest.raises(InputError, match="tile given twice"):
        prep_tiles([a, tmp_path / "." / "a.laz"], fps)


def test_write_prep_index_counts_and_replaces_only_prep_output(tmp_path: Path) -> None:
    cloud, fps = box_scene()
    fps.ids[0] = "a/b c"  # ids become safe file names
    result = prep_cloud(cloud, fps, PrepParams(min_height=0.0, status_field="none"))
    out = write_prep(tmp_path / "out", result)
    rows = read_prep_index(out)
    assert [r["id"] for r in rows] == ["a/b c", "low", "site"]
    assert rows[0]["file"] == "buildings/a_b_c.laz"
    for row, building in zip(rows, result.buildings):
        assert row["points"] == len(building) == len(read_las(row["path"]))
    summary = json.loads((out / "prep.json").read_text())
    assert summary["points_read"] == len(cloud) and summary["buildings"] == 3
    write_prep(out, prep_cloud(cloud, fps))  # an earlier prep output is replaced
    assert [r["id"] for r in read_prep_index(out)] == ["a/b c"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty and was not written by lidarmap"):
        write_prep(tmp_path / "other", result)
    assert (tmp_path / "other" / "keep.txt").read_text() == "mine"


def test_params_are_checked() -> None:
    with pytest.raises(ConfigError, match="buffer must be"):
        PrepParams(buffer=-1.0)
    with pytest.raises(ConfigError, match="roof_percentile"):
        PrepParams(roof_percentile=120.0)


# ----------------------------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("scene")
    cloud, fps = box_scene()
    return write_las(folder / "scene.laz", cloud), write_geojson_crs(folder / "fp.geojson", fps, 32632)


def test_cli_prep_with_config_and_flags(tmp_path: Path, scene_files: tuple[Path, Path]) -> None:
    laz, geojson = scene_files
    config = tmp_path / "c.toml"
    config.write_text("[prep]\nmin_height = 0.0\nbuffer = 2.0\nexcluded_statuses = []\n")
    result = run_cli("prep", str(laz), "--footprints", str(geojson), "-o", str(tmp_path / "out"), "--config",
                     str(config), "--rotation", "15")
    assert result.returncode == 0, result.stderr
    rows = read_prep_index(tmp_path / "out")
    assert [r["id"] for r in rows] == ["tall", "low", "site"]
    tall = read_las(rows[0]["path"])
    assert tall.attrs["footprint_distance"].max() <= 2.0 + 1e-6  # buffer from the config
    summary = json.loads((tmp_path / "out" / "prep.json").read_text())
    assert summary["params"]["rotation_deg"] == 15.0 and summary["params"]["buffer"] == 2.0
    flag = run_cli("prep", str(laz), "-f", str(geojson), "-o", str(tmp_path / "out"), "--config", str(config),
                   "--buffer", "1")
    assert flag.returncode == 0, flag.stderr
    assert read_las(read_prep_index(tmp_path / "out")[0]["path"]).attrs["footprint_distance"].max() <= 1.0 + 1e-6


@pytest.mark.parametrize("case,expected", [
    ("missing_tile", "nope.laz: file not found"),
    ("bad_crs", "footprints do not overlap the points"),
    ("no_crs", "no CRS record in the file; pass --crs"),
    ("not_las", "not a valid LAS/LAZ file"),
    ("out_is_file", "out' is a file"),
    ("bad_config", "unknown option 'bufer' in"),
])
def test_cli_prep_errors_are_one_line(tmp_path: Path, scene_files: tuple[Path, Path], case: str,
                                      expected: str) -> None:
    laz, geojson = scene_files
    out = tmp_path / "out"
    args = [str(laz), "-f", str(geojson), "-o", str(out)]
    if case == "missing_tile":
        args[0] = str(tmp_path / "nope.laz")
    elif case == "bad_crs":  # footprints in UTM 32N, points declared as RD New: reprojected, then they miss
        cloud = read_las(laz)
        no_crs = write_las(tmp_path / "nocrs.laz", PointCloud(cloud.xyz - [X0 - 85000, Y0 - 447000, 0],
                                                             cloud.attrs, None))
        args[0] = str(no_crs)
        args += ["--crs", RD]
    elif case == "no_crs":
        cloud = read_las(laz)
        args[0] = str(write_las(tmp_path / "nocrs.laz", PointCloud(cloud.xyz, cloud.attrs, None)))
    elif case == "not_las":
        (tmp_path / "junk.laz").write_bytes(b"not a point cloud at all")
        args[0] = str(tmp_path / "junk.laz")
    elif case == "out_is_file":
        out.write_text("x")
    elif case == "bad_config":
        (tmp_path / "c.toml").write_text("[prep]\nbufer = 3\n")
        args += ["--config", str(tmp_path / "c.toml")]
    result = run_cli("prep", *args)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert case == "out_is_file" or not out.exists()
