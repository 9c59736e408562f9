"""Output folders that never destroy the user's data.

A folder is ours only if we marked it: every command that writes a folder leaves a marker file
``.lidarmap.json`` in it naming the command (``kind``), the lidarmap version and the files and folders it wrote.

- a missing folder is created (its parent must exist: a typo in ``-o`` is an error, not a tree of new folders);
- an existing folder without our marker is used only if it is empty;
- a folder marked by another command is refused (a ``run`` output is not a ``prep`` output);
- replacing or resuming touches only the entries the marker lists: a file the user added to one of our folders is
  never deleted or replaced.

The marker is written atomically (temporary file + rename), so it is either the old or the new one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from lidarmap._version import __version__
from lidarmap.errors import InputError
from lidarmap.io.atomic import current_umask, write_text_atomic

#: The marker file of a folder lidarmap wrote.
MARKER = ".lidarmap.json"


def read_marker(folder: str | Path) -> dict[str, Any] | None:
    """The marker of ``folder`` (``kind``, ``lidarmap``, ``written``), or ``None`` when it has none (or a damaged
    one: then the folder is not ours)."""
    path = Path(folder) / MARKER
    try:
        marker = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or not isinstance(marker.get("kind"), str):
        return None
    written = marker.get("written")
    marker["written"] = [w for w in written if _plain_name(w)] if isinstance(written, list) else []
    return marker


def _plain_name(name: Any) -> bool:
    """A name directly inside the folder (a damaged or hostile marker must not point outside it)."""
    return isinstance(name, str) and name not in ("", ".", "..", MARKER) and "/" not in name and "\\" not in name


def write_marker(folder: str | Path, kind: str, written: Iterable[str]) -> Path:
    """Mark ``folder`` as a ``kind`` output holding ``written`` (names inside it), atomically."""
    names = sorted({w for w in written if _plain_name(w)})
    doc = {"kind": kind, "lidarmap": __version__, "written": names}
    return write_text_atomic(Path(folder) / MARKER, json.dumps(doc, indent=1) + "\n")


def claim_out_dir(out_dir: str | Path, kind: str, what: str = "output folder") -> Path:
    """Check that ``kind`` may write into ``out_dir``; nothing is created or changed (see the module doc).

    Returns the path; raises :class:`InputError` naming it otherwise.
    """
    out = Path(out_dir)
    if not out.exists():
        parent = out.absolute().parent
        if not parent.is_dir():
            raise InputError(f"the parent folder of the {what} does not exist", parent)
        return out
    if not out.is_dir():
        raise InputError(f"{what} exists and is not a folder", out)
    marker = read_marker(out)
    if marker is None:
        if any(p.name != MARKER for p in out.iterdir()):
            raise InputError(f"{what} is not empty and was not written by lidarmap; choose another or an empty one",
                             out)
        return out
    if marker["kind"] != kind:
        raise InputError(f"{what} holds a lidarmap {marker['kind']} output, not a {kind} output; choose another",
                         out)
    return out


def start_marked_dir(out_dir: str | Path, kind: str, written: Iterable[str]) -> bool:
    """Create ``out_dir`` if needed (after :func:`claim_out_dir`) and mark it as ``kind`` output holding ``written``
    plus what an earlier marker listed; returns whether the folder was created now (see :func:`abandon_marked_dir`)."""
    out = claim_out_dir(out_dir, kind)
    created = not out.exists()
    out.mkdir(exist_ok=True)
    earlier = read_marker(out)
    write_marker(out, kind, [*written, *(earlier["written"] if earlier else [])])
    return created


def abandon_marked_dir(out_dir: str | Path, created: bool) -> None:
    """After a failed command: remove a folder created by :func:`start_marked_dir` when nothing but our marker is in
    it (a refused input leaves nothing behind)."""
    out = Path(out_dir)
    if created and out.is_dir() and all(p.name == MARKER for p in out.iterdir()):
        with contextlib.suppress(FileNotFoundError):
            (out / MARKER).unlink()
        with contextlib.suppress(OSError):
            out.rmdir()


def remove_marked(out_dir: str | Path) -> None:
    """Delete what the marker of ``out_dir`` lists (our earlier outputs); anything else stays, and so does the
    marker (listing nothing now: the folder stays ours, for the command that replaces its outputs)."""
    out = Path(out_dir)
    marker = read_marker(out)
    if marker is None:
        return
    for name in marker["written"]:
        _remove(out / name)
    write_marker(out, marker["kind"], [])


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def atomic_out_dir(out_dir: str | Path, kind: str, replace: bool = True) -> Iterator[Path]:
    """Yield a temporary folder beside ``out_dir`` to fill; on success its entries are published into ``out_dir``
    (created if missing) and the marker lists them. An error leaves ``out_dir`` as it was.

    ``replace``: an earlier output's entries that the new one does not write are deleted (a new ``prep`` replaces
    the old one); otherwise they stay listed (stage commands add outputs to the folder). An entry the new output
    writes that exists in ``out_dir`` without being listed by its marker is refused (it is the user's).
    """
    out = claim_out_dir(out_dir, kind)
    parent = out.absolute().parent
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=parent))
    except OSError as exc:
        raise InputError(f"cannot write into this folder ({exc.strerror or exc})", parent) from None
    try:
        yield tmp
        _publish(tmp, out, kind, replace)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _publish(tmp: Path, out: Path, kind: str, replace: bool) -> None:
    new = sorted(p.name for p in tmp.iterdir() if p.name != MARKER)
    if not out.exists():
        write_marker(tmp, kind, new)
        os.chmod(tmp, 0o777 & ~current_umask())
        os.replace(tmp, out)  # a new folder: published whole, at once
        return
    claim_out_dir(out, kind)  # again: the folder may have changed while we computed
    marker = read_marker(out)
    ours = set(marker["written"]) if marker else set()
    theirs = [name for name in new if (out / name).exists() and name not in ours]
    if theirs:
        raise InputError(f"'{theirs[0]}' exists in the output folder and was not written by lidarmap; "
                         "choose another folder", out)
    # list the new names before moving them in, so that an interruption leaves nothing unlisted
    write_marker(out, kind, [*ours, *new])
    for name in new:
        target = out / name
        if target.is_dir() and not target.is_symlink():
            aside = Path(tempfile.mkdtemp(prefix=f".{name}.old-", dir=tmp))
            os.replace(target, aside / name)
        os.replace(tmp / name, target)
    stale = sorted(ours - set(new)) if replace else []
    for name in stale:
        _remove(out / name)
    write_marker(out, kind, [n for n in (*ours, *new) if n not in stale])
