"""Ground truth on disk: writing it (deterministically) and loading it back as dataclasses.

Formats are documented in docs/simulator.md. Everything is in the CRS (EPSG:32632) unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from pyproj import CRS
from shapely.geometry import Polygon, box

from lidarmap.errors import InputError
from lidarmap.facade.model import FacadeFrame
from lidarmap.frame import LocalFrame
from lidarmap.io.atomic import write_text_atomic
from lidarmap.sim.mesh import KINDS
from lidarmap.sim.terrain import Terrain

FORMAT = "lidarmap-sim-truth"
VERSION = 1


# --- writing ---------------------------------------------------------------------------------------------------

def solid_mesh(triangles_local: np.ndarray, frame: LocalFrame) -> trimesh.Trimesh:
    """Merge a triangle soup's shared corners (exact, in the local frame) and move the result to the CRS."""
    n = len(triangles_local)
    mesh = trimesh.Trimesh(vertices=triangles_local.reshape(-1, 3), faces=np.arange(3 * n).reshape(n, 3),
                           process=False)
    mesh.merge_vertices(digits_vertex=9)
    mesh.remove_unreferenced_vertices()
    return trimesh.Trimesh(vertices=frame.to_crs(mesh.vertices), faces=mesh.faces, process=False)


def dumps(doc: Any) -> str:
    """Deterministic JSON (insertion order, full float precision)."""
    return json.dumps(doc, indent=1, allow_nan=False) + "\n"


def write_json(path: Path, doc: Any) -> Path:
    return write_text_atomic(path, dumps(doc))


# --- loading ---------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class TruthElement:
    """A window, door or structure: rectangle [s0, s1] x [t0, t1] at depth d (façade coordinates)."""

    id: int
    facade_id: int
    kind: str  # "window" | "door" | "structure"
    subtype: str  # "window" | "door" | "balcony" | "pilaster"
    rect: tuple[float, float, float, float]
    depth: float
    has_interior: bool
    room: tuple[float, float, float, float, float] | None
    corners: np.ndarray  # (4, 3) CRS, the rectangle at its depth
    visible_fraction: dict[int, float]  # campaign id -> fraction of its cells seen
    hit_fraction: dict[int, float]  # campaign id -> fraction of its cells hit by actual pulses

    @property
    def polygon(self) -> Polygon:
        s0, s1, t0, t1 = self.rect
        return box(s0, t0, s1, t1)


@dataclasses.dataclass
class TruthFacade:
    """A building wall: origin o (CRS, bottom-left seen from outside at the lowest terrain along it), axis u."""

    id: int
    building_id: int
    edge: int  # index of the footprint edge (footprint[edge] -> footprint[edge + 1])
    origin: np.ndarray
    u: np.ndarray
    width: float
    t_bottom: float
    t_eave: float
    t_top: float
    street_facing: bool
    elements: list[TruthElement]

    @property
    def frame(self) -> FacadeFrame:
        return FacadeFrame(origin=self.origin, u=self.u)

    @property
    def normal(self) -> np.ndarray:
        return self.frame.normal

    def to_facade(self, xyz: np.ndarray) -> np.ndarray:
        return self.frame.to_facade(xyz)


@dataclasses.dataclass
class TruthBuilding:
    id: int
    status: str
    shape: str
    roof_type: str
    footprint: np.ndarray  # (N, 2) CRS, counter-clockwise, not closed
    base_z: float
    floor_z: float
    eave_z: float
    top_z: float
    height: float
    planned_height: float | None
    facades: list[TruthFacade]
    mesh_path: Path

    @property
    def polygon(self) -> Polygon:
        return Polygon(self.footprint)

    def mesh(self) -> trimesh.Trimesh:
        """The watertight solid (CRS coordinates, float64)."""
        return load_ply(self.mesh_path)


@dataclasses.dataclass
class TruthCampaign:
    id: int
    laz: Path
    trajectory: Path
    labels: Path
    visibility_path: Path
    points: int
    direction: int
    lane_offset: float
    speed: float
    translation: np.ndarray
    rotation_deg: float
    pivot: np.ndarray

    def register(self, xyz: np.ndarray) -> np.ndarray:
        """Move this campaign's file coordinates back onto the true geometry (undo the misregistration)."""
        a = -np.radians(self.rotation_deg)
        c, s = np.cos(a), np.sin(a)
        p = np.asarray(xyz, dtype=np.float64) - self.pivot - self.translation
        return np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]]) + self.pivot


@dataclasses.dataclass
class PointTruth:
    """Per-point truth aligned with a LAZ file's point order."""

    classification: np.ndarray
    building_id: np.ndarray
    facade_id: np.ndarray
    element_id: np.ndarray
    kind: np.ndarray
    kind_names: tuple[str, ...] = KINDS

    def __len__(self) -> int:
        return len(self.classification)

    def is_kind(self, name: str) -> np.ndarray:
        return self.kind == self.kind_names.index(name)


