"""The map store: one SQLite file per map, with every campaign's changes kept as history.

Usage (what refinement needs)::

    store = MapStore.open("city.lmap")          # or MapStore.create(path, crs_wkt)
    current = store.load()                       # BuildingMap as of the latest campaign
    ...                                          # modify / fuse a new campaign into it
    current.campaigns.append(campaign)
    store.commit(current, campaign)              # ONE transaction: everything that changed, or nothing
    store.load(as_of=1)                          # the map exactly as it was after campaign 1

Design (docs/map.md has the full schema):

* **Versioned rows.** Every entity (building, façade, layer, element, evidence grid, roof plane) lives in a
  ``*_versions`` table whose rows carry ``valid_from`` (the campaign that wrote the row) and ``valid_to`` (the
  campaign that replaced or removed it; ``NULL`` while current). :meth:`MapStore.commit` compares the new map with
  the current rows by a SHA-256 ``digest`` of each row's content: unchanged rows are left alone, changed rows are
  closed (``valid_to``) and a new version inserted, vanished rows are closed. ``load(as_of=N)`` selects
  ``valid_from <= N AND (valid_to IS NULL OR valid_to > N)``, so any past state is reproduced exactly.
  Campaign ids therefore must increase from one commit to the next.
* **Identity tables** (``buildings``, ``facades``) give each building id / façade a stable integer that version rows
  reference with foreign keys (``PRAGMA foreign_keys = ON``); ``valid_from``/``valid_to`` reference ``campaigns``.
* **Exact values.** Floats are stored as SQLite 8-byte IEEE doubles in columns without type affinity (a ``REAL``
  column would turn -0.0 into 0); SQLite stores NaN as NULL, so a NULL float reads back as NaN. Polygons are WKB
  (float64 coordinates), evidence grids are zlib-compressed raw arrays with their dtype and shape.
* **Transactions and concurrency.** WAL journal, ``synchronous = FULL``. A commit runs inside ``BEGIN IMMEDIATE``:
  a process killed mid-commit leaves the previous map intact (SQLite rolls the partial transaction back on the next
  open). Writers are serialised by an advisory lock file (``<map>.lock``, ``flock``) and by SQLite's write lock with
  a short busy timeout: a second writer gets :class:`~lidarmap.errors.MapLockedError` instead of waiting or
  corrupting anything. Readers are never blocked (WAL snapshots) and see either the old or the new map.
* **Lost updates.** A commit is refused when the store holds campaigns that the map being committed does not list
  in ``BuildingMap.campaigns`` (another process committed after this one loaded).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import sqlite3
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS

from lidarmap._version import __version__
from lidarmap.errors import CRSError, InputError, LidarmapError, MapLockedError
from lidarmap.facade.model import (
    Element,
    ElementKind,
    Facade,
    FacadeEvidence,
    FacadeFrame,
    Layer,
)
from lidarmap.io.atomic import current_umask
from lidarmap.map.model import Building, BuildingMap, Campaign, RoofPlane

__all__ = ["MapStore", "SCHEMA_VERSION", "APPLICATION_ID", "ENTITIES", "campaign_fingerprint", "writer_lock",
           "lock_path_for", "damaged_map_error"]

#: Version of the table layout; a map written by a newer lidarmap (higher version) is refused.
SCHEMA_VERSION = 1
#: ``PRAGMA application_id`` of a lidarmap map ("LMAP").
APPLICATION_ID = 0x4C4D4150
#: Seconds a writer waits for SQLite's write lock before giving up with MapLockedError.
BUSY_TIMEOUT_S = 2.0
#: Entities whose changes are counted per campaign (``changes`` of :meth:`MapStore.history`).
ENTITIES = ("buildings", "facades", "layers", "elements", "evidence", "roofs")

_SQLITE_MAGIC = b"SQLite format 3\x00"
_ARRAY_MAGIC = b"LMA1"

_SCHEMA = """
CREATE TABLE schema_version (version INTEGER NOT NULL);
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE campaigns (
    campaign_id INTEGER PRIMARY KEY,
    kind TEXT NOT NULL,
    source TEXT NOT NULL,
    fingerprint TEXT NOT NULL UNIQUE,
    n_points INTEGER NOT NULL,
    created TEXT NOT NULL,
    summary TEXT NOT NULL,             -- JSON object (Campaign.summary)
    changes TEXT NOT NULL,             -- JSON {entity: {added, updated, removed}} written by the commit
    committed TEXT NOT NULL            -- UTC ISO time of the commit
);
CREATE TABLE buildings (id INTEGER PRIMARY KEY, building_id TEXT NOT NULL UNIQUE);
CREATE TABLE facades (
    id INTEGER PRIMARY KEY,
    building INTEGER NOT NULL REFERENCES buildings(id),
    facade_id INTEGER NOT NULL,
    UNIQUE (building, facade_id)
);
CREATE TABLE building_versions (
    id INTEGER PRIMARY KEY,
    building INTEGER NOT NULL REFERENCES buildings(id),
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    footprint BLOB NOT NULL,           -- WKB (Polygon or MultiPolygon, CRS)
    attributes TEXT NOT NULL           -- JSON object
);
CREATE TABLE facade_versions (
    id INTEGER PRIMARY KEY,
    facade INTEGER NOT NULL REFERENCES facades(id),
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    ox, oy, oz,                        -- frame origin (float64, no affinity)
    ux, uy, uz,                        -- frame axis u (float64)
    sigma,
    s0, s1, t0, t1,                    -- extent
    main_layer INTEGER,
    n_points INTEGER NOT NULL,
    footprint_edge INTEGER,
    campaigns TEXT NOT NULL            -- JSON list of campaign ids
);
CREATE TABLE layer_versions (
    id INTEGER PRIMARY KEY,
    facade INTEGER NOT NULL REFERENCES facades(id),
    layer_id INTEGER NOT NULL,
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    mu, sigma, weight,
    n_points INTEGER NOT NULL,
    campaigns TEXT NOT NULL
);
CREATE TABLE element_versions (
    id INTEGER PRIMARY KEY,
    facade INTEGER NOT NULL REFERENCES facades(id),
    element_id INTEGER NOT NULL,
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    kind TEXT NOT NULL,                -- ElementKind value
    polygon BLOB NOT NULL,             -- WKB in façade coordinates (s, t)
    layer_id INTEGER,
    uncertainty,                       -- epsilon; inf for unknown regions
    n_points INTEGER NOT NULL,
    campaigns TEXT NOT NULL
);
CREATE TABLE evidence_versions (
    id INTEGER PRIMARY KEY,
    facade INTEGER NOT NULL REFERENCES facades(id),
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    cell, s0, t0,
    window_votes BLOB NOT NULL,        -- zlib-compressed array with dtype/shape header
    object_votes BLOB NOT NULL,
    seen BLOB NOT NULL
);
CREATE TABLE roof_versions (
    id INTEGER PRIMARY KEY,
    building INTEGER NOT NULL REFERENCES buildings(id),
    plane_id INTEGER NOT NULL,
    valid_from INTEGER NOT NULL REFERENCES campaigns(campaign_id),
    valid_to INTEGER REFERENCES campaigns(campaign_id),
    digest BLOB NOT NULL,
    nx, ny, nz, "offset",
    outline BLOB NOT NULL,             -- WKB (xy, CRS)
    sigma,
    n_points INTEGER NOT NULL,
    campaigns TEXT NOT NULL
);
CREATE UNIQUE INDEX building_versions_current ON building_versions (building) WHERE valid_to IS NULL;
CREATE UNIQUE INDEX facade_versions_current ON facade_versions (facade) WHERE valid_to IS NULL;
CREATE UNIQUE INDEX layer_versions_current ON layer_versions (facade, layer_id) WHERE valid_to IS NULL;
CREATE UNIQUE INDEX element_versions_current ON element_versions (facade, element_id) WHERE valid_to IS NULL;
CREATE UNIQUE INDEX evidence_versions_current ON evidence_versions (facade) WHERE valid_to IS NULL;
CREATE UNIQUE INDEX roof_versions_current ON roof_versions (building, plane_id) WHERE valid_to IS NULL;
CREATE INDEX building_versions_from ON building_versions (valid_from);
CREATE INDEX facade_versions_from ON facade_versions (valid_from);
CREATE INDEX layer_versions_from ON layer_versions (valid_from);
CREATE INDEX element_versions_from ON element_versions (valid_from);
CREATE INDEX evidence_versions_from ON evidence_versions (valid_from);
CREATE INDEX roof_versions_from ON roof_versions (valid_from);
"""


# ----------------------------------------------------------------------------------------------------------------------
# Versioned tables


@dataclasses.dataclass(frozen=True)
class _Table:
    """A ``*_versions`` table: owned by a building or a façade, keyed within it, with data columns."""

    entity: str            # name in the change counts
    name: str              # SQL table
    owner: str             # "building" or "facade": the identity column
    key: tuple[str, ...]   # key columns within the owner
    cols: tuple[str, ...]  # data columns (in the order of the encoded value tuples)


_TABLES = (
    _Table("buildings", "building_versions", "building", (), ("footprint", "attributes")),
    _Table("facades", "facade_versions", "facade", (),
           ("ox", "oy", "oz", "ux", "uy", "uz", "sigma", "s0", "s1", "t0", "t1", "main_layer", "n_points",
            "footprint_edge", "campaigns")),
    _Table("layers", "layer_versions", "facade", ("layer_id",), ("mu", "sigma", "weight", "n_points", "campaigns")),
    _Table("elements", "element_versions", "facade", ("element_id",),
           ("kind", "polygon", "layer_id", "uncertainty", "n_points", "campaigns")),
    _Table("evidence", "evidence_versions", "facade", (),
           ("cell", "s0", "t0", "window_votes", "object_votes", "seen")),
    _Table("roofs", "roof_versions", "building", ("plane_id",),
           ("nx", "ny", "nz", "offset", "outline", "sigma", "n_points", "campaigns")),
)
_TABLE = {t.entity: t for t in _TABLES}


def _q(column: str) -> str:
    return f'"{column}"'


# ----------------------------------------------------------------------------------------------------------------------
# Encoding: model objects <-> row values (exact)


def _f(value: Any) -> float | None:
    """A float64 for a no-affinity column; NaN becomes NULL (SQLite cannot store NaN)."""
    value = float(value)
    return None if math.isnan(value) else value


def _unf(value: Any) -> float:
    return math.nan if value is None else float(value)


def _opt_int(value: Any) -> int | None:
    return None if value is None else int(value)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (set, frozenset, tuple)):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _dumps(value: Any, what: str) -> str:
    try:
        return json.dumps(value, default=_json_default, ensure_ascii=False)
    except (TypeError, ValueError) as exc:
        raise LidarmapError(f"cannot store {what}: {exc}") from None


def _ids(values: Any) -> str:
    return json.dumps([int(v) for v in (values or [])])


def _wkb(geom: Any, what: str) -> bytes:
    if geom is None or not hasattr(geom, "geom_type"):
        raise LidarmapError(f"cannot store {what}: not a shapely geometry ({type(geom).__name__})")
    dim = 3 if shapely.has_z(geom) else 2
    return shapely.to_wkb(geom, hex=False, output_dimension=dim, byte_order=1, include_srid=False)


def _from_wkb(blob: bytes) -> Any:
    return shapely.from_wkb(bytes(blob))


def encode_array(array: np.ndarray) -> bytes:
    """A numpy array as bytes: magic, header length, JSON header (dtype, shape), zlib-compressed raw data."""
    array = np.asarray(array)
    if array.dtype.hasobject:
        raise LidarmapError("cannot store an object array as evidence")
    header = json.dumps({"dtype": array.dtype.str, "shape": list(array.shape)}).encode()
    raw = np.ascontiguousarray(array).tobytes()
    return _ARRAY_MAGIC + struct.pack("<I", len(header)) + header + zlib.compress(raw, 6)


def decode_array(blob: bytes) -> np.ndarray:
    """Inverse of :func:`encode_array` (a writable array of the stored dtype and shape)."""
    blob = bytes(blob)
    if blob[:4] != _ARRAY_MAGIC:
        raise InputError("corrupt evidence array in map (bad magic)")
    (n,) = struct.unpack("<I", blob[4:8])
    header = json.loads(blob[8:8 + n])
    data = zlib.decompress(blob[8 + n:])
    return np.frombuffer(data, dtype=np.dtype(header["dtype"])).reshape(header["shape"]).copy()


def _digest(values: tuple) -> bytes:
    """SHA-256 of a row's values with exact float bits (so any change, even -0.0 vs 0.0, is seen)."""
    h = hashlib.sha256()
    for v in values:
        if v is None:
            h.update(b"N")
        elif isinstance(v, bool):
            h.update(b"B1" if v else b"B0")
        elif isinstance(v, int):
            s = str(v).encode()
            h.update(b"I" + struct.pack("<I", len(s)) + s)
        elif isinstance(v, float):
            h.update(b"F" + struct.pack("<d", v))
        elif isinstance(v, str):
            s = v.encode()
            h.update(b"S" + struct.pack("<Q", len(s)) + s)
        elif isinstance(v, (bytes, bytearray, memoryview)):
            b = bytes(v)
            h.update(b"X" + struct.pack("<Q", len(b)) + b)
        else:  # pragma: no cover - encoders only produce the types above
            raise TypeError(f"unexpected row value {type(v).__name__}")
    return h.digest()


