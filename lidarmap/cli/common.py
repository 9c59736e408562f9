"""What every command shares: config loading, one-line errors, progress bars, the console."""

from __future__ import annotations

import errno
import functools
import json
import logging
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from lidarmap.config import KNOWN_TABLES, check_sections, load_toml, resolve
from lidarmap.errors import ConfigError, LidarmapError

console = Console()
err_console = Console(stderr=True)
#: Table width when the output is not a terminal (a pipe or a file): wide enough that no cell is cut.
PIPE_WIDTH = 160


def table_console() -> Console:
    """The shared console in a terminal; a wide one when the output goes to a pipe or a file; a silent one under
    ``--quiet`` or ``--json`` (stdout then holds the JSON object only)."""
    if console.quiet:
        return console
    return console if console.is_terminal else Console(width=PIPE_WIDTH)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (tests and embedding programs swap it)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


#: Set by the global options (``--quiet``) for this invocation.
_state = {"quiet": False}


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Log level of the ``lidarmap`` loggers from ``-v`` (info), ``-vv`` (debug) or ``--quiet`` (errors only; also
    no tables or progress bars), printed on stderr as ``level: message``."""
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    logger = logging.getLogger("lidarmap")
    logger.setLevel(level)
    for handler in [h for h in logger.handlers if getattr(h, "lidarmap_cli", False)]:
        logger.removeHandler(handler)
    handler = _StderrHandler()
    handler.lidarmap_cli = True  # type: ignore[attr-defined]
    handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s" if verbose < 2
                                           else "%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    console.quiet = quiet
    _state["quiet"] = quiet


#: ``--json`` option of the commands whose result a script reads.
JsonOption = typer.Option(False, "--json", help="Print the result as one JSON object on stdout (no tables).")


def json_mode(enabled: bool) -> None:
    """Under ``--json`` the tables stay silent, so stdout holds the JSON object only."""
    if enabled:
        console.quiet = True


def echo_json(doc: Any) -> None:
    """Write ``doc`` as one JSON object (one line) on stdout; numpy values and paths as plain JSON."""
    sys.stdout.write(json.dumps(doc, default=_plain_json, ensure_ascii=False) + "\n")
    sys.stdout.flush()


def _plain_json(value: Any) -> Any:
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)

T = TypeVar("T")
P = TypeVar("P")

#: ``--config`` option shared by every command (a TOML file, one table per stage).
ConfigOption = typer.Option(None, "--config", "-c", help="TOML config file; command-line flags override it.",
                            exists=False, dir_okay=False)
#: ``--seed`` option shared by every command that draws random numbers.
SeedOption = typer.Option(None, "--seed", min=0, help="Random seed (>= 0): the same input and seed give the same "
                          "output.")
#: ``--crs`` option of every command that reads LAS/LAZ (for files without a CRS record, e.g. AHN).
CrsOption = typer.Option(None, "--crs", help="CRS of inputs that carry none, e.g. EPSG:28992.")
#: Required ``--footprints`` option of the commands that split by building.
FootprintsOption = typer.Option(..., "--footprints", "-f", dir_okay=False,
                                help="Building footprints: GeoJSON; GeoPackage, Shapefile or FlatGeobuf with "
                                     "the gis extra.")
#: ``--id-field`` option of every command that reads footprints.
IdFieldOption = typer.Option(None, "--id-field", help="Footprint property holding the building id (default 'id').")


def params_from(params_cls: type[P], config_path: Path | None, section: str | None = None, **flags: Any) -> P:
    """Stage parameters: dataclass defaults < the config file's table < flags given on the command line.

    A bad value or unknown key in the file is an error naming the file.
    """
    try:
        config = load_toml(config_path)
        check_sections(config, KNOWN_TABLES | {section or getattr(params_cls, "section", "")})
        return resolve(params_cls, config, section, **flags)
    except ConfigError as exc:
        if exc.path is None and config_path is not None:
            raise ConfigError(exc.problem, config_path) from None
        raise


def fail(message: str, code: int = 2) -> None:
    """Print a one-line error and exit with ``code``."""
    # the message is user text (file names, "[facade]" tables): never rich markup
    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def handle_errors(func: Callable[..., T]) -> Callable[..., T]:
    """Turn lidarmap errors (and unexpected ones) into one line on stderr and a non-zero exit.

    Set ``LIDARMAP_DEBUG=1`` to see the full traceback of an unexpected error.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> T:
        try:
            return func(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except LidarmapError as exc:
            fail(str(exc), exc.exit_code)
        except MemoryError:
            fail("out of memory (try smaller chunks or --workers)", 4)
        except OSError as exc:
            if exc.errno not in ENVIRONMENT_ERRNOS or exc.filename is None:
                _internal(exc)
            fail(f"{exc.filename}: {exc.strerror or exc}", 2)
        except Exception as exc:  # noqa: BLE001 - the last line of defence: no tracebacks for users
            _internal(exc)
        raise AssertionError("unreachable")

    return wrapper


#: OS errors that are the environment's, not a bug: a read-only or full disk, a missing or forbidden path, a name
#: too long. With a file name they are one line naming it and exit code 2, like a bad input.
ENVIRONMENT_ERRNOS = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENOENT,
                                errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG, errno.EEXIST, errno.ENOTEMPTY})


def _internal(exc: BaseException) -> None:
    """A real bug: one line saying so (the traceback with ``LIDARMAP_DEBUG=1``)."""
    if os.environ.get("LIDARMAP_DEBUG"):
        raise exc
    fail(f"internal error: {type(exc).__name__}: {exc} (set LIDARMAP_DEBUG=1 for a traceback)", 1)


def progress(transient: bool = False) -> Progress:
    """A rich progress bar that stays quiet when stderr is not a terminal (CI logs)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=transient,
        disable=not sys.stderr.isatty() or _state["quiet"],
    )


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate with a progress bar."""
    with progress() as bar:
        yield from bar.track(items, description=description, total=total)
