"""Old module names that scripts written against omnitof 0.1 import, kept working.

omnitof 0.2 put each stage of the data flow into its own folder (docs/layout.md), so some
modules moved: `omnitof.tof` is now `omnitof.sensor.tof`, and so on (`MOVED`). A finder on
`sys.meta_path` answers an import of an old name with the module at its new place: the very
same module object, so `omnitof.tof.decode is omnitof.sensor.tof.decode`. Only the names in
`MOVED` are handled; nothing is imported before it is asked for. Figures moved to
`omnitof.viz` and PLY files to `omnitof.io.ply` are not aliased: import them from there.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from types import ModuleType

MOVED = {
    "omnitof.tof": "omnitof.sensor.tof",
    "omnitof.camera": "omnitof.sensor.camera",
    "omnitof.mirrors": "omnitof.sensor.mirrors",
    "omnitof.design": "omnitof.sensor.design",
    "omnitof.config": "omnitof.slam.config",
    "omnitof.timing": "omnitof.slam.timing",
    "omnitof.tofscans": "omnitof.scan.tof_input",
}


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, name: str, path: object = None, target: object = None):
        if name not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(name, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        # The module at its new place: the import system files it under the old name too.
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module: ModuleType) -> None:
        """Nothing to run: the module executed when it was imported under its new name."""


def install() -> None:
    """Put the finder on sys.meta_path once."""
    if not any(isinstance(f, _Alias) for f in sys.meta_path):
        sys.meta_path.append(_Alias())
