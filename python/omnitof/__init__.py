"""omnitof: an omnidirectional time-of-flight range sensor and particle-filter SLAM.

The compiled core (`omnitof._core`) is private; use the Python modules of this package.
"""

__version__ = "0.1.0"
