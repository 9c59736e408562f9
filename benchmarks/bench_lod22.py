"""LoD 2.2 as planar faces against the triangle soup, on the meshes of a finished ``lidarmap run``.

``python benchmarks/bench_lod22.py OUT [--limit N]`` reads ``OUT/buildings/*/mesh.ply`` (the mesh files do not
change: only their CityJSON representation does) and writes three representations of every building to a temporary
CityJSON file:

* baseline: one semantic surface per mesh triangle (what ``buildings.city.json`` held before issue 19);
* planar faces keeping the mesh's vertices (``[lod22] snap = false``, issue 19's first round): approximately planar;
* planar faces snapped (the default): vertices moved onto the planes of their faces (:mod:`lidarmap.export.snap`).

Prints one markdown section: surfaces per building (median, max, total), polygons, file size, export seconds,
``validate_cityjson`` problems, whether ``cjio ... export obj`` converts the file; read back from each file, the
planarity of every polygon (largest distance of its vertices to its own plane: median, p95, max, polygons beyond
1 cm, val3dity's default) and the closed solids (every edge of the solid used once each way); and the deviation of
the LoD 2.2 surface from the mesh (Chamfer: mean of the two directed mean distances, Hausdorff: the larger maximum;
2,000 samples each way per building, mean and max over buildings).
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

from lidarmap.aerial.eval import chamfer_hausdorff
from lidarmap.export import cityjson
from lidarmap.export.cityjson import AerialBuilding, write_aerial_cityjson
from lidarmap.export.geomcheck import plane_basis
from lidarmap.export.gltf import planar_faces_mesh
from lidarmap.export.planar import PlanarParams, planar_faces
from lidarmap.export.validate import validate_cityjson

#: val3dity's default planarity tolerance (m): a polygon's vertices within it of the polygon's plane.
PLANARITY_TOLERANCE = 0.01


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


def _export(buildings: list[AerialBuilding], path: Path, params: PlanarParams | None = None) -> tuple[float, dict]:
    params = params or PlanarParams()
    translate = np.floor(np.min([b.mesh_vertices.min(axis=0) for b in buildings], axis=0))
    tick = time.perf_counter()
    write_aerial_cityjson(path, buildings, "", translate, planar=params)
    return time.perf_counter() - tick, json.loads(path.read_text())


def _cjio_ok(path: Path) -> str:
    cjio = shutil.which("cjio")
    if cjio is None:
        return "cjio missing"
    proc = subprocess.run([cjio, str(path), "export", "obj", str(path.with_suffix(".obj"))], capture_output=True,
                          text=True, timeout=1800, check=False)
    return "yes" if proc.returncode == 0 and path.with_suffix(".obj").is_file() else "no: " + proc.stderr[-200:]


def _solids(doc: dict) -> list[list]:
    return [o["geometry"][-1]["boundaries"][0] for o in doc["CityObjects"].values() if o.get("geometry")]


def _planarity(doc: dict) -> np.ndarray:
    """Every polygon's largest vertex distance (m) to its own plane (Newell normal through the vertices' mean)."""
    vertices = np.asarray(doc["vertices"], dtype=np.float64) * doc["transform"]["scale"]
    out = []
    for shell in _solids(doc):
        for surface in shell:
            rings = [vertices[r] for r in surface]
            basis = plane_basis(rings[0])
            if basis is not None:
                out.append(float(np.max(np.abs((np.concatenate(rings) - basis[0]) @ basis[3]))))
    return np.asarray(out)


def _closed(doc: dict) -> int:
    """Solids in which every directed edge of the surfaces' rings is used once and its reverse once."""
    count = 0
    for shell in _solids(doc):
        edges: dict[tuple[int, int], int] = {}
        for surface in shell:
            for ring in surface:
                for a, b in zip(ring, ring[1:] + ring[:1]):
                    edges[(a, b)] = edges.get((a, b), 0) + 1
        count += all(n == 1 and edges.get((b, a)) == 1 for (a, b), n in edges.items())
    return count


