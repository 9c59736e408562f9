"""The ``lidarmap`` command line: one Typer app; each area registers its commands from its own module."""

from __future__ import annotations

import importlib

import typer

from lidarmap._version import __version__
from lidarmap.cli.common import configure_logging

app = typer.Typer(
    name="lidarmap",
    help="LiDAR point clouds of cities to building models that get better with every new scan.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

#: Modules under lidarmap.cli that define ``register(app)``; order is the order in ``--help``.
COMMAND_MODULES = ["info", "simulate", "prep", "segment", "aerial", "facade_map", "view", "demo", "config_cmd"]


def _version(value: bool) -> None:
    if value:
        typer.echo(f"lidarmap {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit."),
          verbose: int = typer.Option(0, "--verbose", "-v", count=True,
                                      help="More messages on stderr: -v progress notes, -vv debugging."),
          quiet: bool = typer.Option(False, "--quiet", "-q", help="Errors only: no tables, warnings or progress.")
          ) -> None:
    """LiDAR point clouds of cities to building models that get better with every new scan."""
    configure_logging(verbose, quiet)


for _name in COMMAND_MODULES:
    _module = importlib.import_module(f"lidarmap.cli.{_name}")
    _module.register(app)


class _Never(Exception):
    """Stands for an exception class the installed click does not have (never raised)."""


def _click_exceptions():
    """click's exception module: recent typer releases vendor click (``typer._click``), older ones depend on it."""
    try:
        from typer._click import exceptions
    except ImportError:  # typer before the vendored click
        from click import exceptions
    return exceptions


def main() -> None:
    """Console-script entry point: usage errors are one line too (no rich box, no traceback)."""
    import os
    import sys

    click_exc = _click_exceptions()

    try:
        # prog_name: usage lines and the completion variable (_LIDARMAP_COMPLETE) say "lidarmap" however it was
        # started (python -m lidarmap, or inside another program such as pytest)
        code = app(standalone_mode=False, prog_name="lidarmap")  # the exit code of a typer.Exit inside a command
    except getattr(click_exc, "NoArgsIsHelpError", _Never) as exc:
        typer.echo(exc.ctx.get_help() if exc.ctx else "see 'lidarmap --help'")
        sys.exit(0)
    except click_exc.UsageError as exc:
        command = exc.ctx.command_path if exc.ctx else "lidarmap"
        typer.echo(f"error: {exc.format_message()} (see '{command} --help')", err=True)
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        typer.echo("error: aborted", err=True)
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except BrokenPipeError:
        # output piped into a program that stopped reading (e.g. `lidarmap run --help | head`): not an error
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(0)
    except SystemExit as exc:
        if isinstance(exc.__context__, BrokenPipeError):
            sys.exit(0)
        raise
    sys.exit(code if isinstance(code, int) else 0)
