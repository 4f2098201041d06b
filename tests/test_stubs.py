"""The hand-written stubs of the compiled core (python/omnitof/_core.pyi) match the module."""

from __future__ import annotations

import subprocess
import sys


def test_core_stubs_match_the_compiled_module():
    run = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "omnitof._core"], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stdout + run.stderr
