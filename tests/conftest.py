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


# The files whose tests take a minute or more on a 2-core machine (about so many seconds in one
# process, measured 2026-12-08), run first. The README's test command runs two workers that take tests from a
# shared queue and steal from each other's (`-n 2 --dist worksteal`); a long test that starts
# last leaves one worker running it alone while the other idles.
_LONGEST_FIRST = (
    "test_pipeline.py",  # the corridor2 sequence in full, 165
    "test_cli.py",  # the demo on the room world, 116
    "test_real_logs.py",  # Intel and Freiburg 079 mapped, 195
    "test_walls.py",  # two distance corrections fitted, 87
    "test_refine.py",  # joint calibration refinements, 90
    "test_filter3d.py",  # the 3D filter and its back end, 75
    "test_bench.py",  # experiments on Dask workers, 75
    "test_calibration.py",  # the calibration chain, 45
)


def pytest_configure(config):
    # Each of the README's two test workers keeps BLAS and the Rust core's global thread pool to
    # one thread (the filter sizes its own pools by the cores): two workers with two threads each
    # on a 2-core machine only wait for each other. Results do not depend on the thread count
    # (docs/conventions.md); the tests that check so set their counts themselves.
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ.setdefault("RAYON_NUM_THREADS", "1")
        import numpy  # noqa: F401  (threadpoolctl limits only a BLAS already loaded)
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
