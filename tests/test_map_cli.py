"""``lidarmap map ...`` end to end on a small simulated city (2 buildings + a construction site, 2 campaigns):
update, show, history, export, render, re-applied campaigns, a concurrent writer, and bad inputs that must give one
line naming the file, a non-zero exit, no traceback and an untouched map.

Commands run in-process through the console entry point (``lidarmap.cli.main.main``) with stdout/stderr captured;
the concurrent writer is a second process.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import one_line_error
from conftest import run_cli_in_process as run
from PIL import Image

from lidarmap.export.render import facade_image_size
from lidarmap.export.summary import count_map
from lidarmap.export.validate import validate_cityjson
from lidarmap.io.footprints import read_footprints
from lidarmap.io.outdir import MARKER, read_marker
from lidarmap.map.store import MapStore, campaign_fingerprint


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from lidarmap.sim import SimParams, simulate

    return simulate(tmp_path_factory.mktemp("sim"), SimParams(seed=3, buildings=2, campaigns=2))


def campaign_args(sim, i: int) -> list[object]:
    return ["--points", sim.mls[i - 1], "--trajectory", sim.trajectories[i - 1], "--footprints", sim.footprints]


@pytest.fixture(scope="module")
def map1(sim, tmp_path_factory):
    """A map after campaign 1 (the update's exit code and output kept); copy it before changing it."""
    path = tmp_path_factory.mktemp("map") / "city.lmap"
    code, out, err = run("map", "update", path, *campaign_args(sim, 1))
    return path, code, out, err


@pytest.fixture
def map_copy(map1, tmp_path):
    path = tmp_path / "city.lmap"
    shutil.copyfile(map1[0], path)
    return path


def test_update_creates_the_map_and_prints_what_it_holds(sim, map1) -> None:
    path, code, out, err = map1
    assert code == 0, err
    with MapStore.open(path) as store:
        [campaign] = store.campaigns()
        m = store.load()
    assert (campaign.campaign_id, campaign.kind, campaign.source) == (1, "mobile", "mls_1.laz + trajectory_1.csv")
    assert campaign.fingerprint == campaign_fingerprint(sim.mls[0], sim.trajectories[0])
    assert campaign.n_points == sim.mls_points[0]
    k = count_map(m)
    assert {key: campaign.summary[key] for key in k} == k
    assert set(m.buildings) <= set(read_footprints(sim.footprints).ids) and k["facades"] >= 2 and k["windows"] >= 5
    assert f"{k['buildings']} buildings, {k['facades']} façades, {k['windows']} windows, {k['doors']} doors" in out
    assert "campaign 1 (mobile, mls_1.laz + trajectory_1.csv" in out
    assert path.stat().st_mode & 0o077 != 0  # not a private 0600 file


def test_reapplying_a_campaign_is_refused_and_the_map_stays_byte_identical(sim, map_copy) -> None:
    before = map_copy.read_bytes()
    code, out, err = run("map", "update", map_copy, *campaign_args(sim, 1))
    one_line_error(code, err, str(map_copy), "campaign already applied: mls_1.laz + trajectory_1.csv is campaign 1")
    assert map_copy.read_bytes() == before
    assert sorted(p.name for p in map_copy.parent.iterdir()) == ["city.lmap", "city.lmap.lock"]


def test_show_lists_buildings_facades_and_elements(map1) -> None:
    path = map1[0]
    with MapStore.open(path) as store:
        m = store.load()
    code, out, err = run("map", "show", path)
    assert code == 0, err
    assert "as of campaign 1, WGS 84 / UTM zone 32N" in out
    for bid, building in m.buildings.items():
        facade = building.facades[0]
        assert f"{facade.frame.offset:.3f}" in out and f"{facade.sigma * 100:.2f}" in out
    windows = [e for b in m.buildings.values() for f in b.facades for e in f.elements if e.kind.value == "window"]
    assert f"{windows[0].uncertainty:.3f}" in out and "∞" in out
    bid = next(iter(m.buildings))
    code, out, err = run("map", "show", path, "--building", bid)
    assert code == 0 and all(f"│ {other} " not in out for other in m.buildings if other != bid)
    one_line_error(*run("map", "show", path, "--building", "nope")[::2], "no building 'nope' in this map")
    one_line_error(*run("map", "show", path, "--as-of", "7")[::2], "no campaign 7 in this map (campaigns: 1)")


def test_history_lists_the_campaign_and_its_changes(map1) -> None:
    code, out, err = run("map", "history", map1[0])
    assert code == 0, err
    assert "1 campaign(s)" in out and "mls_1.laz + trajectory_1.csv" in out
    with MapStore.open(map1[0]) as store:
        [(_, changes)] = store.history()
    assert f"buildings +{changes['buildings']['added']} ~0 -0" in out


def test_export_writes_valid_cityjson_with_the_map_content(map1, tmp_path) -> None:
    out_file = tmp_path / "x.city.json"
    code, out, err = run("map", "export", map1[0], "-o", out_file)
    assert code == 0, err
    doc = json.loads(out_file.read_text())
    assert validate_cityjson(doc) == []
    with MapStore.open(map1[0]) as store:
        m = store.load()
    k = count_map(m)
    kinds = [s["type"] for o in doc["CityObjects"].values() for g in o.get("geometry", [])
             for s in g.get("semantics", {}).get("surfaces", [])]
    assert set(doc["CityObjects"]) == set(m.buildings)
    assert (kinds.count("Window"), kinds.count("Door")) == (k["windows"], k["doors"])
    assert f"{k['windows']} windows" in out


def test_render_writes_one_png_per_facade(map1, tmp_path) -> None:
    code, out, err = run("map", "render", map1[0], "-o", tmp_path / "png", "--width", "500")
    assert code == 0, err
    with MapStore.open(map1[0]) as store:
        m = store.load()
    facades = {f"{bid}_facade{f.facade_id:02d}.png": f for bid, b in m.buildings.items() for f in b.facades}
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == sorted([*facades, MARKER])
    assert read_marker(tmp_path / "png")["written"] == sorted(facades)  # the folder is ours: a rerender replaces
    for name, facade in facades.items():
        assert Image.open(tmp_path / "png" / name).size == facade_image_size(facade, 500)


def test_second_campaign_refines_the_map_and_as_of_exports_the_first(sim, map1, map_copy, tmp_path) -> None:
    first = tmp_path / "first.city.json"
    assert run("map", "export", map1[0], "-o", first)[0] == 0
    # --json: one object on stdout, nothing else; -v: notes on stderr
    code, out, err = run("-v", "map", "update", map_copy, *campaign_args(sim, 2), "--json")
    assert code == 0, err
    update = json.loads(out)
    assert out.count("\n") == 1
    assert f"INFO: {map_copy}: campaign 2 (mls_2.laz + trajectory_2.csv) committed" in err
    with MapStore.open(map_copy) as store:
        assert [(c.campaign_id, c.kind) for c in store.campaigns()] == [(1, "mobile"), (2, "mobile")]
        after = store.load()
        history = store.history()
    assert any(2 in f.campaigns for b in after.buildings.values() for f in b.facades)
    assert update["campaign"]["campaign_id"] == 2 and update["campaign"]["kind"] == "mobile"
    assert update["counts"]["buildings"] == count_map(after)["buildings"]
    assert update["counts"]["windows"] == count_map(after)["windows"]
    assert update["changes"] == history[-1][1]
    code, out, err = run("map", "history", map_copy)
    assert code == 0 and "2 campaign(s)" in out and "mls_2.laz + trajectory_2.csv" in out
    code, out, err = run("map", "history", map_copy, "--json")
    campaigns = json.loads(out)["campaigns"]
    assert [(c["campaign_id"], c["kind"]) for c in campaigns] == [(1, "mobile"), (2, "mobile")]
    assert campaigns[1]["changes"] == update["changes"]
    again = tmp_path / "again.city.json"
    assert run("map", "export", map_copy, "-o", again, "--as-of", "1")[0] == 0
    assert again.read_bytes() == first.read_bytes()  # the map as it was after campaign 1, exactly
    assert run("map", "show", map_copy, "--as-of", "1")[0] == 0


def test_aerial_update_adds_roof_planes_to_the_maps_buildings(sim, map_copy, tmp_path, monkeypatch) -> None:
    import lidarmap.map.refine

    seen = {}
    real = lidarmap.map.refine.add_aerial

    def spy(stored, cloud, footprints, params, campaign_id, seed):
        seen.update(ids=list(footprints.ids), n=len(cloud), campaign_id=campaign_id, seed=seed)
        return real(stored, cloud, footprints, params, campaign_id, seed)

    monkeypatch.setattr(lidarmap.map.refine, "add_aerial", spy)
    code, out, err = run("map", "update", map_copy, "--aerial", sim.als, "--seed", "4")
    assert code == 0, err
    with MapStore.open(map_copy) as store:
        m = store.load()
        campaign = store.campaigns()[-1]
    # without --footprints the map's own buildings are the footprints
    assert seen == {"ids": list(m.buildings), "n": sim.als_points, "campaign_id": 2, "seed": 4}
    assert (campaign.kind, campaign.source, campaign.fingerprint) == ("aerial", "als.laz", campaign_fingerprint(sim.als))
    roofs = count_map(m)["roofs"]
    assert roofs >= 2 and campaign.summary["roofs"] == roofs and f"{roofs} roof planes" in out
    assert run("map", "export", map_copy, "-o", tmp_path / "r.city.json")[0] == 0
    doc = json.loads((tmp_path / "r.city.json").read_text())
    kinds = [s["type"] for o in doc["CityObjects"].values() for g in o.get("geometry", []) if g["lod"] == "2"
             for s in g.get("semantics", {}).get("surfaces", [])]  # LoD 3 (with openings) repeats the roofs
    assert validate_cityjson(doc) == [] and kinds.count("RoofSurface") == roofs
    before = map_copy.read_bytes()
    one_line_error(*run("map", "update", map_copy, "--aerial", sim.als)[::2], "campaign already applied: als.laz")
    assert map_copy.read_bytes() == before


def test_a_second_process_updating_the_map_is_refused(sim, map_copy, tmp_path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys; from lidarmap.map.store import writer_lock\n"
        "with writer_lock(sys.argv[1]):\n    print('locked', flush=True); sys.stdin.readline()"), str(map_copy)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = map_copy.read_bytes()
        code, out, err = run("map", "update", map_copy, *campaign_args(sim, 2))
        one_line_error(code, err, "another process is updating this map")
        assert code == 3 and map_copy.read_bytes() == before
    finally:
        holder.communicate("\n", timeout=30)


# ----------------------------------------------------------------------------------------------------------------------
# Bad inputs: one line naming the file, non-zero exit, no traceback, map untouched


def _shifted_trajectory(sim, tmp_path: Path) -> Path:
    lines = sim.trajectories[0].read_text().splitlines()
    out = tmp_path / "late.csv"
    out.write_text("\n".join([lines[0]] + [",".join([repr(float(r.split(",")[0]) + 1e5)] + r.split(",")[1:])
                                           for r in lines[1:]]) + "\n")
    return out


def _far_footprints(sim, tmp_path: Path) -> Path:
    doc = json.loads(sim.footprints.read_text())
    for feature in doc["features"]:
        feature["geometry"]["coordinates"] = [[[x + 0.5, y] for x, y in ring]
                                              for ring in feature["geometry"]["coordinates"]]
    out = tmp_path / "far.geojson"
    out.write_text(json.dumps(doc))
    return out


def _footprint_where_nothing_was_seen(sim, tmp_path: Path) -> Path:
    """One footprint 1 m square inside the box of campaign 2's points, at the spot farthest from every point."""
    import pyproj
    from scipy.spatial import cKDTree

    from lidarmap.io.las import read_las

    cloud = read_las(sim.mls[1])
    xy = cloud.xyz[:, :2]
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(x0 + 1, x1 - 1, 60), np.linspace(y0 + 1, y1 - 1, 60))
    spots = np.column_stack([gx.ravel(), gy.ravel()])
    gap, _ = cKDTree(xy).query(spots)
    x, y = spots[np.argmax(gap)]
    assert gap.max() > 4.0  # no point, building or other, within 4 m of it
    to_lonlat = pyproj.Transformer.from_crs(cloud.crs, "EPSG:4326", always_xy=True)
    ring = [to_lonlat.transform(x + dx, y + dy) for dx, dy in ((-.5, -.5), (.5, -.5), (.5, .5), (-.5, .5), (-.5, -.5))]
    doc = json.loads(sim.footprints.read_text())
    doc["features"] = doc["features"][:1]
    doc["features"][0]["geometry"]["coordinates"] = [[list(p) for p in ring]]
    out = tmp_path / "empty.geojson"
    out.write_text(json.dumps(doc))
    return out


