"""All-or-nothing writes: of one file (`atomic_write`) and of a whole folder (`atomic_folder`).

Every writer of omnitof goes through `atomic_write`, so that a run that is interrupted (an
exception, Ctrl-C, SIGTERM, a full disk) never leaves a half-written trajectory, map or report
behind: readers see either the previous file or the complete new one. A results folder is one
unit on top of that (`atomic_folder`): it is built under a hidden name beside its place and
renamed into it when complete, so that the files of two runs can never mix.

Temporary names. Everything in the making is a hidden sibling of its target, in the same
folder so that the final rename stays within one file system and is atomic:

    .<name>.<pid>-<12 hex>.tmp       a file (atomic_write)
    .<name>.<pid>-<12 hex>.partial   a folder being built (atomic_folder)
    .<name>.<pid>-<12 hex>.old       the folder it replaces, for the moment between two renames

The process id in the name tells whose it is. A process killed outright (SIGKILL, a power cut)
cannot clean up; the next write to the same target sweeps what such a process left
(`sweep_leftovers`), and leaves alone what a live process is still writing.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from omnitof.errors import OutputError
from omnitof.interrupts import deferred_signals, pause_point

_MODES = ("w", "wb")

# .<name>.<pid>-<token>.<kind>, and the temporary files of omnitof 0.1 (no process id).
_LEFTOVER = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)-[0-9a-f]{12}\.(?P<kind>tmp|partial|old)")
_OLD_STYLE_TMP = re.compile(r"\.(?P<name>.+)\.[0-9a-f]{12}\.tmp")

# Temporaries this process is writing now: never swept, even though their process is alive.
_ACTIVE: set[Path] = set()


def _temporary(path: Path, kind: str) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(6)}.{kind}")


def _unwritable(path: Path, err: OSError) -> OutputError:
    """The error for an output whose temporary beside it cannot be made: named by the output, not
    by the temporary."""
    why = "its folder does not exist" if not path.parent.is_dir() else (err.strerror or str(err))
    return OutputError(f"{path}: cannot write: {why}")


def _alive(pid: int) -> bool:
    """Whether process `pid` exists (a process of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OverflowError, ValueError):
        return False  # no process can have such a number
    return True


def _in_use(leftover: Path, pid: int) -> bool:
    """Whether a temporary may still be written: by a live process, or by this one now."""
    return leftover in _ACTIVE if pid == os.getpid() else _alive(pid)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with suppress(FileNotFoundError, IsADirectoryError):
            path.unlink()


def sweep_leftovers(path: str | Path) -> list[str]:
    """Remove the temporaries that killed processes left beside `path` (see the module notes)
    and return their names. A folder that such a process had moved aside to put its new one
    in place (`.old`) is moved back when `path` itself is missing: the previous result then
    comes back, as if the killed run had never finished."""
    path = Path(path)
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return []
    swept = []
    for entry in sorted(entries, key=lambda e: e.name):
        leftover = Path(entry.path)
        match = _LEFTOVER.fullmatch(entry.name)
        if match is not None:
            if match["name"] != path.name or _in_use(leftover, int(match["pid"])):
                continue
        elif not ((m := _OLD_STYLE_TMP.fullmatch(entry.name)) and m["name"] == path.name):
            continue
        if match is not None and match["kind"] == "old" and not os.path.lexists(path):
            with suppress(OSError):
                os.rename(leftover, path)
                swept.append(entry.name)
                continue
        _remove(leftover)
        swept.append(entry.name)
    return swept


