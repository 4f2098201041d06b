"""Range readings from ToF frames (paper sec. III): each frame through the lens and the mirrors'
virtual cameras to 3D points, a horizontal slice of them, and 360 one-degree bins of range
(`extract`); and the ToF input of a run, bags or frames in memory to a ScanSequence with the
rig that fits them (`tof_input`)."""

from omnitof.scan.extract import (
    N_BINS,
    ScanConfigError,
    ScanExtractor,
    ScanInputError,
    ScanSettings,
    SlicePoints,
    scan_settings,
    scans_from_frames,
)

__all__ = [
    "N_BINS",
    "ScanConfigError",
    "ScanExtractor",
    "ScanInputError",
    "ScanSettings",
    "SlicePoints",
    "scan_settings",
    "scans_from_frames",
]
