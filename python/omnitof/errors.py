"""Exceptions of omnitof.

Library code raises these; the command line turns them into one clear line and a non-zero exit
status, never a traceback, because they describe a user's mistake (bad file, bad value), not a bug.
"""

from __future__ import annotations

from pathlib import Path


class OmnitofError(Exception):
    """Base class of every error omnitof raises on purpose."""


class InputError(OmnitofError):
    """Bad input data: names the file and, where known, the line and what was expected."""

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else Path(path)
        self.line = line
        self.reason = message
        where = ""
        if path is not None:
            where = f"{path}" + (f":{line}" if line is not None else "") + ": "
        super().__init__(where + message)


class ConfigError(OmnitofError):
    """An invalid configuration value; the message names the field."""
