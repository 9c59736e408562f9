"""What GIS tools need: footprints from GeoPackage/Shapefile/FlatGeobuf, the run's GeoPackage layer, LAS and mesh
CRS records a GIS reads, described extra dimensions."""

from __future__ import annotations

import builtins
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import shapely
from pyproj import CRS
from shapely.geometry import MultiPolygon, Polygon, box

from lidarmap.errors import CRSError, InputError
from lidarmap.io.footprints import read_footprints
from lidarmap.io.gpkg import write_gpkg_polygons

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
    meta, _, wkb, (ids, coverage, points, reason) = pyogrio.raw.read(out)
    assert shapely.from_wkb(wkb[0]).equals(COURTYARD) and shapely.from_wkb(wkb[1]).equals(TWO_PARTS)
    assert wkb[2] is None
    assert list(ids) == ["a", "b", "c"] and coverage[0] == 0.5 and np.isnan(coverage[1:]).all()
    assert list(reason) == [None, None, "no points within 1 m"]
    with sqlite3.connect(out) as db:  # the GeoPackage marks GDAL checks too
        assert db.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
        assert db.execute("PRAGMA user_version").fetchone()[0] == 10300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.gpkg"]  # no temporary or journal file left


def test_geopackage_without_crs_declares_an_undefined_one(tmp_path: Path) -> None:
    out = write_gpkg_polygons(tmp_path / "b.gpkg", "buildings", [COURTYARD], {"id": ["a"]}, None)
    info = pyogrio.read_info(out)
    assert "Undefined Cartesian SRS" in info["crs"] and info["features"] == 1
