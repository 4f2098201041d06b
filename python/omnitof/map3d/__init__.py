"""3D occupancy maps (paper Fig. 11(b)): a sparse log-odds voxel grid filled with every
back-projected pixel along a trajectory (`voxels`). PLY files are in `omnitof.io.ply`, the
figures in `omnitof.viz.map3d`."""

from omnitof.map3d.voxels import (
    DEFAULT_L_FREE,
    DEFAULT_L_MAX,
    DEFAULT_L_MIN,
    DEFAULT_L_OCC,
    DEFAULT_MAX_RANGE,
    DEFAULT_OCCUPIED_THRESHOLD,
    DEFAULT_RESOLUTION,
    IntegrateStats,
    Map3DError,
    VoxelMap,
    backproject_frame,
    build_voxel_map,
    surface_distance,
    transform_points,
    voxel_map_from_clouds,
)

__all__ = [
    "DEFAULT_L_FREE",
    "DEFAULT_L_MAX",
    "DEFAULT_L_MIN",
    "DEFAULT_L_OCC",
    "DEFAULT_MAX_RANGE",
    "DEFAULT_OCCUPIED_THRESHOLD",
    "DEFAULT_RESOLUTION",
    "IntegrateStats",
    "Map3DError",
    "VoxelMap",
    "backproject_frame",
    "build_voxel_map",
    "surface_distance",
    "transform_points",
    "voxel_map_from_clouds",
]
