"""Voxelization (lidarmap.aerial.voxel): majority labels, colours, exact CRS mapping, the naive baseline, files, viewers.

Synthetic points check the rules against brute force; a small simulated scene (2 buildings, no mobile campaign)
checks voxel IoU against the truth solids: the majority voxels of the true building points against the naive
MinecraftUBC baseline on the delivered classes (80 % of wall points are left unclassified there).
"""

from __future__ import annotations

import json
import struct
from collections import Counter

import numpy as np
import pytest
import shapely
import trimesh
from pyproj import CRS

from lidarmap.aerial.eval import voxel_scores, voxelize_mesh
from lidarmap.aerial.voxel import (
    VoxelParams,
    default_origin,
    fill_columns,
    voxelize,
    voxelize_naive,
)
from lidarmap.config import resolve
from lidarmap.core import VoxelGrid
from lidarmap.errors import ConfigError, InputError
from lidarmap.io.las import read_las
from lidarmap.io.voxels import read_voxels, write_vox, write_voxel_ply, write_voxels
from lidarmap.sim import SimParams, load_truth, simulate

UTM = np.array([500123.0, 5800456.0, 87.0])
CRS_UTM = CRS.from_epsg(32632)


def _brute_force(xyz, labels, rgb, size, origin):
    """Reference: a dict of voxel -> points, majority by Counter (ties -> smallest label), mean colour of those."""
    voxels: dict[tuple, list[int]] = {}
    for n, p in enumerate(xyz):
        key = tuple(int(v) for v in np.floor((p - origin) / size))
        voxels.setdefault(key, []).append(n)
    out = {}
    for key, members in voxels.items():
        counts = Counter(int(labels[m]) for m in members)
        best = max(counts.values())
        label = min(v for v, c in counts.items() if c == best)
        chosen = [m for m in members if labels[m] == label]
        out[key] = (label, len(members), np.rint(rgb[chosen].astype(float).mean(axis=0)).astype(np.uint8))
    return out


@pytest.mark.parametrize("n_labels", [4, 1000])  # few labels: dense vote table; many: the sparse path
def test_majority_label_and_colour_match_brute_force(n_labels):
    rng = np.random.default_rng(n_labels)
    xyz = UTM + rng.uniform(0, 4, (3000, 3))
    labels = rng.integers(0, n_labels, len(xyz))
    rgb = rng.integers(0, 256, (len(xyz), 3)).astype(np.uint8)
    grid = voxelize(xyz, labels, rgb, VoxelParams(size=0.5), crs=CRS_UTM)
    expected = _brute_force(xyz, labels, rgb, 0.5, grid.origin)
    assert len(grid) == len(expected)
    for ijk, label, count, colour in zip(grid.ijk, grid.label, grid.count, grid.rgb):
        e_label, e_count, e_colour = expected[tuple(ijk)]
        assert (label, count) == (e_label, e_count)
        np.testing.assert_array_equal(colour, e_colour)
    assert np.all(np.diff(grid.ijk[:, 0]) >= 0)  # sorted by i first
    assert CRS.from_wkt(grid.crs_wkt).to_epsg() == 32632


def test_majority_outvotes_speckle_and_ties_go_to_the_smaller_label():
    base = UTM + [0.5, 0.5, 0.5]
    pts = np.array([base, base + 0.1, base + 0.2, base + 0.3,  # voxel A: 3 x building (1), 1 x ground (0)
                    base + [1, 0, 0], base + [1.1, 0, 0],  # voxel B: tie 6 vs 2 -> 2
                    base + [2, 0, 0]])  # voxel C: a single point
    labels = np.array([1, 1, 1, 0, 6, 2, 5])
    rgb = np.array([[10, 20, 30], [20, 30, 40], [30, 40, 50], [255, 255, 255], [0, 0, 0], [100, 100, 100],
                    [7, 7, 7]], np.uint8)
    grid = voxelize(pts, labels, rgb)
    assert grid.label.tolist() == [1, 2, 5]
    assert grid.count.tolist() == [4, 2, 1]
    assert grid.rgb.tolist() == [[20, 30, 40], [100, 100, 100], [7, 7, 7]]  # the ground point does not tint A
    everything = voxelize(pts, labels, rgb, VoxelParams(colour_majority_only=False))
    assert everything.rgb[0].tolist() == [79, 86, 94]  # (10+20+30+255)/4 = 78.75, ...
    kept = voxelize(pts, labels, rgb, VoxelParams(min_points=2, keep_labels=(1, 6)))
    assert kept.label.tolist() == [1]
    assert voxelize(pts).label.tolist() == [1, 1, 1]  # no labels: every voxel is "building"


