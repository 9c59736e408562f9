"""``simulate``: build the city, fly it, drive it, and write the data and the ground truth."""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon

from lidarmap.core import Trajectory
from lidarmap.errors import InputError
from lidarmap.io.footprints import write_geojson_wgs84
from lidarmap.io.las import write_las
from lidarmap.io.npz import write_npz
from lidarmap.io.trajectory import write_trajectory
from lidarmap.sim.aerial import scan_aerial
from lidarmap.sim.buildings import solid_triangles
from lidarmap.sim.city import Car, City
from lidarmap.sim.family import build_family_city
from lidarmap.sim.hard import CampaignSetup, Drift, Van, campaign_setup, gps_drift
from lidarmap.sim.mesh import KINDS
from lidarmap.sim.mobile import (
    Campaign,
    plan_campaign,
    profile_plane_normals,
    scan_campaign,
    sensor_path,
)
from lidarmap.sim.params import SimParams
from lidarmap.sim.plyout import write_points_ply
from lidarmap.sim.raycast import Tracer
from lidarmap.sim.scan import Scan
from lidarmap.sim.truth import FORMAT, VERSION, save_ply, solid_mesh, write_json
from lidarmap.sim.visibility import HitGrids, Observability, seen_grid, visible_fraction

#: ``progress(task, completed, total)`` is called as work advances (task: "city", "aerial", "mobile <i>", "truth").
Progress = Callable[[str, int, int], None]

#: Header comment of the truth meshes.
TRUTH_PLY_COMMENT = "lidarmap simulator truth, CRS coordinates"


@dataclasses.dataclass
class SimResult:
    """What ``simulate`` wrote, with point counts."""

    out_dir: Path
    als: Path
    als_points: int
    mls: list[Path]
    mls_points: list[int]
    trajectories: list[Path]
    footprints: Path
    truth_dir: Path
    seconds: float

    def files(self) -> list[Path]:
        return [self.als, *self.mls, *self.trajectories, self.footprints, self.truth_dir / "scene.json"]


def simulate(out_dir: str | Path, params: SimParams | None = None, progress: Progress | None = None) -> SimResult:
    """Simulate the scene of ``params`` (default :class:`SimParams`) into ``out_dir`` (created if needed)."""
    params = params or SimParams()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", out)
    (out / "truth" / "meshes").mkdir(parents=True, exist_ok=True)
    report = progress or (lambda task, done, total: None)
    started = time.perf_counter()

    report("city", 0, 1)
    city = build_family_city(params)
    report("city", 1, 1)

    als_doc = _aerial(city, params, out, report)
    fractions: dict[int, dict[str, dict[str, float]]] = {}
    campaign_docs = [_mobile(city, params, i, out, report, fractions) for i in range(1, params.campaigns + 1)]

    report("truth", 0, 1)
    footprints = _write_footprints(city, out / "footprints.geojson")
    _write_meshes(city, out / "truth" / "meshes")
    doc = _scene_doc(city, params, als_doc, campaign_docs, fractions)
    write_json(out / "truth" / "scene.json", doc)
    _remove_stale(out, params.campaigns, [b.id for b in city.buildings], params.mls_format)
    report("truth", 1, 1)
    return SimResult(out_dir=out, als=out / "als.laz", als_points=als_doc["points"],
                     mls=[out / c["file"] for c in campaign_docs], mls_points=[c["points"] for c in campaign_docs],
                     trajectories=[out / c["trajectory"] for c in campaign_docs], footprints=footprints,
                     truth_dir=out / "truth", seconds=time.perf_counter() - started)


#: Per-campaign and per-building outputs: files of an earlier, larger simulation in the same folder are removed.
_INDEXED = ("mls_{}.laz", "mls_{}.ply", "trajectory_{}.csv", "truth/mls_{}_labels.npz", "truth/visibility_{}.npz")


def _remove_stale(out: Path, campaigns: int, building_ids: list[int], mls_format: str = "laz") -> None:
    """Delete simulator outputs this run did not write (same names, other indices or the other point format), so
    the folder is consistent."""
    other = "mls_{}.ply" if mls_format == "laz" else "mls_{}.laz"
    wanted = {p.format(i) for p in _INDEXED if p != other for i in range(1, campaigns + 1)}
    wanted |= {f"truth/meshes/building_{i}.ply" for i in building_ids}
    for template in (*_INDEXED, "truth/meshes/building_{}.ply"):
        name = re.compile(re.escape(template).replace(r"\{\}", r"\d+"))
        for path in sorted(out.glob(template.format("*"))):
            relative = path.relative_to(out).as_posix()
            if name.fullmatch(relative) and relative not in wanted:
                path.unlink()


