"""Files of a generated scene: LAZ per campaign, trajectory CSV, cadastre footprints (GeoJSON, WGS84), truth."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import laspy
import numpy as np
import pyproj
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from .scanners import drift, sensor_pose
from .scene import World

GPS_EPOCH = dt.datetime(1980, 1, 6)


def write_laz(path: Path, world: World, camp, pts: dict, cls: np.ndarray) -> int:
    """LAS 1.4 point format 6, scale 1 mm, CRS WKT, adjusted standard GPS time, points in delivery order."""
    xyz = world.to_crs(pts["xyz"]) + drift(camp.drift, pts["tau"])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([np.floor(world.origin[0] / 1000) * 1000, np.floor(world.origin[1] / 1000) * 1000, 0.0])
    header.add_crs(pyproj.CRS.from_epsg(world.epsg))
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.generating_software = "lidarmap.sim.independent"
    header.system_identifier = f"simulated {camp.kind}"
    header.creation_date = (GPS_EPOCH + dt.timedelta(seconds=camp.t0 + 1e9)).date()
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = pts["intensity"]
    las.return_number = pts["return_number"]
    las.number_of_returns = pts["number_of_returns"]
    las.gps_time = camp.t0 + pts["tau"]
    las.classification = cls
    las.point_source_id = np.full(len(xyz), camp.id, np.uint16)
    las.write(str(path))
    return len(xyz)


def write_trajectory(path: Path, world: World, camp) -> None:
    """Laser origin and vehicle attitude at traj_rate Hz over [first pulse - 0.5 s, last pulse + 0.5 s]."""
    tau = np.arange(-0.5, camp.motion.t_fire + 0.5 + 1e-9, 1.0 / camp.traj_rate)
    origin, _, rpy = sensor_pose(camp.motion, world.terrain, camp.scanner, tau)
    xyz = world.to_crs(origin) + drift(camp.drift, tau)
    yaw = np.angle(np.exp(1j * (rpy[:, 2] + world.azimuth)))
    rows = np.column_stack([camp.t0 + tau, xyz, rpy[:, 0], rpy[:, 1], yaw])
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("time,x,y,z,roll,pitch,yaw\n")
        for r in rows:
            fh.write(f"{r[0]:.6f},{r[1]:.4f},{r[2]:.4f},{r[3]:.4f},{r[4]:.7f},{r[5]:.7f},{r[6]:.7f}\n")


def cadastre(world: World) -> dict:
    """Per building: true footprint, the cadastre's (shifted 0-0.3 m and rotated up to 0.5 deg per block, so the
    corners of a terraced row stay shared), and the offset/rotation about the building's true centroid."""
    out = {}
    houses = world.street.houses
    for block in sorted({h.block for h in houses}):
        members = [h for h in houses if h.block == block]
        rng = np.random.default_rng([world.seed, 11, block])
        rot = np.radians(rng.uniform(-0.5, 0.5))
        ang = rng.uniform(0, 2 * np.pi)
        shift = rng.uniform(0.0, 0.3) * np.array([np.cos(ang), np.sin(ang)])
        pivot = np.mean(np.vstack([h.corners() for h in members]), axis=0)
        c, s = np.cos(rot), np.sin(rot)
        R = np.array([[c, -s], [s, c]])
        for h in members:
            true = h.corners()
            cad = (true - pivot) @ R.T + pivot + shift
            centroid = true.mean(0)
            offset = shift + (R - np.eye(2)) @ (centroid - pivot)
            out[h.id] = {"true": true, "cadastre": cad, "offset": offset, "rotation_deg": float(np.degrees(rot))}
    return out


def write_footprints(path: Path, world: World, cad: dict) -> None:
    to_wgs = pyproj.Transformer.from_crs(world.epsg, 4326, always_xy=True)
    feats = []
    for h in world.street.houses:
        xy = world.to_crs(np.column_stack([cad[h.id]["cadastre"], np.zeros(4)]))[:, :2]
        lon, lat = to_wgs.transform(xy[:, 0], xy[:, 1])
        poly = orient(Polygon(np.column_stack([lon, lat])), sign=1.0)  # RFC 7946: exterior counter-clockwise
        ring = [[round(float(a), 9), round(float(b), 9)] for a, b in poly.exterior.coords]
        props = {"id": h.id, "height": round(h.height, 2), "roof": h.roof}
        if h.roof == "gabled":
            props["ridge_height"] = round(h.height + (h.y_back - h.y_front) / 2 * np.tan(h.pitch), 2)
        feats.append({"type": "Feature", "properties": props, "geometry": {"type": "Polygon", "coordinates": [ring]}})
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}, indent=1), encoding="utf-8")


def write_json(path: Path, doc: dict) -> None:
    path.write_text(json.dumps(doc, indent=1, sort_keys=False), encoding="utf-8")