def test_voxels_map_back_to_the_crs_exactly():
    rng = np.random.default_rng(3)
    xyz = UTM + rng.uniform(0, 10, (2000, 3))
    xyz[:5] = UTM + [2.5, 2.5, 2.5]  # exactly on voxel faces (0.5 m voxels): the voxel above/right owns them
    grid = voxelize(xyz, params=VoxelParams(size=0.5))
    np.testing.assert_array_equal(grid.origin, np.floor(xyz.min(axis=0) / 0.5) * 0.5)
    np.testing.assert_array_equal(grid.origin % 0.5, 0.0)
    lo = grid.corners()
    owner = {tuple(v): n for n, v in enumerate(grid.ijk)}
    index = np.array([owner[tuple(v)] for v in np.floor((xyz - grid.origin) / 0.5).astype(int)])
    assert np.all((xyz >= lo[index]) & (xyz < lo[index] + 0.5))
    assert tuple(np.floor((xyz[0] - grid.origin) / 0.5).astype(int)) == tuple(((UTM + 2.5 - grid.origin) / 0.5))
    np.testing.assert_allclose(grid.centers(), lo + 0.25, rtol=0, atol=1e-9)
    shifted = voxelize(xyz, params=VoxelParams(size=0.5), origin=grid.origin - 1.0)  # a given origin is kept
    np.testing.assert_array_equal(shifted.ijk, grid.ijk + 2)