def _aerial(city: City, params: SimParams, out: Path, report: Progress) -> dict:
    rng = np.random.default_rng([params.seed, 2])
    t0 = 300000.0 + float(rng.integers(0, 100000))
    report("aerial", 0, 1)
    scan, strips, cars = scan_aerial(city, params, rng, t0)
    write_las(out / "als.laz", scan.to_cloud(city.frame, city.crs))
    _write_labels(out / "truth" / "als_labels.npz", scan)
    report("aerial", 1, 1)
    return {"file": "als.laz", "labels": "truth/als_labels.npz", "points": len(scan),
            "strips": [s.to_json(city.frame.offset) for s in strips], "cars": [_car_json(city, c) for c in cars]}


def _mobile(city: City, params: SimParams, index: int, out: Path, report: Progress,
            fractions: dict[int, dict[str, dict[str, float]]]) -> dict:
    """One campaign: scan, write LAZ/trajectory/labels, compute visibility truth; returns its scene.json entry.

    Hard family: the campaign scans with its own lane, speed, sensor height, rate and scanner heads
    (:func:`lidarmap.sim.hard.campaign_setup`), and its trajectory and points carry a smooth GPS drift.
    """
    task = f"mobile {index}"
    rng = np.random.default_rng([params.seed, 3, index])
    setup = campaign_setup(params, index) if params.family == "hard" else None
    scan_params = setup.params if setup else params
    campaign = plan_campaign(rng, index, scan_params, city)
    if setup:
        campaign.lane_offset = setup.lane_offset
    cars = city.draw_cars(rng)
    tracer = Tracer(city.scene(cars), seed=[params.seed, 6, index])
    path = sensor_path(city, campaign, scan_params)
    yaws = setup.yaws if setup else (params.mls_tilt,)
    done = [0]

    def on_chunk(n: int, total: int) -> None:
        done[0] += n
        report(task, done[0], total * len(yaws))

    hits = HitGrids(city.facades, params.visibility_cell)
    scans = [scan_campaign(campaign, dataclasses.replace(scan_params, mls_tilt=yaw), rng, tracer, path, on_chunk,
                           on_stops=lambda *chunk: hits.add(tracer.scene.facade_id, *chunk)) for yaw in yaws]
    scan = scans[0] if len(scans) == 1 else _by_time(Scan.concatenate(scans))
    drift = gps_drift(params, index, path.time[0], path.time[-1]) if setup else None
    suffix = "laz" if params.mls_format == "laz" else "ply"
    names = {"file": f"mls_{index}.{suffix}", "trajectory": f"trajectory_{index}.csv",
             "labels": f"truth/mls_{index}_labels.npz", "visibility": f"truth/visibility_{index}.npz"}
    cloud = scan.to_cloud(city.frame, city.crs, transform=_delivered(campaign, drift, scan.gps_time))
    if params.mls_format == "laz":
        write_las(out / names["file"], cloud)
    else:
        _write_mobile_ply(out / names["file"], cloud, city, campaign, path, params, drift)
    write_trajectory(out / names["trajectory"], _crs_trajectory(city, campaign, path, drift))
    _write_labels(out / names["labels"], scan)
    _visibility(city, params, tracer, path, hits, campaign, out / names["visibility"], fractions, yaws, setup)
    extra = {"setup": setup.to_json(), "gps_drift": drift.to_json()} if setup and drift else {}
    return {"id": index, **names, "points": len(scan), **campaign.to_json(),
            "cars": [_car_json(city, c) for c in cars], **extra}


def _by_time(scan: Scan) -> Scan:
    """Points of several scanner heads interleaved by GPS time, as one receiver's file would hold them."""
    return scan.take(np.argsort(scan.gps_time, kind="stable"))


def _write_mobile_ply(target: Path, cloud, city: City, campaign: Campaign, path, params: SimParams,
                      drift: Drift | None) -> None:
    """A campaign as a PLY file (``mls_format``): double coordinates, the LAS attributes as PLY properties, GPS
    time and the pulses' sensor origins (delivered like the points: misregistered, drifted) when asked."""
    columns = {"x": cloud.xyz[:, 0], "y": cloud.xyz[:, 1], "z": cloud.xyz[:, 2]}
    for name in ("intensity", "return_number", "number_of_returns", "classification", "red", "green", "blue"):
        columns[name] = cloud.attrs[name]
    gps_time = cloud.attrs["gps_time"]
    if params.mls_gps_time:
        columns["gps_time"] = gps_time
    if params.mls_origins:
        origins = _delivered(campaign, drift, gps_time)(city.frame.to_crs(path.at(gps_time)[0]))
        columns.update(x_origin=origins[:, 0], y_origin=origins[:, 1], z_origin=origins[:, 2])
    write_points_ply(target, columns, [f"crs EPSG:{city.crs.to_epsg()}", "lidarmap simulator mobile campaign"],
                     binary=params.mls_format == "ply")


