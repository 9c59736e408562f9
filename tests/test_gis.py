"""What GIS tools need: footprints from GeoPackage/Shapefile/FlatGeobuf, the run's GeoPackage layer, LAS and mesh
CRS records a GIS reads, described extra dimensions."""

from __future__ import annotations

import builtins
import sqlite3
from pathlib import Path

import laspy
import numpy as np
import pytest
import shapely
import trimesh
from pyproj import CRS, Transformer
from shapely.geometry import MultiPolygon, Polygon, box

import lidarmap
from lidarmap.core import PointCloud
from lidarmap.errors import CRSError, InputError
from lidarmap.io.footprints import read_footprints
from lidarmap.io.gpkg import write_gpkg_polygons
from lidarmap.io.las import EXTRA_DIMS, read_las, write_las
from lidarmap.io.meshfile import read_ply_crs, write_mesh

pyogrio = pytest.importorskip("pyogrio", reason="pyogrio is in the test extra (pip install -e '.[test]')")

RD = CRS.from_epsg(28992)
#: Two footprints near Delft (RD New), one a polygon with a courtyard, one a two-part multipolygon.
COURTYARD = Polygon([(85000, 446000), (85030, 446000), (85030, 446020), (85000, 446020)],
                    [[(85010, 446005), (85020, 446005), (85020, 446015), (85010, 446015)]])
TWO_PARTS = MultiPolygon([box(85040, 446000, 85050, 446010), box(85060, 446000, 85070, 446010)])


def _write_vector(path: Path, driver: str, crs: CRS | None = RD) -> Path:
    geoms = np.array([shapely.to_wkb(COURTYARD), shapely.to_wkb(MultiPolygon([COURTYARD])),
                      shapely.to_wkb(TWO_PARTS)], dtype=object)
    ids = np.array(["0363100012345678", "0363100012345679", "0363100012345680"], dtype=object)
    heights = np.array([12.5, 9.0, 7.25])
    pyogrio.raw.write(path, geoms, (ids, heights), ["bag_id", "height"], driver=driver,
                      geometry_type="MultiPolygon", crs=None if crs is None else crs.to_wkt())
    return path


@pytest.mark.parametrize(("name", "driver"), [("bag.gpkg", "GPKG"), ("bag.shp", "ESRI Shapefile"),
                                              ("bag.fgb", "FlatGeobuf")])
def test_footprints_from_gdal_formats_keep_ids_geometry_properties_and_crs(tmp_path: Path, name: str,
                                                                          driver: str) -> None:
    path = _write_vector(tmp_path / name, driver)
    fp = read_footprints(path, id_field="bag_id")
    # FlatGeobuf's spatial index reorders features: compare by id
    assert sorted(fp.ids) == ["0363100012345678", "0363100012345679", "0363100012345680"]
    assert fp.crs.to_epsg() == 28992
    polygon = dict(zip(fp.ids, fp.polygons))
    assert polygon["0363100012345678"].equals(COURTYARD)  # the courtyard stays a hole
    assert polygon["0363100012345680"].equals(TWO_PARTS)
    height = {i: p["height"] for i, p in zip(fp.ids, fp.properties)}
    assert height == {"0363100012345678": 12.5, "0363100012345679": 9.0, "0363100012345680": 7.25}
    assert all(type(h) is float for h in height.values())  # plain Python values (JSON, CityJSON attributes)
    wgs = read_footprints(path, id_field="bag_id", crs=CRS.from_epsg(4326))
    lon, lat = shapely.get_coordinates(wgs.polygons[0])[0]
    assert 4.3 < lon < 4.4 and 51.9 < lat < 52.1  # Delft


@pytest.mark.filterwarnings("ignore:'crs' was not provided")
def test_shapefile_without_prj_is_a_crs_error(tmp_path: Path) -> None:
    path = _write_vector(tmp_path / "nocrs.shp", "ESRI Shapefile", crs=None)
    with pytest.raises(CRSError, match=r"nocrs\.shp: footprint file has no CRS"):
        read_footprints(path)


def test_broken_geopackage_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.gpkg"
    path.write_bytes(b"not a database at all")
    with pytest.raises(InputError, match=r"broken\.gpkg: cannot read as GeoPackage \("):
        read_footprints(path)