@dataclasses.dataclass
class SimTruth:
    """Everything ``simulate`` knows about the scene it scanned."""

    root: Path
    crs: CRS
    frame: LocalFrame
    params: dict
    buildings: list[TruthBuilding]
    campaigns: list[TruthCampaign]
    als: Path
    als_labels: Path
    doc: dict

    @property
    def facades(self) -> dict[int, TruthFacade]:
        return {f.id: f for b in self.buildings for f in b.facades}

    @property
    def elements(self) -> dict[int, TruthElement]:
        return {e.id: e for f in self.facades.values() for e in f.elements}

    def building(self, building_id: int) -> TruthBuilding:
        return next(b for b in self.buildings if b.id == building_id)

    def labels(self, name: str) -> PointTruth:
        """Per-point truth of ``"als"`` or ``"mls_<i>"``."""
        path = self.root / "truth" / f"{name}_labels.npz"
        if not path.exists():
            raise InputError("no such truth labels", path)
        with np.load(path) as data:
            return PointTruth(**{k: data[k] for k in ("classification", "building_id", "facade_id", "element_id",
                                                      "kind")}, kind_names=tuple(str(k) for k in data["kind_names"]))

    def visibility(self, campaign: int) -> dict[int, dict[str, np.ndarray]]:
        """Per façade id: ``{"seen": bool grid, "wall_seen": bool grid, "hit": bool grid}`` (rows t, columns s;
        :mod:`lidarmap.sim.visibility`). Truth written before ``wall_seen`` existed gives ``seen`` for it."""
        path = self.root / "truth" / f"visibility_{campaign}.npz"
        with np.load(path) as data:
            return {int(fid): {"seen": data[f"seen_{fid}"], "hit": data[f"hit_{fid}"],
                               "wall_seen": data[f"wall_seen_{fid}"] if f"wall_seen_{fid}" in data
                               else data[f"seen_{fid}"]} for fid in data["facade_ids"]}

    @property
    def visibility_cell(self) -> float:
        return float(self.doc["visibility_cell"])

    def terrain_height(self, xy: np.ndarray) -> np.ndarray:
        """True ground height (the terrain mesh) at CRS points (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        local = self.frame.to_local(np.column_stack([xy, np.zeros(len(xy))]))
        return Terrain.from_json(self.doc["terrain"]).height(local[:, :2])

    def terrain_mesh(self) -> trimesh.Trimesh:
        return load_ply(self.root / "truth" / "meshes" / "terrain.ply")


def save_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, comment: str) -> None:
    """Write a truth mesh: binary PLY, ``double`` vertices (CRS coordinates), triangles.

    The simulator keeps its own writer (the inverse of :func:`load_ply`) so that the truth never depends on the
    production code it judges.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    vertices = np.asarray(vertices, dtype="<f8").reshape(-1, 3)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {len(vertices)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    rows["n"], rows["idx"] = 3, faces
    Path(path).write_bytes(header.encode("ascii") + vertices.tobytes() + rows.tobytes())


def load_ply(path: Path) -> trimesh.Trimesh:
    """Read a truth mesh written by :func:`save_ply` (float64 vertices kept)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    n_v = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    n_f = int(next(line.split()[2] for line in header if line.startswith("element face")))
    vertices = np.frombuffer(data, dtype="<f8", count=3 * n_v, offset=end).reshape(n_v, 3)
    rows = np.frombuffer(data, dtype=[("n", "u1"), ("idx", "<i4", (3,))], count=n_f, offset=end + 24 * n_v)
    return trimesh.Trimesh(vertices=vertices.copy(), faces=rows["idx"].astype(np.int64), process=False)


def load_truth(out_dir: str | Path) -> SimTruth:
    """Load ``OUT_DIR/truth/scene.json`` (and locate the other truth files) written by ``simulate``."""
    root = Path(out_dir)
    path = root / "truth" / "scene.json"
    if not path.exists():
        raise InputError("no simulator truth here (truth/scene.json missing)", root)
    doc = json.loads(path.read_text(encoding="utf-8"))
    if doc.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} file", path)
    buildings = [_building(b, root) for b in doc["buildings"]]
    campaigns = [_campaign(c, root) for c in doc["campaigns"]]
    frame = LocalFrame(offset=tuple(doc["local_frame"]["offset"]), rotation_deg=doc["local_frame"]["rotation_deg"])
    return SimTruth(root=root, crs=CRS.from_wkt(doc["crs"]["wkt"]), frame=frame, params=doc["params"],
                    buildings=buildings, campaigns=campaigns, als=root / doc["als"]["file"],
                    als_labels=root / doc["als"]["labels"], doc=doc)


def _building(b: dict, root: Path) -> TruthBuilding:
    facades = [TruthFacade(id=f["id"], building_id=f["building_id"], edge=f["edge"], origin=np.array(f["origin"]),
                           u=np.array(f["u"]), width=f["width"], t_bottom=f["t_bottom"], t_eave=f["t_eave"],
                           t_top=f["t_top"], street_facing=f["street_facing"],
                           elements=[_element(e) for e in f["elements"]]) for f in b["facades"]]
    return TruthBuilding(id=b["id"], status=b["status"], shape=b["shape"], roof_type=b["roof_type"],
                         footprint=np.array(b["footprint"]), base_z=b["base_z"], floor_z=b["floor_z"],
                         eave_z=b["eave_z"], top_z=b["top_z"], height=b["height"], planned_height=b["planned_height"],
                         facades=facades, mesh_path=root / b["mesh"])


def _element(e: dict) -> TruthElement:
    return TruthElement(id=e["id"], facade_id=e["facade_id"], kind=e["kind"], subtype=e["subtype"],
                        rect=tuple(e["rect"]), depth=e["depth"], has_interior=e["has_interior"],
                        room=tuple(e["room"]) if e["room"] else None, corners=np.array(e["corners"]),
                        visible_fraction={int(k): v for k, v in e["visible_fraction"].items()},
                        hit_fraction={int(k): v for k, v in e["hit_fraction"].items()})


def _campaign(c: dict, root: Path) -> TruthCampaign:
    m = c["misregistration"]
    return TruthCampaign(id=c["id"], laz=root / c["file"], trajectory=root / c["trajectory"],
                         labels=root / c["labels"], visibility_path=root / c["visibility"], points=c["points"],
                         direction=c["direction"], lane_offset=c["lane_offset"], speed=c["speed"],
                         translation=np.array(m["translation"]), rotation_deg=m["rotation_deg"],
                         pivot=np.array(m["pivot"]))

