"""LoD 2.2 as planar faces against the triangle soup, on the meshes of a finished ``lidarmap run``.

``python benchmarks/bench_lod22.py OUT [--limit N]`` reads ``OUT/buildings/*/mesh.ply`` (the meshes do not change:
only their CityJSON representation does, so Chamfer/IoU of ``bench_aerial`` are unaffected) and writes both
representations of every building to a temporary CityJSON file:

* baseline: one semantic surface per mesh triangle (what ``buildings.city.json`` held before);
* planar: :func:`lidarmap.export.planar.planar_faces` (default ``[lod22]`` parameters).

Prints one markdown section: surfaces per building (median, max, total), planarity of the faces (largest distance of
a face's vertices to its plane: median, p95), file size, export seconds, ``validate_cityjson`` problems and whether
``cjio ... export obj`` converts the file.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from lidarmap.export import cityjson
from lidarmap.export.cityjson import AerialBuilding, write_aerial_cityjson
from lidarmap.export.planar import planar_faces
from lidarmap.export.validate import validate_cityjson


def _soup_solid(v: Any, vertices: np.ndarray, faces: np.ndarray, params: Any = None) -> dict | None:
    """The baseline: one semantic surface per triangle (Roof/Wall/Ground by its normal)."""
    tri = vertices[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = normals[:, 2] / np.maximum(np.linalg.norm(normals, axis=1), 1e-12)
    kinds = np.where(nz > 0.3, "RoofSurface", np.where(nz < -0.3, "GroundSurface", "WallSurface"))
    boundaries, semantics = [], []
    for t, kind in zip(tri, kinds.tolist()):
        for polygon in v.polygons([t]):
            semantics.append({"type": kind})
            boundaries.append(polygon)
    return {"type": "Solid", "lod": "2.2", "boundaries": [boundaries],
            "semantics": {"surfaces": semantics, "values": [list(range(len(semantics)))]}} if boundaries else None


def _buildings(run: Path, limit: int | None) -> list[AerialBuilding]:
    out = []
    for path in sorted((run / "buildings").glob("*/mesh.ply"))[:limit]:
        mesh = trimesh.load(path, process=False)
        out.append(AerialBuilding(id=path.parent.name, footprint=None, ground_z=float("nan"), height=float("nan"),
                                  mesh_vertices=np.asarray(mesh.vertices), mesh_faces=np.asarray(mesh.faces),
                                  attributes={}))
    return out


def _export(buildings: list[AerialBuilding], path: Path) -> tuple[float, dict]:
    translate = np.floor(np.min([b.mesh_vertices.min(axis=0) for b in buildings], axis=0))
    tick = time.perf_counter()
    write_aerial_cityjson(path, buildings, "", translate)
    return time.perf_counter() - tick, json.loads(path.read_text())


def _cjio_ok(path: Path) -> str:
    cjio = shutil.which("cjio")
    if cjio is None:
        return "cjio missing"
    proc = subprocess.run([cjio, str(path), "export", "obj", str(path.with_suffix(".obj"))], capture_output=True,
                          text=True, timeout=1800, check=False)
    return "yes" if proc.returncode == 0 and path.with_suffix(".obj").is_file() else "no: " + proc.stderr[-200:]


def _row(name: str, doc: dict, seconds: float, path: Path) -> str:
    per = [len(o["geometry"][0]["semantics"]["surfaces"]) for o in doc["CityObjects"].values() if o.get("geometry")]
    problems = validate_cityjson(doc)
    return (f"| {name} | {int(np.median(per))} | {max(per)} | {sum(per):,} | {path.stat().st_size / 1e6:.1f} MB | "
            f"{seconds:.1f} | {len(problems)} | {_cjio_ok(path)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="output folder of a finished lidarmap run")
    parser.add_argument("--limit", type=int, default=None, help="only the first N buildings")
    args = parser.parse_args()
    buildings = _buildings(args.run, args.limit)
    triangles = sum(len(b.mesh_faces) for b in buildings)
    tick = time.perf_counter()
    faces = [planar_faces(b.mesh_vertices, b.mesh_faces) for b in buildings]
    seconds_faces = time.perf_counter() - tick
    planarity = np.array([f.planarity for fs in faces for f in fs])
    roofs = [sum(f.kind == "RoofSurface" for f in fs) for fs in faces]
    with tempfile.TemporaryDirectory() as tmp:
        planar_s, planar_doc = _export(buildings, Path(tmp) / "planar.city.json")
        original = cityjson._mesh_solid
        cityjson._mesh_solid = _soup_solid  # the baseline representation, same writer otherwise
        try:
            soup_s, soup_doc = _export(buildings, Path(tmp) / "soup.city.json")
        finally:
            cityjson._mesh_solid = original
        print(f"## LoD 2.2 planar faces ({platform.node()}, {time.strftime('%Y-%m-%d')}, {args.run})\n")
        print(f"{len(buildings)} buildings, {triangles:,} mesh triangles; planar faces found in {seconds_faces:.1f} s; "
              f"roof faces per building median {int(np.median(roofs))}; face planarity (largest vertex distance to "
              f"the face's plane) median {np.median(planarity):.3f} m, p95 {np.percentile(planarity, 95):.3f} m, "
              f"max {planarity.max():.3f} m.\n")
        print("| representation | surfaces / building (median) | max | total | file | export s | validate problems "
              "| cjio OBJ |")
        print("|---|---|---|---|---|---|---|---|")
        print(_row("triangle soup (baseline)", soup_doc, soup_s, Path(tmp) / "soup.city.json"))
        print(_row("planar faces", planar_doc, planar_s, Path(tmp) / "planar.city.json"))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