def test_a_campaign_that_saw_none_of_the_mapped_buildings_changes_no_building(sim, map_copy, tmp_path) -> None:
    """Issue 18 round 37: within the box of a campaign's points, footprints none of whose buildings it saw (a street
    of unmapped houses) are no input error: a warning, the campaign recorded, no building changed. Footprints away
    from the points stay an error ("far footprints" above)."""
    street = _footprint_where_nothing_was_seen(sim, tmp_path)
    with MapStore.open(map_copy) as store:
        before = store.load()
    code, out, err = run("map", "update", map_copy, *_args(sim, ["--footprints", street, "--points", sim.mls[1],
                                                                 "--trajectory", sim.trajectories[1]]))
    assert code == 0, err
    assert "saw none of the mapped buildings; no building changes" in err + out
    with MapStore.open(map_copy) as store:
        assert [c.campaign_id for c in store.campaigns()] == [1, 2]
        after = store.load()
    assert count_map(after) == count_map(before) and set(after.buildings) == set(before.buildings)


def _corrupt_laz(sim, tmp_path: Path) -> Path:
    """64 kB of the compressed point data overwritten (a few kB may only hit an attribute layer LAZ cannot check)."""
    data = bytearray(sim.mls[0].read_bytes())
    start = len(data) // 3
    stop = start + 65536
    data[start:stop] = bytes(np.random.default_rng(0).integers(0, 256, stop - start, dtype=np.uint8))
    out = tmp_path / "corrupt.laz"
    out.write_bytes(bytes(data))
    return out