def test_naive_baseline_follows_minecraftubc():
    base = UTM + 0.25
    pts = np.array([base, base + 0.1, base + 0.2,  # voxel A: three class-6 points (+ a class-1 point, ignored)
                    base + 0.3,
                    base + [1, 0, 0],  # voxel B: a single class-6 point -> dropped (<= 1 point)
                    base + [2, 0, 0], base + [2.1, 0, 0]])  # voxel C: only unclassified points -> lost
    classes = np.array([6, 6, 6, 1, 6, 1, 1])
    rgb = np.array([[0, 0, 0], [30, 30, 30], [60, 60, 60], [255, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], np.uint8)
    grid = voxelize_naive(pts, classes, rgb)
    assert grid.ijk.tolist() == [[0, 0, 0]]
    assert grid.label.tolist() == [6] and grid.count.tolist() == [3] and grid.rgb.tolist() == [[30, 30, 30]]
    np.testing.assert_array_equal(grid.origin, default_origin(pts[classes == 6], 1.0))
    assert len(voxelize_naive(pts, np.ones(len(pts), int))) == 0  # nothing classified: nothing left


def test_params_validation_and_config():
    with pytest.raises(ConfigError, match="size must be a finite number > 0"):
        VoxelParams(size=0)
    with pytest.raises(ConfigError, match="min_points must be an integer >= 1"):
        VoxelParams(min_points=0)
    params = resolve(VoxelParams, {"voxel": {"size": 0.5, "keep_labels": [1, 6]}})
    assert params == VoxelParams(size=0.5, keep_labels=(1, 6))
    with pytest.raises(InputError, match="labels: expected shape"):
        voxelize(np.zeros((3, 3)), labels=np.zeros(2, int))
    with pytest.raises(InputError, match="coordinates must be finite"):
        voxelize(np.full((2, 3), np.nan))


def test_fill_columns_makes_a_solid_of_a_shell():
    # a 6 x 5 x 4 box shell without floor (walls + roof), roof voxel (2, 2) missing (no point fell there)
    i, j, k = np.meshgrid(np.arange(6), np.arange(5), np.arange(4), indexing="ij")
    box = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    wall = (box[:, 0] % 5 == 0) | (box[:, 1] % 4 == 0)
    roof = (box[:, 2] == 3) & ~((box[:, 0] == 2) & (box[:, 1] == 2))
    shell = box[wall | roof]
    grid = VoxelGrid(origin=UTM, size=0.5, ijk=shell, label=np.full(len(shell), 6), rgb=None,
                     count=np.ones(len(shell)))
    solid = fill_columns(grid)
    np.testing.assert_array_equal(solid.ijk, box)  # sorted (i, j, k) like the full box
    assert solid.count.sum() == len(shell) and np.all(solid.label == 6)
    # a notch in the outline one column wide is closed only with close_gaps
    notch = grid.subset(~((grid.ijk[:, 0] == 5) & (grid.ijk[:, 1] == 2)))
    assert len(fill_columns(notch)) == len(box) - 4
    assert len(fill_columns(notch, close_gaps=1)) == len(box)


def test_voxel_file_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(5)
    xyz = UTM + [0.123456789, 0.987654321, 0.5] + rng.uniform(0, 20, (500, 3))
    grid = voxelize(xyz, rng.integers(0, 3, 500), rng.integers(0, 256, (500, 3)).astype(np.uint8),
                    VoxelParams(size=0.3), crs=CRS_UTM)
    path = write_voxels(tmp_path / "b.voxels.npz", grid)
    back = read_voxels(path)
    assert back.origin.tobytes() == grid.origin.tobytes() and back.size == 0.3
    for name in ("ijk", "label", "count", "rgb"):
        np.testing.assert_array_equal(getattr(back, name), getattr(grid, name))
    assert CRS.from_wkt(back.crs_wkt) == CRS_UTM
    header = json.loads(str(np.load(path)["header"]))
    assert header["format"] == "lidarmap-voxels" and header["voxels"] == len(grid)
    no_colour = read_voxels(write_voxels(tmp_path / "plain.npz", voxelize(xyz)))
    assert no_colour.rgb is None and no_colour.crs_wkt is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.voxels.npz", "plain.npz"]  # no temporary files left


def test_read_voxels_reports_bad_files(tmp_path):
    with pytest.raises(InputError, match=r"missing\.npz: no such voxel file"):
        read_voxels(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"junk\.npz: not a lidarmap voxel file"):
        read_voxels(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", header=np.array(json.dumps({"format": "something"})))
    with pytest.raises(InputError, match=r"other\.npz: not a lidarmap voxel file \(format 'something'\)"):
        read_voxels(tmp_path / "other.npz")


def _parse_vox(data: bytes) -> dict:
    """Minimal .vox reader for the test: models (size, xyzi), transforms of the shape nodes, palette."""
    assert data[:4] == b"VOX " and struct.unpack("<i", data[4:8])[0] == 150 and data[8:12] == b"MAIN"
    pos, models, translations, palette = 20, [], [], None
    while pos < len(data):
        tag, n, m = data[pos:pos + 4], *struct.unpack("<ii", data[pos + 4:pos + 12])
        body = data[pos + 12:pos + 12 + n]
        if tag == b"SIZE":
            models.append({"size": struct.unpack("<iii", body)})
        elif tag == b"XYZI":
            count = struct.unpack("<i", body[:4])[0]
            models[-1]["xyzi"] = np.frombuffer(body[4:4 + 4 * count], np.uint8).reshape(count, 4)
        elif tag == b"nTRN" and b"_t" in body:
            translations.append(tuple(int(v) for v in body.split(b"_t")[1][4:].decode().split()))
        elif tag == b"RGBA":
            palette = np.frombuffer(body, np.uint8).reshape(256, 4)
        pos += 12 + n + m
    return {"models": models, "translations": translations, "palette": palette}


def test_write_vox_splits_large_grids_into_256_models(tmp_path):
    # an L of voxels 300 long in x and 20 in z: two models along x
    ijk = np.array([[i, 0, 0] for i in range(300)] + [[0, 1, k] for k in range(1, 21)])
    colours = np.where(ijk[:, :1] < 150, [[200, 10, 10]], [[10, 10, 200]]).astype(np.uint8)
    grid = VoxelGrid(origin=UTM, size=1.0, ijk=ijk + 7, label=np.ones(len(ijk)), rgb=colours,
                     count=np.ones(len(ijk)))
    vox = _parse_vox(write_vox(tmp_path / "b.vox", grid).read_bytes())
    assert len(vox["models"]) == 2 and all(max(m["size"]) <= 256 for m in vox["models"])
    placed = []
    for model, t in zip(vox["models"], vox["translations"]):
        size = np.array(model["size"])
        xyz = model["xyzi"][:, :3].astype(int)
        assert np.all(xyz < size)
        placed.append(xyz + np.array(t) - size // 2)  # MagicaVoxel: _t is the model's centre
    placed = np.concatenate(placed)
    assert sorted(map(tuple, placed)) == sorted(map(tuple, ijk))  # the models tile the grid exactly
    # colours: two exact palette entries, each voxel with its own
    by_position = {tuple(p): vox["palette"][c - 1, :3].tolist()
                   for m, t in zip(vox["models"], vox["translations"])
                   for p, c in zip(m["xyzi"][:, :3].astype(int) + np.array(t) - np.array(m["size"]) // 2,
                                   m["xyzi"][:, 3])}
    assert all(by_position[tuple(p)] == c.tolist() for p, c in zip(ijk, colours))


def test_vox_palette_quantises_many_colours(tmp_path):
    rng = np.random.default_rng(2)
    ijk = np.argwhere(np.ones((20, 20, 3), bool))
    colours = rng.integers(0, 256, (len(ijk), 3)).astype(np.uint8)
    grid = VoxelGrid(origin=UTM, size=1.0, ijk=ijk, label=np.ones(len(ijk)), rgb=colours, count=np.ones(len(ijk)))
    vox = _parse_vox(write_vox(tmp_path / "c.vox", grid).read_bytes())
    model, t = vox["models"][0], np.array(vox["translations"][0])
    used = np.unique(model["xyzi"][:, 3])
    assert used.min() >= 1 and len(used) <= 255
    position = model["xyzi"][:, :3].astype(int) + t - np.array(model["size"]) // 2
    order = np.lexsort((position[:, 2], position[:, 1], position[:, 0]))
    error = np.abs(vox["palette"][model["xyzi"][order, 3] - 1, :3].astype(int) - colours.astype(int))
    assert error.mean() < 40 and error.max() <= 255  # 255 colours for 1200 random ones: a coarse but fair palette
    with pytest.raises(InputError, match="no voxels to write"):
        write_vox(tmp_path / "empty.vox", grid.subset(np.zeros(len(grid), bool)))


def test_voxel_ply_has_double_cube_corners(tmp_path):
    grid = VoxelGrid(origin=UTM + 0.123456, size=0.25, ijk=[[0, 0, 0], [3, 1, 2]], label=[1, 6], rgb=None,
                     count=[3, 4], crs_wkt=CRS_UTM.to_wkt())
    path = write_voxel_ply(tmp_path / "cubes.ply", grid)
    assert b"property double x" in path.read_bytes()[:400]
    mesh = trimesh.load(path, process=False)
    assert len(mesh.vertices) == 16 and len(mesh.faces) == 24  # quads come back as 2 triangles each
    np.testing.assert_array_equal(mesh.vertices.min(axis=0), grid.origin)
    np.testing.assert_array_equal(mesh.vertices.max(axis=0), grid.origin + np.array([4, 2, 3]) * 0.25)
    assert mesh.split(only_watertight=True).__len__() == 2


# ----------------------------------------------------------------------------------------------------------------------
# Against the simulator's truth


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    simulate(out, SimParams(seed=4, buildings=2, campaigns=0))
    truth = load_truth(out)
    cloud = read_las(out / "als.laz")
    return truth, cloud, truth.labels("als")


def test_majority_voxels_of_true_points_beat_the_naive_baseline(scene):
    truth, cloud, labels = scene
    delivered = cloud.attrs["classification"]
    for building in truth.buildings:
        if building.status != "existing":
            continue
        mine = labels.building_id == building.id
        # every point within 2 m of the footprint, labelled by the truth (building / not): the majority keeps walls
        near = building.polygon.buffer(2.0)
        around = shapely.contains_xy(near, cloud.xyz[:, 0], cloud.xyz[:, 1])
        majority = voxelize(cloud.xyz[around], mine[around].astype(int), params=VoxelParams(keep_labels=(1,)))
        naive = voxelize_naive(cloud.xyz[mine], delivered[mine], origin=majority.origin)
        truth_voxels = voxelize_mesh(building.mesh(), 1.0, majority.origin, ground=truth.terrain_height)
        good, bad = voxel_scores(majority.ijk, truth_voxels), voxel_scores(naive.ijk, truth_voxels)
        assert good["precision"] > 0.95 and bad["precision"] > 0.95  # what each keeps is right ...
        assert good["iou"] > 0.45 and bad["iou"] < 0.25  # ... but the naive baseline loses the walls
        assert good["iou"] > 2.5 * bad["iou"]