def _row(name: str, doc: dict, seconds: float, path: Path, deviation: str) -> str:
    per = [len(o["geometry"][-1]["semantics"]["surfaces"]) for o in doc["CityObjects"].values() if o.get("geometry")]
    polygons = sum(len(shell) for shell in _solids(doc))
    flat = _planarity(doc)
    problems = validate_cityjson(doc)
    return (f"| {name} | {int(np.median(per))} | {max(per)} | {sum(per):,} | {polygons:,} | "
            f"{path.stat().st_size / 1e6:.1f} MB | {seconds:.1f} | {len(problems)} | {_cjio_ok(path)} | "
            f"{np.median(flat):.4f} / {np.percentile(flat, 95):.4f} / {flat.max():.4f} | "
            f"{int(np.sum(flat > PLANARITY_TOLERANCE)):,} | {_closed(doc)} of {len(per)} | {deviation} |")


def _deviation(buildings: list[AerialBuilding], params: PlanarParams) -> tuple[str, dict]:
    """Chamfer / Hausdorff of each building's LoD 2.2 surface against its mesh (mean and max over buildings), and
    the faces' statistics."""
    chamfer, hausdorff, faces, split, seconds = [], [], [], 0, 0.0
    for b in buildings:
        tick = time.perf_counter()
        found = planar_faces(b.mesh_vertices, b.mesh_faces, params)
        seconds += time.perf_counter() - tick
        faces.append(len(found))
        split += sum(f.split for f in found)
        d = chamfer_hausdorff(planar_faces_mesh(found), trimesh.Trimesh(b.mesh_vertices, b.mesh_faces, process=False),
                              n_samples=2000)
        chamfer.append(d["chamfer"])
        hausdorff.append(d["hausdorff"])
    text = (f"Chamfer {np.mean(chamfer):.3f} (max {np.max(chamfer):.3f}), Hausdorff {np.mean(hausdorff):.2f} "
            f"(max {np.max(hausdorff):.2f})")
    return text, {"faces": faces, "split": split, "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="output folder of a finished lidarmap run")
    parser.add_argument("--limit", type=int, default=None, help="only the first N buildings")
    args = parser.parse_args()
    buildings = _buildings(args.run, args.limit)
    triangles = sum(len(b.mesh_faces) for b in buildings)
    loose, snapped = PlanarParams(snap=False), PlanarParams()
    loose_dev, loose_stats = _deviation(buildings, loose)
    snap_dev, snap_stats = _deviation(buildings, snapped)
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for name, params, dev in (("planar faces, mesh vertices (snap = false)", loose, loose_dev),
                                  ("planar faces, snapped (default)", snapped, snap_dev)):
            path = Path(tmp) / f"{params.snap}.city.json"
            seconds, doc = _export(buildings, path, params)
            rows.append(_row(name, doc, seconds, path, dev))
        original = cityjson._mesh_solid
        cityjson._mesh_solid = _soup_solid  # the baseline representation, same writer otherwise
        try:
            soup_s, soup_doc = _export(buildings, Path(tmp) / "soup.city.json")
        finally:
            cityjson._mesh_solid = original
        rows.insert(0, _row("triangle soup (baseline)", soup_doc, soup_s, Path(tmp) / "soup.city.json", "0 (the mesh)"))
        print(f"## LoD 2.2 planar faces ({platform.node()}, {time.strftime('%Y-%m-%d')}, {args.run})\n")
        print(f"{len(buildings)} buildings, {triangles:,} mesh triangles. Faces per building (median): "
              f"{int(np.median(loose_stats['faces']))} without snapping, {int(np.median(snap_stats['faces']))} snapped "
              f"({sum(snap_stats['faces']):,} faces, {snap_stats['split']} of them exported as triangles because "
              f"snapping left them non-planar or invalid); planar_faces seconds: {loose_stats['seconds']:.1f} "
              f"without snapping, {snap_stats['seconds']:.1f} snapped.\n")
        print("| representation | surfaces / building (median) | max | total | polygons | file | export s | "
              "validate problems | cjio OBJ | polygon planarity p50 / p95 / max m | polygons > 1 cm | closed solids "
              "| deviation from the mesh m |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for row in rows:
            print(row)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