def test_missing_pyogrio_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _write_vector(tmp_path / "bag.gpkg", "GPKG")
    real_import = builtins.__import__

    def no_pyogrio(name: str, *args, **kwargs):
        if name == "pyogrio" or name.startswith("pyogrio."):
            raise ImportError("No module named 'pyogrio'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pyogrio)
    with pytest.raises(InputError) as info:
        read_footprints(path)
    assert str(info.value) == (f"{path}: reading GeoPackage footprints needs pyogrio: pip install 'lidarmap[gis]' "
                               "(or convert to GeoJSON)")


def test_geopackage_writer_round_trips_through_gdal(tmp_path: Path) -> None:
    out = write_gpkg_polygons(tmp_path / "b.gpkg", "buildings", [COURTYARD, TWO_PARTS, None],
                              {"id": ["a", "b", "c"], "coverage": [0.5, float("nan"), None], "points": [10, None, 3],
                               "reason": [None, None, "no points within 1 m"]}, RD)
    info = pyogrio.read_info(out)
    assert info["layer_name"] == "buildings" and info["geometry_type"] == "MultiPolygon"
    assert info["crs"] == "EPSG:28992" and info["features"] == 3
    assert list(info["fields"]) == ["id", "coverage", "points", "reason"]
    assert info["ogr_types"] == ["OFTString", "OFTReal", "OFTInteger64", "OFTString"]
    assert info["total_bounds"] == (85000.0, 446000.0, 85070.0, 446020.0)
    _, _, wkb, (ids, coverage, points, reason) = pyogrio.raw.read(out)
    assert shapely.from_wkb(wkb[0]).equals(COURTYARD) and shapely.from_wkb(wkb[1]).equals(TWO_PARTS)
    assert wkb[2] is None
    assert list(ids) == ["a", "b", "c"] and coverage[0] == 0.5 and np.isnan(coverage[1:]).all()
    assert list(reason) == [None, None, "no points within 1 m"]
    assert points[0] == 10 and np.isnan(points[1]) and points[2] == 3
    with sqlite3.connect(out) as db:  # the GeoPackage marks GDAL checks too
        assert db.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
        assert db.execute("PRAGMA user_version").fetchone()[0] == 10300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.gpkg"]  # no temporary or journal file left


def test_geopackage_without_crs_declares_an_undefined_one(tmp_path: Path) -> None:
    out = write_gpkg_polygons(tmp_path / "b.gpkg", "buildings", [COURTYARD], {"id": ["a"]}, None)
    info = pyogrio.read_info(out)
    assert "Undefined Cartesian SRS" in info["crs"] and info["features"] == 1


# ---------------------------------------------------------------- LAS and mesh CRS records
def _cloud(crs: CRS | None) -> PointCloud:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 50, (200, 3)) + [85000.0, 446000.0, 0.0]
    plane_id = np.where(np.arange(200) % 2 == 0, -1, 3).astype(np.int32)
    return PointCloud(xyz=xyz, attrs={"plane_id": plane_id, "building_probability": rng.random(200, np.float32),
                                      "my_dim": np.ones(200, np.uint8)},
                      crs=crs, extra_dims=["plane_id", "building_probability", "my_dim"])


def test_las_carries_wkt1_crs_described_extra_dims_and_lidarmap_as_software(tmp_path: Path) -> None:
    compound = CRS.from_user_input("EPSG:28992+5709")  # RD New + NAP height, as AHN
    path = write_las(tmp_path / "p.laz", _cloud(compound))
    las = laspy.read(path)
    assert las.header.generating_software == f"lidarmap {lidarmap.__version__}"
    wkt = las.header.vlrs.get("WktCoordinateSystemVlr")[0].string
    assert wkt.startswith('COMPD_CS["Amersfoort / RD New + NAP height"')  # WKT1, not WKT2's COMPOUNDCRS
    assert las.header.global_encoding.wkt
    assert las.header.parse_crs().to_epsg() == 7415
    assert read_las(path).crs.equals(compound)
    structs = {s.name.rstrip(b"\0").decode(): s for s in las.header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs}
    assert structs["plane_id"].description.rstrip(b"\0") == b"flatten plane id, -1: none"
    assert structs["plane_id"].no_data[0] == -1 and structs["plane_id"].options & 1  # no-data bit set
    assert structs["building_probability"].description.rstrip(b"\0") == b"P(building) from segmentation"
    assert not structs["my_dim"].options & 1  # unknown dimensions: no invented no-data value
    assert np.array_equal(np.asarray(las["plane_id"]), _cloud(None).attrs["plane_id"])


def test_every_known_extra_dim_description_fits_the_las_field() -> None:
    assert all(len(text.encode()) <= 32 for text, _ in EXTRA_DIMS.values())


@pytest.mark.parametrize("crs", [CRS.from_epsg(28992), CRS.from_proj4("+proj=tmerc +lon_0=5 +x_0=1000 +ellps=GRS80")])
def test_meshes_name_their_crs_in_the_ply_header_and_a_prj_sidecar(tmp_path: Path, crs: CRS) -> None:
    mesh = trimesh.creation.box(extents=(10, 10, 10))
    mesh.apply_translation([85000.0, 446000.0, 5.0])
    write_mesh(tmp_path / "m.ply", mesh, crs)
    write_mesh(tmp_path / "n.obj", mesh, crs)
    assert read_ply_crs(tmp_path / "m.ply").equals(crs)
    header = (tmp_path / "m.ply").read_bytes().split(b"end_header")[0].decode()
    assert ("comment crs EPSG:28992" in header) == (crs.to_epsg() == 28992)
    for prj in (tmp_path / "m.prj", tmp_path / "n.prj"):
        # the same system (ESRI WKT renames datums: compare what it does to a point)
        to_prj = Transformer.from_crs(crs, CRS.from_user_input(prj.read_text()), always_xy=True)
        assert np.allclose(to_prj.transform(85000.0, 446000.0), (85000.0, 446000.0), atol=1e-6)
        assert prj.read_text().startswith("PROJCS[")  # WKT1 as .prj files carry it
    loaded = trimesh.load(tmp_path / "m.ply", process=False)
    assert np.allclose(loaded.vertices, mesh.vertices)  # the extra comment does not disturb readers


def test_mesh_without_crs_has_no_sidecar(tmp_path: Path) -> None:
    write_mesh(tmp_path / "m.ply", trimesh.creation.box())
    assert read_ply_crs(tmp_path / "m.ply") is None and sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]