def _encode_building(b: Building) -> tuple:
    return (_wkb(b.footprint, f"building {b.building_id!r} footprint"),
            _dumps(b.attributes or {}, f"building {b.building_id!r} attributes"))


def _encode_facade(f: Facade) -> tuple:
    o = np.asarray(f.frame.origin, dtype=np.float64).reshape(3)
    u = np.asarray(f.frame.u, dtype=np.float64).reshape(3)
    s0, s1, t0, t1 = (float(x) for x in f.extent)
    return (_f(o[0]), _f(o[1]), _f(o[2]), _f(u[0]), _f(u[1]), _f(u[2]), _f(f.sigma), _f(s0), _f(s1), _f(t0), _f(t1),
            _opt_int(f.main_layer), int(f.n_points), _opt_int(f.footprint_edge), _ids(f.campaigns))


def _encode_layer(layer: Layer) -> tuple:
    return (_f(layer.mu), _f(layer.sigma), _f(layer.weight), int(layer.n_points), _ids(layer.campaigns))


def _encode_element(e: Element, where: str) -> tuple:
    kind = ElementKind(e.kind).value
    return (kind, _wkb(e.polygon, f"{where} element {e.element_id} polygon"), _opt_int(e.layer_id),
            _f(e.uncertainty), int(e.n_points), _ids(e.campaigns))