@contextmanager
def atomic_write(
    path: str | Path, mode: str = "w", *, encoding: str = "utf-8"
) -> Iterator[IO[Any]]:
    """Open a temporary file beside `path` for writing, and rename it over `path` on success.

    The temporary file lives in the same directory as `path` so that the final `os.replace` is a
    rename within one file system, which is atomic. The data are flushed and fsync'ed before the
    rename. If the `with` block raises, the temporary file is removed and `path` is left as it
    was: absent if it did not exist, otherwise untouched. Temporaries of `path` left by killed
    processes are swept first (`sweep_leftovers`).

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
    sweep_leftovers(path)
    while True:
        tmp = _temporary(path, "tmp")
        try:
            # Mode 0o666 lets the process umask decide the permissions, as a plain open() would
            # (tempfile.mkstemp would leave the final file readable by its owner only).
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
        except OSError as err:
            raise _unwritable(path, err) from None
    _ACTIVE.add(tmp)
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
    finally:
        _ACTIVE.discard(tmp)


@contextmanager
def temporary_folder(path: str | Path) -> Iterator[Path]:
    """A new, empty hidden folder beside `path` (`.<name>.<pid>-<hex>.tmp`, after sweeping the
    leftovers of `path`), removed with its content after the block. For writers that build
    their target inside it and rename it out themselves (ROS bags: omnitof.io.rosbag.common)."""
    path = Path(path)
    sweep_leftovers(path)
    while True:
        folder = _temporary(path, "tmp")
        try:
            folder.mkdir()
            break
        except FileExistsError:
            continue
        except OSError as err:
            raise _unwritable(path, err) from None
    _ACTIVE.add(folder)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        _ACTIVE.discard(folder)


@contextmanager
def atomic_folder(
    path: str | Path, *, may_replace: Callable[[Path], None] | None = None
) -> Iterator[Path]:
    """Build a folder under a hidden temporary name beside `path`; put it in place of `path`
    when the `with` block succeeds. Yields the folder to write into.

    Before the block: `path` must be a folder or absent (else OutputError), and not a mount
    point nor a folder that cannot be renamed (an immutable one: it is moved aside and back to
    find out, `check_replaceable`); `may_replace(path)` may refuse an existing folder (by
    raising), leftovers of killed processes are swept, the missing parent folders are made and
    the temporary folder is created, which proves that the place can be written (else
    OutputError). So a run that opens its results folder first learns of a bad output path
    before it does any work.

    When the block succeeds, the new folder (its files fsync'ed) replaces the old one by two
    renames, `path` → `.old` and the new folder → `path`, with SIGINT and SIGTERM held off
    meanwhile; the old one is deleted afterwards. Between the two renames `path` is absent for
    a moment; a process killed outright just then leaves both complete folders under hidden
    names, and the next write to `path` moves the old one back (`sweep_leftovers`). When the
    block raises, the temporary folder is removed, parents made for it are removed again, and
    `path` is left as it was.
    """
    shown = Path(path)
    if "\0" in str(shown):
        raise OutputError(f"{str(shown)!r}: a path cannot hold a NUL character")
    try:
        path = _checked_target(shown, may_replace)
    except OSError as err:  # a name too long for the file system, a folder that cannot be listed
        raise OutputError(f"{shown}: cannot be the results folder: {err.strerror or err}") from None
    made = _make_parents(path.parent, shown)
    staging = _temporary(path, "partial")
    try:
        staging.mkdir()
    except OSError as err:
        _remove_made(made)
        raise OutputError(f"{shown}: cannot create the results folder: {err.strerror or err}") from None
    _ACTIVE.add(staging)
    try:
        yield staging
        with deferred_signals():
            _fsync_folder(staging)
            _put_in_place(staging, path)
    except BaseException:
        with deferred_signals():
            shutil.rmtree(staging, ignore_errors=True)
            _remove_made(made)
        raise
    finally:
        _ACTIVE.discard(staging)


def replaceable_place(shown: str | Path, thing: str) -> Path:
    """The absolute path `shown` names, where `thing` (a results folder, a bag) is to replace
    whatever is there as a whole: never the root, nor the current folder or one that holds it
    (the new one put in its place would pull the process's folder away)."""
    path = Path(os.path.abspath(shown))
    if path.parent == path:
        raise OutputError(f"{shown}: the root folder cannot be {thing}")
    here, real = Path.cwd().resolve(), path.resolve()
    if here == real or real in here.parents:
        raise OutputError(f"{shown}: holds the current folder, which {thing} in its place would pull away")
    return path


def _checked_target(shown: Path, may_replace: Callable[[Path], None] | None) -> Path:
    """The absolute folder `shown` names, once it is known that a results folder may go there."""
    path = replaceable_place(shown, "a results folder")
    if path.is_symlink():
        path = path.resolve()  # replace the folder the link names, keep the link
    if path.exists() and not path.is_dir():
        raise OutputError(f"{shown}: is a file, not a folder; choose another place for the results")
    if path.is_dir():
        if may_replace is not None and not os.path.ismount(path):
            may_replace(path)
        check_replaceable(path, shown, RESULTS)
    sweep_leftovers(path)
    return path


@dataclass(frozen=True)
class Replaced:
    """What is written by replacing an existing file or folder as a whole, in an error's words."""

    thing: str  # "the folder"
    writes: str  # "results are written by replacing the folder"
    instead: str  # what to give instead of a mount point, with `{shown}` for the path
    elsewhere: str  # what to give instead of what cannot be renamed


RESULTS = Replaced("the folder", "results are written by replacing the folder",
                   "give a folder inside it, e.g. {shown}/run1", "give another folder for the results")
BAG = Replaced("the bag", "a bag is written by replacing it as a whole",
               "give the bag a new name (one inside the mount, if it is a folder)", "give another path for the bag")


def check_replaceable(path: Path, shown: Path, what: Replaced) -> None:
    """Refuse an existing `path` that cannot be replaced by a rename when the work is done: a
    mount point (a Docker volume), or one that cannot be renamed, found by moving it aside and back
    at once (a mount point os.path.ismount misses, such as a bind mount within one file system,
    or an immutable folder, chattr +i). Either would fail only at the end, with the work lost."""
    mount_point = OutputError(f"{shown}: is a mount point: {what.writes}; {what.instead.format(shown=shown)}")
    if os.path.ismount(path):
        raise mount_point
    aside = _temporary(path, "old")  # a process killed in between leaves it for sweep_leftovers
    with deferred_signals():
        try:
            os.rename(path, aside)
        except OSError as err:
            if err.errno == errno.EBUSY:  # Linux's answer for a mount point
                raise mount_point from None
            raise OutputError(f"{shown}: {what.thing} cannot be replaced ({err.strerror or err}), and "
                              f"{what.writes}: {what.elsewhere}") from None
        os.rename(aside, path)


def _make_parents(folder: Path, shown: Path) -> list[Path]:
    """Make `folder` and its missing parents; returns those made, innermost first."""
    missing = []
    while not os.path.lexists(folder):
        missing.append(folder)
        folder = folder.parent
    if not folder.is_dir():
        raise OutputError(f"{shown}: {folder} is a file, not a folder")
    for made in reversed(missing):
        try:
            made.mkdir()
        except FileExistsError:
            continue
        except OSError as err:
            _remove_made([m for m in missing if m.exists()])
            raise OutputError(f"{shown}: cannot create the folder {made}: {err.strerror or err}") from None
    return missing


def _remove_made(made: list[Path]) -> None:
    for folder in made:  # innermost first; only if still empty
        with suppress(OSError):
            folder.rmdir()


def _put_in_place(staging: Path, path: Path) -> None:
    old = None
    if os.path.lexists(path):
        old = _temporary(path, "old")
        os.rename(path, old)
    pause_point("swap")  # the moment between the two renames (tests kill the run here)
    try:
        os.rename(staging, path)
    except BaseException:
        if old is not None:
            os.rename(old, path)
        raise
    fsync_dir(path.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _fsync_folder(folder: Path) -> None:
    """fsync the folder's entries (its files were fsync'ed as they were written)."""
    for sub in [folder, *(p for p in folder.rglob("*") if p.is_dir())]:
        fsync_dir(sub)


def fsync_dir(folder: Path) -> None:
    """fsync a folder's entries, where the platform allows it."""
    with suppress(OSError):  # not every platform / file system lets a folder be fsync'ed
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
