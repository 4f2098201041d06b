"""omnitof: an omnidirectional time-of-flight range sensor and particle-filter SLAM.

One folder per stage of the data flow (docs/layout.md): sensor → io → sim → calibration →
scan → slam → map3d → eval → viz, with `cli`, `demo` and `results` on top. The compiled core
(`omnitof._core`) is private; use the Python modules of this package.
"""

from omnitof import _moved

__version__ = "0.2.0"

_moved.install()