def _encode_evidence(ev: FacadeEvidence, where: str) -> tuple:
    shapes = {np.asarray(a).shape for a in (ev.window_votes, ev.object_votes, ev.seen)}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise LidarmapError(f"cannot store {where} evidence: grids must be 2D and of one shape (got {sorted(shapes)})")
    return (_f(ev.cell), _f(ev.s0), _f(ev.t0), encode_array(ev.window_votes), encode_array(ev.object_votes),
            encode_array(ev.seen))


def _encode_roof(r: RoofPlane, where: str) -> tuple:
    n = np.asarray(r.normal, dtype=np.float64).reshape(3)
    return (_f(n[0]), _f(n[1]), _f(n[2]), _f(r.offset), _wkb(r.outline, f"{where} roof {r.plane_id} outline"),
            _f(r.sigma), int(r.n_points), _ids(r.campaigns))


def _unique(ids: list, what: str) -> None:
    seen: set = set()
    for i in ids:
        if i in seen:
            raise LidarmapError(f"cannot store the map: duplicate {what} {i!r}")
        seen.add(i)


def _encode_map(building_map: BuildingMap) -> dict[str, dict[tuple, tuple]]:
    """Rows of every versioned table: {entity: {key: values}} with keys (building_id, [facade_id,] [sub id])."""
    rows: dict[str, dict[tuple, tuple]] = {t.entity: {} for t in _TABLES}
    for map_key, b in building_map.buildings.items():
        bid = str(b.building_id)
        if str(map_key) != bid:
            raise LidarmapError(f"cannot store the map: buildings[{map_key!r}] holds building {bid!r}")
        rows["buildings"][(bid,)] = _encode_building(b)
        _unique([int(f.facade_id) for f in b.facades], f"façade id in building {bid!r}: façade")
        _unique([int(r.plane_id) for r in b.roofs], f"roof plane id in building {bid!r}: plane")
        for f in b.facades:
            fid = int(f.facade_id)
            where = f"building {bid!r} façade {fid}"
            rows["facades"][(bid, fid)] = _encode_facade(f)
            _unique([int(la.layer_id) for la in f.layers], f"layer id in {where}: layer")
            _unique([int(e.element_id) for e in f.elements], f"element id in {where}: element")
            for la in f.layers:
                rows["layers"][(bid, fid, int(la.layer_id))] = _encode_layer(la)
            for e in f.elements:
                rows["elements"][(bid, fid, int(e.element_id))] = _encode_element(e, where)
            if f.evidence is not None:
                rows["evidence"][(bid, fid)] = _encode_evidence(f.evidence, where)
        for r in b.roofs:
            rows["roofs"][(bid, int(r.plane_id))] = _encode_roof(r, f"building {bid!r}")
    return rows