def _xyz_without_time(sim, tmp_path: Path) -> Path:
    """The campaign's first points as x y z text: a trajectory file cannot place them (no GPS time)."""
    from lidarmap.io.las import iter_las

    xyz = next(iter_las(sim.mls[0], chunk_size=1000)).xyz
    out = tmp_path / "plain.xyz"
    np.savetxt(out, xyz, fmt="%.3f")
    return out


def _bad_config(sim, tmp_path: Path) -> Path:
    out = tmp_path / "cfg.toml"
    out.write_text("[facade]\nbogus = 1\n")
    return out


BAD = {
    "gps times": (lambda s, t: ["--trajectory", _shifted_trajectory(s, t)], "late.csv", "lie outside the trajectory"),
    "far footprints": (lambda s, t: ["--footprints", _far_footprints(s, t)], "far.geojson",
                       "footprints do not overlap the points of mls_1.laz"),
    "corrupt laz": (lambda s, t: ["--points", _corrupt_laz(s, t)], "corrupt.laz", "corrupt"),
    "unknown option": (lambda s, t: ["--bogus"], "No such option: --bogus", "lidarmap map update --help"),
    "config": (lambda s, t: ["--config", _bad_config(s, t)], "cfg.toml", "unknown option 'bogus'"),
    "trajectory without gps time": (lambda s, t: ["--points", _xyz_without_time(s, t), "--crs", "EPSG:32632"],
                                    "plain.xyz", "the points have no GPS time"),
}


