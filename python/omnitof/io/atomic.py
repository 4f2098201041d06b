"""All-or-nothing file writes.

Every writer of omnitof goes through `atomic_write`, so that a run that is interrupted (an
exception, Ctrl-C, a crash) never leaves a half-written trajectory, map or report behind: readers
see either the previous file or the complete new one.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO, Any

_MODES = ("w", "wb")


def _create_temporary(path: Path) -> tuple[int, Path]:
    """Create an empty, exclusive temporary file beside `path`; returns (fd, temp path)."""
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            # Mode 0o666 lets the process umask decide the permissions, as a plain open() would
            # (tempfile.mkstemp would leave the final file readable by its owner only).
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp
        except FileExistsError:
            continue


@contextmanager
def atomic_write(
    path: str | Path, mode: str = "w", *, encoding: str = "utf-8"
) -> Iterator[IO[Any]]:
    """Open a temporary file beside `path` for writing, and rename it over `path` on success.

    The temporary file lives in the same directory as `path` so that the final `os.replace` is a
    rename within one file system, which is atomic. The data are flushed and fsync'ed before the
    rename. If the `with` block raises, the temporary file is removed and `path` is left as it
    was: absent if it did not exist, otherwise untouched.

    Args:
        path: the file to write.
        mode: "w" (text, `encoding`, "\\n" line endings on every platform) or "wb" (bytes).
        encoding: text encoding for mode "w".

    Yields:
        The open file object.
    """
    if mode not in _MODES:
        raise ValueError(f"atomic_write mode must be one of {_MODES}, got {mode!r}")
    path = Path(path)
    fd, tmp = _create_temporary(path)
    try:
        if mode == "wb":
            handle: IO[Any] = os.fdopen(fd, "wb")
        else:
            handle = os.fdopen(fd, "w", encoding=encoding, newline="")
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with suppress(FileNotFoundError):
            tmp.unlink()
        raise