def _delivered(campaign: Campaign, drift: Drift | None, gps_time: np.ndarray) -> Callable:
    """CRS points as delivered: misregistered, and drifted with the GPS at each point's time."""
    if drift is None:
        return campaign.misregister
    return lambda xyz: campaign.misregister(xyz) + drift.at(gps_time)


def _crs_trajectory(city: City, campaign: Campaign, path, drift: Drift | None = None) -> Trajectory:
    """The trajectory as delivered: CRS, misregistered (and drifted) like the points, yaw wrapped to [-pi, pi)."""
    xyz = _delivered(campaign, drift, path.time)(city.frame.to_crs(path.xyz))
    rpy = path.rpy.copy()
    yaw = rpy[:, 2] + math.radians(city.frame.rotation_deg + campaign.rotation_deg)
    rpy[:, 2] = (yaw + math.pi) % (2 * math.pi) - math.pi
    return Trajectory(time=path.time, xyz=xyz, rpy=rpy)


def _visibility(city: City, params: SimParams, tracer: Tracer, path, hits: HitGrids, campaign: Campaign,
                target: Path, fractions: dict, yaws: tuple[float, ...], setup: CampaignSetup | None) -> None:
    """Write the campaign's seen/hit grids and record each element's visible fractions.

    Hard family: seen by any scanner head, and only where observable (incidence and sample spacing, see
    :class:`lidarmap.sim.visibility.Observability`).
    """
    cell = params.visibility_cell
    rule = Observability()
    if setup is not None:
        rule = Observability(max_incidence=params.visibility_max_incidence, max_spacing=params.visibility_max_spacing,
                             angular_step=setup.params.mls_angular_step)
    facades = city.facades
    arrays: dict[str, np.ndarray] = {"facade_ids": np.array([f.id for f in facades], np.int32),
                                     "cell_size": np.array(cell)}
    for f in facades:
        per_head = [seen_grid(tracer, f, path.xyz, profile_plane_normals(path, yaw), cell, params.mls_max_range,
                              rule) for yaw in yaws]
        seen = np.logical_or.reduce([g[0] for g in per_head])
        wall_seen = np.logical_or.reduce([g[1] for g in per_head])
        arrays[f"seen_{f.id}"] = seen
        arrays[f"wall_seen_{f.id}"] = wall_seen
        arrays[f"hit_{f.id}"] = hits.grids[f.id]
        for e in f.elements:
            entry = fractions.setdefault(e.id, {"visible_fraction": {}, "hit_fraction": {}})
            # openings behind a balcony's parapet are hidden by it; the structure itself is seen
            grid = seen if e.kind == "structure" else wall_seen
            entry["visible_fraction"][str(campaign.id)] = visible_fraction(grid, e.rect, cell)
            entry["hit_fraction"][str(campaign.id)] = visible_fraction(hits.grids[f.id], e.rect, cell)
    write_npz(target, arrays)


def _write_labels(path: Path, scan: Scan) -> None:
    t = scan.truth
    write_npz(path, {"classification": t["classification"].astype(np.uint8),
                     "building_id": t["building_id"].astype(np.int32), "facade_id": t["facade_id"].astype(np.int32),
                     "element_id": t["element_id"].astype(np.int32), "kind": t["kind"].astype(np.uint8),
                     "kind_names": np.array(KINDS)})


def _write_footprints(city: City, path: Path) -> Path:
    polygons, props = [], []
    for b in city.buildings:
        ring = city.frame.to_crs(np.column_stack([b.ring, np.zeros(len(b.ring))]))[:, :2]
        polygons.append(Polygon(ring))
        height = b.planned_height if b.planned_height is not None else b.height
        props.append({"id": b.id, "height": float(height), "status": b.status})
    return write_geojson_wgs84(path, polygons, props, city.crs)


def _write_meshes(city: City, folder: Path) -> None:
    for b in city.buildings:
        mesh = solid_mesh(solid_triangles(b), city.frame)
        save_ply(folder / f"building_{b.id}.ply", mesh.vertices, mesh.faces, TRUTH_PLY_COMMENT)
    verts, faces = city.terrain.mesh()
    save_ply(folder / "terrain.ply", city.frame.to_crs(verts), faces, TRUTH_PLY_COMMENT)


# --- scene.json --------------------------------------------------------------------------------------------------