def _args(sim, override: list) -> list:
    args = campaign_args(sim, 1)
    for flag, value in zip(override[::2], override[1::2] + [None] * (len(override) % 2)):
        if flag in args:
            i = args.index(flag)
            args[i:i + 2] = [] if value is None else [flag, value]
        else:
            args += [flag] if value is None else [flag, value]
    return args


@pytest.mark.parametrize("case", list(BAD))
def test_bad_inputs_on_a_new_map_create_nothing(sim, tmp_path, case) -> None:
    make, *needles = BAD[case]
    path = tmp_path / "new.lmap"
    code, out, err = run("map", "update", path, *_args(sim, make(sim, tmp_path)))
    one_line_error(code, err, *needles)
    assert not path.exists() and not (tmp_path / "new.lmap.lock").exists()  # nothing left behind


@pytest.mark.parametrize("case", ["gps times", "corrupt laz"])
def test_bad_inputs_leave_an_existing_map_byte_identical(sim, map_copy, tmp_path, case) -> None:
    make, *needles = BAD[case]
    before = map_copy.read_bytes()
    code, out, err = run("map", "update", map_copy, *_args(sim, make(sim, tmp_path)))
    one_line_error(code, err, *needles)
    assert map_copy.read_bytes() == before


def test_commands_on_a_file_that_is_not_a_map(sim) -> None:
    for command in (["show"], ["history"], ["export", "-o", "x.json"], ["render", "-o", "renders"]):
        one_line_error(*run("map", command[0], sim.footprints, *command[1:])[::2], "footprints.geojson",
                       "not a lidarmap map (not an SQLite database)")


# ---------------------------------------------------------------- --json: one object on stdout, nothing else
def test_show_as_json(map1) -> None:
    code, out, err = run("map", "show", map1[0], "--json")
    assert code == 0, err
    shown = json.loads(out)
    with MapStore.open(map1[0]) as store:
        first = store.load()
    assert shown["state"] == "as of campaign 1"
    assert [b["id"] for b in shown["buildings"]] == list(first.buildings)
    facades = [f for b in shown["buildings"] for f in b["facades"]]
    assert len(facades) == count_map(first)["facades"]
    kinds = [e["kind"] for f in facades for e in f["elements"]]
    assert kinds.count("window") == count_map(first)["windows"]


def test_quiet_prints_nothing_but_errors(map1) -> None:
    code, out, err = run("-q", "map", "show", map1[0])
    assert code == 0 and out == "" and err == ""
    code, out, err = run("-q", "map", "show", map1[0], "--building", "nope")
    assert code == 2 and "no building 'nope' in this map" in err  # errors still show
    code, out, err = run("map", "show", map1[0])
    assert code == 0 and "façades" in out