def _campaign_from_row(row: sqlite3.Row) -> Campaign:
    return Campaign(campaign_id=int(row["campaign_id"]), kind=row["kind"], source=row["source"],
                    fingerprint=row["fingerprint"], n_points=int(row["n_points"]), created=row["created"],
                    summary=json.loads(row["summary"]))


# ----------------------------------------------------------------------------------------------------------------------
# Advisory writer lock


def lock_path_for(map_path: str | Path) -> Path:
    """The advisory lock file of a map: ``<map>.lock`` beside it (left in place; never delete it while in use)."""
    map_path = Path(map_path)
    return map_path.with_name(map_path.name + ".lock")


_held: dict[str, list] = {}  # resolved lock path -> [fd, depth]
_held_guard = threading.Lock()


def _acquire_lock_file(lock_path: Path, map_path: str | Path) -> int | None:
    """An exclusive ``flock`` on the lock file (its fd), ``None`` where no lock file can be made (read-only folder)."""
    import fcntl

    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return None  # read-only or missing folder: rely on SQLite's lock
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held = os.fstat(fd)
        current = os.stat(lock_path)
        # the file we locked may have been removed by its previous holder (see _release_lock_file) meanwhile
        stale = (held.st_dev, held.st_ino) != (current.st_dev, current.st_ino)
    except OSError:
        stale = True
    if stale:
        os.close(fd)
        raise MapLockedError(f"another process is updating this map (lock {lock_path.name} is held); "
                             "try again when it has finished", map_path)
    return fd


def _release_lock_file(fd: int, lock_path: Path, map_path: str | Path) -> None:
    """Unlock; the lock file goes too when there is no map (a first update that failed, or one given a file that is
    not a map, leaves nothing behind)."""
    import fcntl

    if not _is_sqlite_file(Path(map_path)):
        with contextlib.suppress(OSError):
            lock_path.unlink()  # while still locked: a process that opened it before sees it is stale
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)


def damaged_map_error(exc: BaseException | None, path: str | Path) -> InputError | None:
    """The one-line error naming the map for SQLite's "database disk image is malformed" (a damaged page is found
    only when it is read, and SQLite's message names no file); ``None`` for any other exception."""
    if isinstance(exc, sqlite3.DatabaseError) and not isinstance(exc, (sqlite3.OperationalError,
                                                                      sqlite3.IntegrityError)):
        return InputError(f"damaged map: {exc}; restore it from a backup", path)
    return None


def _is_sqlite_file(path: Path) -> bool:
    try:
        with path.open("rb") as fh:
            return fh.read(len(_SQLITE_MAGIC)) == _SQLITE_MAGIC
    except OSError:
        return False


@contextlib.contextmanager
def writer_lock(map_path: str | Path) -> Iterator[None]:
    """Hold the map's advisory writer lock (re-entrant in one process); MapLockedError at once if another holds it.

    ``lidarmap map update`` holds it for the whole update (reading, extraction, commit), so a second update of the
    same map is refused before it spends minutes computing. :meth:`MapStore.commit` takes it too. The lock file
    ``<map>.lock`` stays beside the map; it is removed on release only when the map does not exist (a failed first
    update). Where ``flock`` is unavailable (not POSIX) or the folder is read-only, only SQLite's own write lock
    protects the map.
    """
    try:
        import fcntl  # noqa: F401 - POSIX only
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    lock_path = lock_path_for(map_path)
    key = str(lock_path.resolve())
    with _held_guard:
        nested = key in _held
        if nested:
            _held[key][1] += 1
    if not nested:
        fd = _acquire_lock_file(lock_path, map_path)
        with _held_guard:
            _held[key] = [fd, 1]
    try:
        yield
    finally:
        with _held_guard:
            entry = _held[key]
            entry[1] -= 1
            release = entry[1] == 0
            if release:
                del _held[key]
        if release and entry[0] is not None:
            _release_lock_file(entry[0], lock_path, map_path)


