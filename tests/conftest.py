"""Shared fixtures: the real datasets (skipped with a reason when OMNITOF_DATA is unset) and the
simulated corridor loop."""

from __future__ import annotations

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
