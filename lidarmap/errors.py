"""Errors a user can act on.

Every problem with user input is raised as a :class:`LidarmapError` whose message is one line that names the file
(when there is one) and the problem. The CLI prints that line and exits non-zero; it never shows a traceback for them.
"""

from __future__ import annotations

from pathlib import Path


class LidarmapError(Exception):
    """A problem with the user's input or options, reported as one line."""

    exit_code = 2

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else str(path)
        self.problem = " ".join(str(message).split())  # one line, always
        super().__init__(f"{self.path}: {self.problem}" if self.path else self.problem)


class InputError(LidarmapError):
    """A file that cannot be read or whose content is invalid."""


class CRSError(LidarmapError):
    """A missing, unknown or mismatched coordinate reference system."""


class ConfigError(LidarmapError):
    """An unknown option or an invalid value in a config file or on the command line."""


class ParameterError(ConfigError, ValueError):
    """A parameter outside its declared constraint (:func:`lidarmap.config.check_params`); also a ValueError, as
    Python code building parameter objects expects."""


class MapLockedError(LidarmapError):
    """Another process is writing the same map."""

    exit_code = 3