def _rotate(city: City, v: np.ndarray) -> np.ndarray:
    a = math.radians(city.frame.rotation_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def _pt(city: City, p: np.ndarray) -> list[float]:
    return [float(v) for v in city.frame.to_crs(np.asarray(p, dtype=np.float64).reshape(1, 3))[0]]


def _car_json(city: City, c: Car) -> dict:
    return {"centre": _pt(city, [c.x, c.y, c.ground_z]),
            "heading_deg": math.degrees(c.heading) + city.frame.rotation_deg,
            "length": c.length, "width": c.width, "height": c.height, "type": "van" if isinstance(c, Van) else "car"}


def _scene_doc(city: City, params: SimParams, als: dict, campaigns: list[dict], fractions: dict) -> dict:
    return {
        "format": FORMAT, "version": VERSION, "seed": params.seed, "family": params.family,
        "params": dataclasses.asdict(params),
        "crs": {"epsg": 32632, "wkt": city.crs.to_wkt()},
        "local_frame": {"offset": list(city.frame.offset), "rotation_deg": city.frame.rotation_deg,
                        "formula": "crs = Rz(rotation_deg) @ local + offset"},
        "terrain": {**city.terrain.to_json(), "frame": "local", "mesh": "truth/meshes/terrain.ply"},
        "kinds": list(KINDS), "classes": {"1": "other (cars)", "2": "ground", "5": "vegetation", "6": "building"},
        "visibility_cell": params.visibility_cell,
        "streets": [{"id": s.id, "axis": [_pt(city, [s.x0, s.y, 0.0])[:2], _pt(city, [s.x1, s.y, 0.0])[:2]]}
                    for s in city.streets],
        "buildings": [_building_json(city, b, fractions) for b in city.buildings],
        "trees": [{"position": _pt(city, [t.x, t.y, t.ground_z]), "trunk_height": t.trunk_height,
                   "trunk_radius": t.trunk_radius, "crown_radius": t.crown_radius,
                   "crown_half_height": t.crown_half_height} for t in city.trees],
        "als": als, "campaigns": campaigns,
    }


def _building_json(city: City, b, fractions: dict) -> dict:
    ring = city.frame.to_crs(np.column_stack([b.ring, np.zeros(len(b.ring))]))[:, :2]
    return {
        "id": b.id, "status": b.status, "shape": b.shape, "roof_type": b.roof_type,
        "footprint": [[float(x), float(y)] for x, y in ring], "base_z": b.base_z, "floor_z": b.floor_z,
        "eave_z": b.eave_z, "top_z": b.top_z, "height": b.height, "planned_height": b.planned_height,
        "ridge_edge": b.ridge_edge, "mesh": f"truth/meshes/building_{b.id}.ply",
        "facades": [_facade_json(city, f, i, fractions) for i, f in enumerate(b.facades)],
    }


def _facade_json(city: City, f, edge: int, fractions: dict) -> dict:
    u = _rotate(city, f.u)
    normal = np.cross(u, [0.0, 0.0, 1.0])
    origin = _pt(city, f.origin)
    return {
        "id": f.id, "building_id": f.building_id, "edge": edge, "origin": origin, "u": [float(v) for v in u],
        "normal": [float(v) for v in normal], "plane_offset": float(-normal @ np.array(origin)),
        "width": f.width, "t_bottom": f.t_bottom, "t_eave": f.t_eave, "t_top": f.t_top,
        "street_facing": f.street_facing,
        "elements": [_element_json(city, f, e, fractions) for e in f.elements],
    }


def _element_json(city: City, f, e, fractions: dict) -> dict:
    sdt = np.array([[e.s0, e.t0, e.depth], [e.s1, e.t0, e.depth], [e.s1, e.t1, e.depth], [e.s0, e.t1, e.depth]])
    corners = city.frame.to_crs(f.to_local(sdt))
    frac = fractions.get(e.id, {"visible_fraction": {}, "hit_fraction": {}})
    return {"id": e.id, "facade_id": e.facade_id, "kind": e.kind, "subtype": e.subtype,
            "rect": [e.s0, e.s1, e.t0, e.t1], "depth": e.depth, "has_interior": e.has_interior,
            "room": list(e.room) if e.room else None, "corners": corners.tolist(), **frac, **_hard_json(e)}


def _hard_json(e) -> dict:
    """Hard-family extras of an element: glazing or door style, a glass pane's return share, the frame."""
    if not e.glazing:
        return {}
    out = {"glazing": e.glazing}
    if e.glazing == "glass":
        out["return_fraction"] = e.return_fraction
    if e.frame is not None:
        out["frame"] = {"width": e.frame[0], "front_depth": e.frame[1]}
    return out