def campaign_fingerprint(points_path: str | Path, trajectory_path: str | Path | None = None,
                         chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of the point file's bytes followed by the trajectory file's bytes: detects a re-applied campaign."""
    h = hashlib.sha256()
    for tag, path in (("points", points_path), ("trajectory", trajectory_path)):
        if path is None:
            continue
        h.update(tag.encode() + b"\0")
        try:
            with open(path, "rb") as fh:
                while block := fh.read(chunk):
                    h.update(block)
        except FileNotFoundError:
            raise InputError("file not found", path) from None
        h.update(b"\0")
    return h.hexdigest()


def _is_locked(exc: sqlite3.OperationalError) -> bool:
    text = str(exc).lower()
    return "locked" in text or "busy" in text


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _insert_version(cur: sqlite3.Cursor, table: _Table, owner_id: int, key: tuple, campaign_id: int, digest: bytes,
                    values: tuple) -> None:
    """Insert one version row (a separate function so that tests can interrupt a commit half-way)."""
    cols = (table.owner, *table.key, "valid_from", "digest", *table.cols)
    cur.execute(f"INSERT INTO {table.name} ({', '.join(_q(c) for c in cols)}) VALUES ({', '.join('?' * len(cols))})",
                (owner_id, *key, campaign_id, digest, *values))


# ----------------------------------------------------------------------------------------------------------------------
# The store


class MapStore:
    """A building map in one SQLite file. Create with :meth:`create`, open with :meth:`open`; close when done."""

    def __init__(self, path: Path, conn: sqlite3.Connection):
        self.path = Path(path)
        self._conn = conn
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        self.crs_wkt: str = meta.get("crs_wkt", "")
        self.schema_version: int = int(conn.execute("SELECT version FROM schema_version").fetchone()[0])

    # -- opening -------------------------------------------------------------------------------------------------------

    @staticmethod
    def _connect(path: Path, busy_timeout: float, mode: str = "mode=rw") -> sqlite3.Connection:
        uri = "file:" + str(path.resolve()).replace("?", "%3f").replace("#", "%23") + "?" + mode
        conn = sqlite3.connect(uri, uri=True, timeout=busy_timeout, isolation_level=None, check_same_thread=False)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA foreign_keys = ON")
        conn.execute("PRAGMA synchronous = FULL")
        return conn

    @classmethod
    def create(cls, path: str | Path, crs_wkt: str, busy_timeout: float = BUSY_TIMEOUT_S) -> "MapStore":
        """Create a new, empty map for CRS ``crs_wkt`` (refused when ``path`` exists).

        The file is built under a temporary name and linked into place, so a crash never leaves a half-made map and
        two processes creating the same map cannot both succeed.
        """
        path = Path(path)
        if path.exists():
            raise InputError("map already exists", path)
        try:
            CRS.from_user_input(crs_wkt)
        except Exception:  # noqa: BLE001
            raise CRSError(f"cannot create a map with an unknown CRS: {str(crs_wkt)[:60]!r}", path) from None
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        try:
            conn = sqlite3.connect(tmp_path, isolation_level=None)
            try:
                conn.execute("PRAGMA journal_mode = DELETE")
                conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
                conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                conn.executescript(_SCHEMA)  # a private temporary file: atomicity comes from the link below
                conn.execute("BEGIN")
                conn.execute("INSERT INTO schema_version (version) VALUES (?)", (SCHEMA_VERSION,))
                conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", [
                    ("application", "lidarmap"), ("crs_wkt", str(crs_wkt)), ("created", _now()),
                    ("lidarmap_version", __version__)])
                conn.execute("COMMIT")
                conn.execute("PRAGMA journal_mode = WAL")
            finally:
                conn.close()
            os.chmod(tmp_path, 0o666 & ~current_umask())  # mkstemp made it 0600; a map gets the mode of a plain open()
            try:
                os.link(tmp_path, path)
            except FileExistsError:
                raise InputError("map already exists", path) from None
            except OSError:  # file systems without hard links: best effort
                if path.exists():
                    raise InputError("map already exists", path) from None
                os.replace(tmp_path, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp_path.unlink()
        return cls.open(path, busy_timeout)

    @classmethod
    def open(cls, path: str | Path, busy_timeout: float = BUSY_TIMEOUT_S, readonly: bool = False) -> "MapStore":
        """Open an existing map; one-line errors for a missing file, a file that is not a map, a newer schema.

        ``readonly`` (show, history, export, render): a map on a read-only disk or in a folder the user may not write
        is opened read-only, and where SQLite cannot make its shared-memory file there, read as it is on disk
        (``immutable``: safe because nobody can write there). Elsewhere the usual connection, which leaves no
        ``-wal``/``-shm`` files behind when it closes.
        """
        path = Path(path)
        if not path.exists():
            raise InputError("map not found", path)
        if not path.is_file():
            raise InputError("not a lidarmap map (not a file)", path)
        try:
            with path.open("rb") as fh:
                head = fh.read(len(_SQLITE_MAGIC))
        except OSError as exc:
            raise InputError(f"cannot read map ({exc.strerror})", path) from None
        if head != _SQLITE_MAGIC:
            raise InputError("not a lidarmap map (not an SQLite database)", path)
        writable = os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)
        modes = ["mode=ro", "mode=ro&immutable=1"] if readonly and not writable else ["mode=rw"]
        for k, mode in enumerate(modes):
            try:
                conn = cls._connect(path, busy_timeout, mode)
                conn.execute("SELECT 1 FROM sqlite_master LIMIT 1").fetchall()
                break
            except sqlite3.OperationalError as exc:
                if k + 1 < len(modes):
                    continue
                raise InputError(f"cannot open map ({exc})", path) from None
            except sqlite3.Error as exc:
                raise InputError(f"cannot open map ({exc})", path) from None
        try:
            try:
                row = conn.execute("SELECT version FROM schema_version").fetchone()
                app = conn.execute("SELECT value FROM meta WHERE key = 'application'").fetchone()
            except sqlite3.DatabaseError as exc:
                if "no such table" in str(exc):
                    raise InputError("not a lidarmap map (an SQLite database without lidarmap tables)", path) \
                        from None
                raise InputError(f"cannot read map ({exc})", path) from None
            if row is None or app is None or app[0] != "lidarmap":
                raise InputError("not a lidarmap map (no lidarmap schema version)", path)
            version = int(row[0])
            if version > SCHEMA_VERSION:
                raise InputError(f"map schema version {version} is newer than this lidarmap supports "
                                 f"({SCHEMA_VERSION}); upgrade lidarmap", path)
            if version < SCHEMA_VERSION:  # pragma: no cover - no older layout exists yet
                raise InputError(f"map schema version {version} is too old (this lidarmap reads {SCHEMA_VERSION})",
                                 path)
            if "mode=rw" in modes and conn.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
                with contextlib.suppress(sqlite3.OperationalError):
                    conn.execute("PRAGMA journal_mode = WAL")
            return cls(path, conn)
        except BaseException:
            conn.close()
            raise

    def close(self) -> None:
        """Close the connection (the map stays as committed)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None  # type: ignore[assignment]

    def __enter__(self) -> "MapStore":
        return self

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        self.close()
        damaged = damaged_map_error(exc, self.path)
        if damaged is not None:
            raise damaged from None

    def __repr__(self) -> str:
        return f"MapStore({str(self.path)!r})"

    @property
    def conn(self) -> sqlite3.Connection:
        if self._conn is None:
            raise LidarmapError("map store is closed", self.path)
        return self._conn

    # -- reading -------------------------------------------------------------------------------------------------------

    @contextlib.contextmanager
    def _snapshot(self) -> Iterator[sqlite3.Connection]:
        """A read transaction: every SELECT inside sees one committed state of the map."""
        conn = self.conn
        conn.execute("BEGIN")
        try:
            yield conn
        finally:
            conn.execute("COMMIT")

    def campaigns(self) -> list[Campaign]:
        """All campaigns applied to the map, oldest first."""
        rows = self.conn.execute("SELECT * FROM campaigns ORDER BY campaign_id").fetchall()
        return [_campaign_from_row(r) for r in rows]

    def history(self) -> list[tuple[Campaign, dict[str, dict[str, int]]]]:
        """Each campaign with what its commit changed: {entity: {"added", "updated", "removed"}} (see ENTITIES)."""
        rows = self.conn.execute("SELECT * FROM campaigns ORDER BY campaign_id").fetchall()
        return [(_campaign_from_row(r), json.loads(r["changes"])) for r in rows]

    def has_fingerprint(self, fingerprint: str) -> bool:
        """Whether a campaign with this fingerprint was applied already."""
        return self.conn.execute("SELECT 1 FROM campaigns WHERE fingerprint = ?", (fingerprint,)).fetchone() is not None

    def campaign_for_fingerprint(self, fingerprint: str) -> Campaign | None:
        """The campaign applied with this fingerprint, if any."""
        row = self.conn.execute("SELECT * FROM campaigns WHERE fingerprint = ?", (fingerprint,)).fetchone()
        return None if row is None else _campaign_from_row(row)

    def latest_campaign_id(self) -> int | None:
        """The id of the newest campaign (``None`` for an empty map)."""
        row = self.conn.execute("SELECT MAX(campaign_id) FROM campaigns").fetchone()
        return None if row[0] is None else int(row[0])

    def next_campaign_id(self) -> int:
        """The id for the next campaign: one more than the newest (1 for an empty map)."""
        latest = self.latest_campaign_id()
        return 1 if latest is None else latest + 1

    def _select(self, conn: sqlite3.Connection, table: _Table, as_of: int | None,
                extra: str = "") -> list[sqlite3.Row]:
        if table.owner == "building":
            join = "JOIN buildings b ON b.id = v.building"
            order = "b.id"
        else:
            join = "JOIN facades f ON f.id = v.facade JOIN buildings b ON b.id = f.building"
            order = "b.id, f.facade_id"
        where = "v.valid_to IS NULL" if as_of is None else "v.valid_from <= :n AND (v.valid_to IS NULL OR v.valid_to > :n)"
        keys = ", ".join(f"v.{_q(k)}" for k in table.key)
        order_keys = ", ".join([order] + [f"v.{_q(k)}" for k in table.key])
        owner_cols = "b.building_id" + (", f.facade_id" if table.owner == "facade" else "")
        select = ", ".join(filter(None, [owner_cols, keys, extra]))
        sql = f"SELECT {select} FROM {table.name} v {join} WHERE {where} ORDER BY {order_keys}"
        return conn.execute(sql, {"n": as_of}).fetchall()

    def load(self, as_of: int | None = None) -> BuildingMap:
        """The map as of now, or as it was right after campaign ``as_of`` (exactly as committed then).

        Façades, layers, elements and roofs come back ordered by their ids; buildings in the order the store first saw
        them.
        """
        with self._snapshot() as conn:
            ids = [int(r[0]) for r in conn.execute("SELECT campaign_id FROM campaigns ORDER BY campaign_id")]
            if as_of is not None:
                as_of = int(as_of)
                if as_of not in ids:
                    known = ", ".join(map(str, ids)) or "none"
                    raise LidarmapError(f"no campaign {as_of} in this map (campaigns: {known})", self.path)
            cond = "" if as_of is None else " WHERE campaign_id <= :n"
            campaigns = [_campaign_from_row(r) for r in
                         conn.execute(f"SELECT * FROM campaigns{cond} ORDER BY campaign_id", {"n": as_of})]
            buildings: dict[str, Building] = {}
            for r in self._select(conn, _TABLE["buildings"], as_of, "v.footprint, v.attributes"):
                bid = r["building_id"]
                buildings[bid] = Building(building_id=bid, footprint=_from_wkb(r["footprint"]),
                                          attributes=json.loads(r["attributes"]))
            facades: dict[tuple[str, int], Facade] = {}
            t = _TABLE["facades"]
            for r in self._select(conn, t, as_of, ", ".join(f"v.{_q(c)}" for c in t.cols)):
                frame = FacadeFrame(np.array([_unf(r["ox"]), _unf(r["oy"]), _unf(r["oz"])]), np.array([1.0, 0, 0]))
                frame.origin = np.array([_unf(r["ox"]), _unf(r["oy"]), _unf(r["oz"])], dtype=np.float64)
                frame.u = np.array([_unf(r["ux"]), _unf(r["uy"]), _unf(r["uz"])], dtype=np.float64)  # exact: no renorm
                f = Facade(facade_id=int(r["facade_id"]), frame=frame, sigma=_unf(r["sigma"]),
                           extent=(_unf(r["s0"]), _unf(r["s1"]), _unf(r["t0"]), _unf(r["t1"])),
                           main_layer=_opt_int(r["main_layer"]), n_points=int(r["n_points"]),
                           footprint_edge=_opt_int(r["footprint_edge"]), campaigns=json.loads(r["campaigns"]))
                facades[(r["building_id"], f.facade_id)] = f
                buildings[r["building_id"]].facades.append(f)
            t = _TABLE["layers"]
            for r in self._select(conn, t, as_of, ", ".join(f"v.{_q(c)}" for c in t.cols)):
                facades[(r["building_id"], int(r["facade_id"]))].layers.append(Layer(
                    layer_id=int(r["layer_id"]), mu=_unf(r["mu"]), sigma=_unf(r["sigma"]), weight=_unf(r["weight"]),
                    n_points=int(r["n_points"]), campaigns=json.loads(r["campaigns"])))
            t = _TABLE["elements"]
            for r in self._select(conn, t, as_of, ", ".join(f"v.{_q(c)}" for c in t.cols)):
                try:
                    kind = ElementKind(r["kind"])
                except ValueError:
                    raise InputError(f"unknown element kind {r['kind']!r} (written by a newer lidarmap?)",
                                     self.path) from None
                facades[(r["building_id"], int(r["facade_id"]))].elements.append(Element(
                    element_id=int(r["element_id"]), kind=kind, polygon=_from_wkb(r["polygon"]),
                    layer_id=_opt_int(r["layer_id"]), uncertainty=_unf(r["uncertainty"]),
                    n_points=int(r["n_points"]), campaigns=json.loads(r["campaigns"])))
            t = _TABLE["evidence"]
            for r in self._select(conn, t, as_of, ", ".join(f"v.{_q(c)}" for c in t.cols)):
                facades[(r["building_id"], int(r["facade_id"]))].evidence = FacadeEvidence(
                    cell=_unf(r["cell"]), s0=_unf(r["s0"]), t0=_unf(r["t0"]),
                    window_votes=decode_array(r["window_votes"]), object_votes=decode_array(r["object_votes"]),
                    seen=decode_array(r["seen"]))
            t = _TABLE["roofs"]
            for r in self._select(conn, t, as_of, ", ".join(f"v.{_q(c)}" for c in t.cols)):
                buildings[r["building_id"]].roofs.append(RoofPlane(
                    plane_id=int(r["plane_id"]), normal=np.array([_unf(r["nx"]), _unf(r["ny"]), _unf(r["nz"])]),
                    offset=_unf(r["offset"]), outline=_from_wkb(r["outline"]), sigma=_unf(r["sigma"]),
                    n_points=int(r["n_points"]), campaigns=json.loads(r["campaigns"])))
        return BuildingMap(crs_wkt=self.crs_wkt, buildings=buildings, campaigns=campaigns)

    # -- writing -------------------------------------------------------------------------------------------------------

    def _check_crs(self, crs_wkt: str) -> None:
        if not crs_wkt or not self.crs_wkt or crs_wkt == self.crs_wkt:
            return
        try:
            same = CRS.from_user_input(crs_wkt) == CRS.from_user_input(self.crs_wkt)
        except Exception:  # noqa: BLE001
            same = False
        if not same:
            raise CRSError(f"the map is in {CRS.from_user_input(self.crs_wkt).name!r} but the new map's CRS differs",
                           self.path)

    def commit(self, new_map: BuildingMap, campaign: Campaign) -> dict[str, dict[str, int]]:
        """Write ``new_map`` as the state after ``campaign``: everything that changed, in ONE transaction.

        Refused (nothing written) when the campaign's fingerprint was applied already, its id is not newer than every
        stored campaign, the map lists fewer campaigns than the store holds (another process committed since it was
        loaded), or another process is writing (:class:`MapLockedError`). Returns the change counts
        {entity: {"added", "updated", "removed"}} that :meth:`history` reports for the campaign.
        """
        if not isinstance(campaign, Campaign):
            raise TypeError("campaign must be a lidarmap.map.model.Campaign")
        cid = int(campaign.campaign_id)
        self._check_crs(new_map.crs_wkt)
        rows = _encode_map(new_map)  # encode (and compress) before taking any lock
        digests = {entity: {k: _digest(v) for k, v in table_rows.items()} for entity, table_rows in rows.items()}
        listed = {int(c.campaign_id) for c in new_map.campaigns} | {cid}
        summary = _dumps(campaign.summary or {}, f"campaign {cid} summary")
        with writer_lock(self.path):
            conn = self.conn
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as exc:
                if _is_locked(exc):
                    raise MapLockedError("another process is writing this map (database is locked); try again "
                                         "when it has finished", self.path) from None
                raise
            try:
                cur = conn.cursor()
                dup = cur.execute("SELECT campaign_id FROM campaigns WHERE fingerprint = ?",
                                  (campaign.fingerprint,)).fetchone()
                if dup is not None:
                    raise LidarmapError(f"campaign already applied: fingerprint {campaign.fingerprint[:12]}… matches "
                                        f"campaign {dup[0]}", self.path)
                stored = [int(r[0]) for r in cur.execute("SELECT campaign_id FROM campaigns ORDER BY campaign_id")]
                if stored and cid <= stored[-1]:
                    raise LidarmapError(f"campaign id {cid} is not newer than the map's latest campaign {stored[-1]}",
                                        self.path)
                missing = [c for c in stored if c not in listed]
                if missing:
                    raise MapLockedError(f"the map changed since it was loaded (campaign(s) "
                                         f"{', '.join(map(str, missing))} committed meanwhile); load it again and "
                                         "redo the update", self.path)
                cur.execute("INSERT INTO campaigns (campaign_id, kind, source, fingerprint, n_points, created, summary,"
                            " changes, committed) VALUES (?, ?, ?, ?, ?, ?, ?, '{}', ?)",
                            (cid, str(campaign.kind), str(campaign.source), str(campaign.fingerprint),
                             int(campaign.n_points), str(campaign.created), summary, _now()))
                changes = self._write_changes(cur, rows, digests, cid)
                cur.execute("UPDATE campaigns SET changes = ? WHERE campaign_id = ?", (json.dumps(changes), cid))
                conn.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
                raise
        return changes

    def _identity(self, cur: sqlite3.Cursor, cache: dict, key: tuple) -> int:
        """Integer id of a building (key (bid,)) or façade (key (bid, fid)), created on first use."""
        if key in cache:
            return cache[key]
        if len(key) == 1:
            cur.execute("INSERT OR IGNORE INTO buildings (building_id) VALUES (?)", key)
            ident = cur.execute("SELECT id FROM buildings WHERE building_id = ?", key).fetchone()[0]
        else:
            building = self._identity(cur, cache, key[:1])
            cur.execute("INSERT OR IGNORE INTO facades (building, facade_id) VALUES (?, ?)", (building, key[1]))
            ident = cur.execute("SELECT id FROM facades WHERE building = ? AND facade_id = ?",
                                (building, key[1])).fetchone()[0]
        cache[key] = int(ident)
        return cache[key]

    def _write_changes(self, cur: sqlite3.Cursor, rows: dict, digests: dict, cid: int) -> dict[str, dict[str, int]]:
        cache: dict[tuple, int] = {}
        changes: dict[str, dict[str, int]] = {}
        for table in _TABLES:
            owner_len = 1 if table.owner == "building" else 2
            current: dict[tuple, tuple[int, bytes]] = {}
            for r in self._select(cur.connection, table, None, "v.id AS _rowid, v.digest AS _digest"):
                key = tuple(r[i] for i in range(owner_len + len(table.key)))
                key = (str(key[0]), *(int(k) for k in key[1:]))
                current[key] = (int(r["_rowid"]), bytes(r["_digest"]))
            new_rows, new_digests = rows[table.entity], digests[table.entity]
            added = updated = removed = 0
            for key, values in new_rows.items():
                digest = new_digests[key]
                old = current.get(key)
                if old is not None and old[1] == digest:
                    continue
                if old is not None:
                    cur.execute(f"UPDATE {table.name} SET valid_to = ? WHERE id = ?", (cid, old[0]))
                    updated += 1
                else:
                    added += 1
                owner = self._identity(cur, cache, key[:owner_len])
                _insert_version(cur, table, owner, key[owner_len:], cid, digest, values)
            for key, (rowid, _) in current.items():
                if key not in new_rows:
                    cur.execute(f"UPDATE {table.name} SET valid_to = ? WHERE id = ?", (cid, rowid))
                    removed += 1
            changes[table.entity] = {"added": added, "updated": updated, "removed": removed}
        return changes
