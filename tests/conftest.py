"""Shared fixtures: the real datasets (skipped with a reason when OMNITOF_DATA is unset), the
simulated corridor loop, and a place that cannot be replaced."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The folder of real public datasets ($OMNITOF_DATA); tests that need it skip without it."""
    value = os.environ.get("OMNITOF_DATA")
    if not value:
        pytest.skip("OMNITOF_DATA is not set: the real-data tests need the shared datasets folder")
    path = Path(value)
    if not path.is_dir():
        pytest.skip(f"OMNITOF_DATA={value} is not a folder")
    return path


@pytest.fixture(scope="session")
def corridor_loop():
    """The simulated corridor loop of omnitof.sim.laser2d (seed 0), with its ground truth."""
    from omnitof.sim.laser2d import make_loop_dataset

    return make_loop_dataset(seed=0)


@pytest.fixture
def unreplaceable(monkeypatch):
    """`unreplaceable(path, case)` makes `path` a place that cannot be replaced by a rename, as
    `case` says: "mount point" (os.path.ismount says so), "bind mount" (it does not, but a
    rename fails with EBUSY, as for a bind mount within one file system) or "immutable" (EPERM,
    chattr +i). Mounting and chattr need privileges that tests lack."""

    def make(path: Path, case: str) -> None:
        if case == "mount point":
            monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == path)
            return
        code = {"bind mount": errno.EBUSY, "immutable": errno.EPERM}[case]
        rename = os.rename

        def refused(src, dst):
            if Path(src) == path:
                raise OSError(code, os.strerror(code), str(src), None, str(dst))
            rename(src, dst)

        monkeypatch.setattr(os, "rename", refused)

    return make
