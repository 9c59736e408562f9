"""Meshes on disk in CRS coordinates with double precision: binary PLY (``double`` x/y/z) and OBJ.

With a CRS, the PLY header says it (``comment crs EPSG:28992``, or the WKT1 when there is no EPSG code) and a ``.prj``
sidecar (same stem, ESRI WKT1 as Shapefiles carry it) tells GIS tools that read neither PLY comments nor OBJ.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from pyproj import CRS

from lidarmap.errors import InputError
from lidarmap.io.atomic import atomic_path, write_text_atomic

MESH_SUFFIXES = (".ply", ".obj")
DEFAULT_COMMENT = "lidarmap mesh, CRS coordinates"


def crs_comment(crs: CRS) -> str:
    """The PLY header line (without ``comment``) naming a CRS: ``crs EPSG:<code>``, else ``crs <WKT1>``."""
    epsg = crs.to_epsg()
    return f"crs EPSG:{epsg}" if epsg is not None else f"crs {crs.to_wkt('WKT1_GDAL') or crs.to_wkt()}"


def read_ply_crs(path: str | Path) -> CRS | None:
    """The CRS a PLY header names in its ``comment crs`` line (``None`` when it names none)."""
    with Path(path).open("rb") as fh:
        for raw in fh:
            line = raw.decode("ascii", "replace").strip()
            if line == "end_header":
                return None
            if line.startswith("comment crs "):
                return CRS.from_user_input(line.removeprefix("comment crs "))
    return None


def write_prj(mesh_path: str | Path, crs: CRS) -> Path:
    """The ``.prj`` sidecar of a mesh file (ESRI WKT1; GDAL WKT1 when ESRI's flavour cannot express the CRS)."""
    wkt = crs.to_wkt("WKT1_ESRI") or crs.to_wkt("WKT1_GDAL") or crs.to_wkt()
    return write_text_atomic(Path(mesh_path).with_suffix(".prj"), wkt)


def write_ply_arrays(path: str | Path, vertices: np.ndarray, faces: np.ndarray, vertex_colors: np.ndarray | None = None,
                     face_colors: np.ndarray | None = None, comment: str | None = None) -> Path:
    """Binary little-endian PLY: ``double`` x/y/z, optional ``uchar`` red/green/blue per vertex and per face.

    ``faces`` is (F, k) with one polygon size k (3 triangles, 4 quads).
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64)
    k = faces.shape[1]
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {line}" for line in (comment or DEFAULT_COMMENT).splitlines()]
    header += [f"element vertex {len(vertices)}", "property double x", "property double y", "property double z"]
    vertex_fields = [("xyz", "<f8", (3,))]
    if vertex_colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        vertex_fields.append(("rgb", "u1", (3,)))
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    face_fields = [("n", "u1"), ("idx", "<i4", (k,))]
    if face_colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        face_fields.append(("rgb", "u1", (3,)))
    header.append("end_header")
    vertex_rows = np.empty(len(vertices), dtype=vertex_fields)
    vertex_rows["xyz"] = vertices
    if vertex_colors is not None:
        vertex_rows["rgb"] = np.asarray(vertex_colors)[:, :3]
    face_rows = np.empty(len(faces), dtype=face_fields)
    face_rows["n"] = k
    face_rows["idx"] = faces
    if face_colors is not None:
        face_rows["rgb"] = np.asarray(face_colors)[:, :3]
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vertex_rows.tobytes())
        fh.write(face_rows.tobytes())
    return Path(path)


def _write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, vertex_colors: np.ndarray | None) -> Path:
    """Wavefront OBJ: ``v x y z [r g b]`` with the shortest text that reads back to the same float64, 1-based faces."""
    if vertex_colors is None:
        v_lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    else:
        c = np.asarray(vertex_colors)[:, :3] / 255.0
        v_lines = [f"v {x!r} {y!r} {z!r} {r:.4f} {g:.4f} {b:.4f}"
                   for (x, y, z), (r, g, b) in zip(vertices.tolist(), c.tolist())]
    f_lines = ["f " + " ".join(map(str, row)) for row in (np.asarray(faces) + 1).tolist()]
    with atomic_path(path) as tmp:
        tmp.write_text("# lidarmap mesh, CRS coordinates\n" + "\n".join(v_lines + f_lines) + "\n", encoding="ascii")
    return Path(path)


def write_mesh(path: str | Path, mesh: trimesh.Trimesh, crs: CRS | None = None) -> Path:
    """Write a mesh as ``.ply`` (binary, float64 vertices, vertex or face colours) or ``.obj`` (text, vertex
    colours only), atomically, by the file's suffix; with ``crs``, the PLY header names it and a ``.prj`` sidecar
    is written beside either."""
    suffix = Path(path).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(f"unknown mesh format {suffix or '(no suffix)'!r} (use {' or '.join(MESH_SUFFIXES)})", path)
    kind = mesh.visual.kind if hasattr(mesh.visual, "kind") else None
    vertex_colors = np.asarray(mesh.visual.vertex_colors) if kind == "vertex" else None
    if suffix == ".obj":
        _write_obj(path, np.asarray(mesh.vertices, dtype=np.float64), mesh.faces, vertex_colors)
    else:
        face_colors = np.asarray(mesh.visual.face_colors) if kind == "face" else None
        comment = DEFAULT_COMMENT if crs is None else f"{DEFAULT_COMMENT}\n{crs_comment(crs)}"
        write_ply_arrays(path, mesh.vertices, mesh.faces, vertex_colors=vertex_colors, face_colors=face_colors,
                         comment=comment)
    if crs is not None:
        write_prj(path, crs)
    return Path(path)
