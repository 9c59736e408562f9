"""The curated top-level API: the README's Python example, on a small simulated scene and a real tile."""

from __future__ import annotations

import numpy as np
import pytest

import lidarmap
from lidarmap.sim import SimParams, load_truth, simulate


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    out = tmp_path_factory.mktemp("api") / "city"
    simulate(out, SimParams(seed=21, buildings=2, campaigns=2))
    return out


def test_top_level_names_load_lazily_and_unknown_names_fail():
    assert lidarmap.__version__
    assert set(lidarmap.__all__) >= {"read", "run", "segment_buildings", "update_map", "open_map", "export_cityjson"}
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        lidarmap.nope  # noqa: B018


def test_read_write_round_trip_keeps_coordinates(sample_c, tmp_path):
    cloud = lidarmap.read(sample_c, crs="EPSG:2227")
    back = lidarmap.read(lidarmap.write(tmp_path / "c.laz", cloud))
    assert len(back) == len(cloud) == 14408
    assert np.abs(back.xyz - cloud.xyz).max() < 1e-4 and back.crs.to_epsg() == 2227  # within the LAS scale


def test_readme_example_end_to_end(city, tmp_path):
    truth = load_truth(city)
    footprints = lidarmap.read_footprints(city / "footprints.geojson")
    result = lidarmap.run([truth.als], footprints, tmp_path / "out", crs=None)
    assert len(result.processed) >= 1 and not result.failed
    cloud = lidarmap.read(truth.als)
    probability = lidarmap.segment_buildings(cloud)
    assert probability.shape == (len(cloud),) and 0 <= probability.min() and probability.max() <= 1
    map_path = tmp_path / "city.lmap"
    for campaign in truth.campaigns:
        update = lidarmap.update_map(map_path, points=campaign.laz, trajectory=campaign.trajectory,
                                     footprints=city / "footprints.geojson")
        assert update.counts["windows"] > 0
    city_map = lidarmap.open_map(map_path)
    assert [c.campaign_id for c in city_map.campaigns] == [1, 2]
    assert len(lidarmap.open_map(map_path, as_of=1).campaigns) == 1
    out = lidarmap.export_cityjson(city_map, tmp_path / "city.city.json")
    assert out.read_text(encoding="utf-8").startswith('{"type":"CityJSON"')
