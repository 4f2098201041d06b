# Type stubs of the compiled core (rust/src/lib.rs). Private: use omnitof.slam and friends.
from typing import Any, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "OccupancyGrid",
    "ParticleFilter",
    "ParticleFilter3D",
    "Submap",
    "VoxelGrid",
    "beam_likelihood",
    "low_variance_resample",
    "neff",
    "rvl_decode",
    "rvl_encode",
    "sample_motion_odometry",
]

_F64 = npt.NDArray[np.float64]
_F32 = npt.NDArray[np.float32]
_U64 = npt.NDArray[np.uint64]
_I64 = npt.NDArray[np.int64]
_U32 = npt.NDArray[np.uint32]

@final
class ParticleFilter:
    # Each section is the dict `SlamConfig.<section>.model_dump()` (python/omnitof/slam/config.py),
    # `filter` without linear_update and angular_update_deg; the core checks the keys.
    def __new__(
        cls,
        *,
        filter: dict[str, Any],
        motion: dict[str, Any],
        sensor_model: dict[str, Any],
        likelihood_field: dict[str, Any],
        scan_matcher: dict[str, Any],
        map: dict[str, Any],
        angles: _F64,
        sensor_pose: _F64,
        scan_max_range: float,
    ) -> ParticleFilter: ...
    # angles: this scan's own beam bearings (one per range) where the geometry varies; None: the filter's.
    def step(
        self, odom_prev: _F64, odom_cur: _F64, ranges: _F32, scan: int, angles: _F64 | None = None
    ) -> tuple[float, bool, bool]: ...
    def match_scan(
        self, start: _F64, ranges: _F32, angles: _F64 | None = None
    ) -> tuple[list[float], float] | None: ...
    # odometry (M+1, 3), ranges (M, B) padded with +inf, angles (M, B) or None: poses relative to
    # the best particle's (M, 3) and whether each match stood (M,); None before the first scan.
    def match_scans(
        self, odometry: _F64, ranges: _F32, min_matched: float, angles: _F64 | None = None
    ) -> tuple[_F64, npt.NDArray[np.bool_]] | None: ...
    def best_pose(self) -> _F64 | None: ...
    def reset(self, pose: _F64, scan: int, grid: OccupancyGrid) -> None: ...
    def best_trajectory(self) -> tuple[_U64, _F64]: ...
    def best_map(self) -> tuple[_F32, int, int]: ...
    def map_of(self, index: int) -> tuple[_F32, int, int]: ...
    def poses(self) -> _F64: ...
    def log_weights(self) -> _F64: ...
    def tile_counts(self) -> tuple[int, int]: ...
    @staticmethod
    def tile_bytes() -> int: ...
    @property
    def steps(self) -> int: ...
    @property
    def resamplings(self) -> int: ...
    @property
    def fallbacks(self) -> int: ...

@final
class OccupancyGrid:
    def __new__(cls, resolution: float, l_occ: float, l_free: float, l_min: float, l_max: float) -> OccupancyGrid: ...
    def integrate(
        self,
        robot_pose: _F64,
        angles: _F64,
        ranges: _F32,
        max_range: float,
        clear_no_echo: bool = False,
        sensor_pose: _F64 | None = None,
        once_per_scan: bool = False,
    ) -> None: ...
    def to_dense(self) -> tuple[_F32, int, int]: ...
    def match_scan(
        self,
        start: _F64,
        angles: _F64,
        ranges: _F32,
        *,
        sensor_pose: _F64 | None = None,
        sigma: float = 0.05,
        window: int = 3,
        max_range: float = 20.0,
        occupied_threshold: float = 0.0,
        step_xy: float = 0.05,
        step_theta: float = 0.035,
        refinements: int = 3,
        gauss_newton: int = 10,
    ) -> tuple[list[float], float]: ...
    def match_best(
        self,
        starts: _F64,
        angles: _F64,
        ranges: _F32,
        *,
        sensor_pose: _F64 | None = None,
        sigma: float = 0.05,
        window: int = 3,
        max_range: float = 20.0,
        occupied_threshold: float = 0.0,
        step_xy: float = 0.05,
        step_theta: float = 0.035,
        refinements: int = 3,
        gauss_newton: int = 10,
        threads: int | None = None,
    ) -> tuple[list[float], float]: ...
    def match_each(
        self,
        starts: _F64,
        ranges: _F32,
        angles: _F64,
        *,
        sensor_pose: _F64 | None = None,
        sigma: float = 0.05,
        z_hit: float = 0.9,
        z_rand: float = 0.1,
        window: int = 3,
        fit_walls: bool = False,
        max_range: float = 20.0,
        occupied_threshold: float = 0.0,
        beam_stride: int = 1,
        gauss_newton: int = 10,
        threads: int | None = None,
    ) -> tuple[_F64, _F64]:
        """Every scan re-posed in this map by Gauss-Newton from its row of `starts`: (poses
        (N, 3), share of end points near an obstacle (N,)); `angles` (B,) or (N, B)."""
    def expected_ranges(self, sensor_pose: _F64, angles: _F64, max_range: float, occupied_threshold: float) -> _F64: ...

@final
class Submap:
    def __new__(
        cls,
        resolution: float,
        l_occ: float,
        l_free: float,
        l_min: float,
        l_max: float,
        max_range: float,
        *,
        clear_no_echo: bool = False,
        once_per_scan: bool = False,
        unknown_probability: float = ...,
        depth: int = ...,
        spread_sigma: float = 0.0,
        threads: int | None = None,
    ) -> Submap: ...
    def insert(self, pose: _F64, ranges: _F32, angles: _F64, sensor_pose: _F64 | None = None) -> None: ...
    def finish(self) -> None: ...
    def release_grids(self) -> None: ...
    @property
    def has_grids(self) -> bool: ...
    @staticmethod
    def max_side_cells() -> float: ...
    @property
    def finished(self) -> bool: ...
    @property
    def num_scans(self) -> int: ...
    @property
    def origin(self) -> _F64 | None: ...
    @property
    def resolution(self) -> float: ...
    def memory_bytes(self) -> int: ...
    def to_dense(self) -> tuple[_F32, int, int]: ...
    def match_scan(
        self,
        ranges: _F32,
        angles: _F64,
        initial_pose: _F64,
        linear_window: float,
        angular_window: float,
        min_score: float,
        sensor_pose: _F64 | None = None,
        refine: bool = True,
        field_sigma: float | None = None,
    ) -> tuple[_F64, float, _F64] | None: ...

@final
class VoxelGrid:
    def __new__(
        cls, resolution: float, l_occ: float, l_free: float, l_min: float, l_max: float, threads: int | None = None
    ) -> VoxelGrid: ...
    @property
    def resolution(self) -> float: ...
    def integrate(self, origins: _F64, endpoints: _F64, max_range: float) -> tuple[int, int, int, int, int]: ...
    def occupied(self, threshold: float = 0.0) -> _F64: ...
    def observed(self) -> tuple[_I64, _F32]: ...
    def log_odds_at(self, points: _F64) -> _F64: ...
    def voxel_count(self) -> int: ...
    def block_count(self) -> int: ...
    def memory_bytes(self) -> int: ...
    def bounds(self) -> tuple[list[float], list[float]] | None: ...

# The 3D filter (rust/src/filter3d.rs, filter3d_bindings.rs); its driver is omnitof.slam.filter3d.
# Sections as ParticleFilter's, plus `filter3d` (less enabled, pixel_stride, project_z_*).
@final
class ParticleFilter3D:
    def __new__(
        cls,
        *,
        filter: dict[str, Any],
        motion: dict[str, Any],
        sensor_model: dict[str, Any],
        likelihood_field: dict[str, Any],
        scan_matcher: dict[str, Any],
        map: dict[str, Any],
        filter3d: dict[str, Any],
    ) -> ParticleFilter3D: ...
    # origins, endpoints (N, 3) robot frame: (Neff, resampled, scan-match fallbacks, rays scored,
    # odometry replaced by the odometry check).
    def step(
        self, odom_prev: _F64, odom_cur: _F64, origins: _F64, endpoints: _F64, scan: int
    ) -> tuple[float, bool, int, int, bool]: ...
    # Mean log-likelihood and matched end points at each pose (K, 3) in particle `index`'s map.
    def score(self, index: int, poses: _F64, endpoints: _F64) -> tuple[_F64, _U64]: ...
    # Every particle at `pose` on one map of the frames clouds[k] ((M, 6) float32, robot frame)
    # written at poses[k] (K, 3): the back end's correction fed back.
    def reset(self, pose: _F64, scan: int, poses: _F64, clouds: list[_F32]) -> None: ...
    def best_pose(self) -> _F64 | None: ...
    def best_trajectory(self) -> tuple[_U64, _F64]: ...
    def map(self, index: int | None = None) -> VoxelGrid: ...
    def poses(self) -> _F64: ...
    def log_weights(self) -> _F64: ...
    def block_counts(self, indices: list[int] | None = None) -> tuple[int, int]: ...
    @staticmethod
    def block_bytes() -> int: ...
    @property
    def steps(self) -> int: ...
    @property
    def resamplings(self) -> int: ...
    @property
    def fallbacks(self) -> int: ...
    @property
    def resolution(self) -> float: ...

# Private: the renderer behind omnitof.sim.render.Renderer (rust/src/render_bindings.rs).
@final
class _Renderer:
    def __new__(
        cls,
        *,
        walls: _F64,
        wall_materials: _U32,
        boxes: _F64,
        box_materials: _U32,
        materials: _F64,
        floor_material: int,
        ceiling_material: int,
        ceiling_height: float,
        cell: float,
        directions: _F64,
        height: int,
        width: int,
        sub_rays: int,
        mirror_planes: _F64,
        mirror_vertices: _F64,
        mirror_counts: _U64,
        mirror_reflectivity: _F64,
        robot_T_camera: _F64,
        f_mod: float,
        amplitude_at_1m: float,
        max_bounces: int,
        min_gain: float,
        threads: int | None = None,
        leds: _F64 | None = None,
        led_profile_exponent: float = 0.0,
        led_half_angle_deg: float = 180.0,
        multipath_rays: int = 0,
        multipath_window: int = 0,
        seed: int = 0,
    ) -> _Renderer: ...
    def render(self, poses: _F64, keys: _F64 | None = None) -> _F32: ...
    # Frames from images of `render` (rust/src/tof_frames.rs): samples (N, 4, H, W), distance,
    # amplitude, offset (N, H, W) and saturated (N, H, W).
    def frames(
        self,
        phasor: _F32,
        active: _F32,
        ambient: _F32,
        first: _U64,
        per_sample: npt.NDArray[np.bool_],
        seeds: _U64,
        *,
        electrons_per_unit: float,
        read_noise: float,
        full_well: float,
        harmonics: tuple[float, float] | None = None,
        amplitude_offset: tuple[float, float] | None = None,
        fixed_pattern: _F64 | None = None,
    ) -> tuple[_F32, _F32, _F32, _F32, npt.NDArray[np.bool_]]: ...
    def cast(self, origins: _F64, directions: _F64) -> tuple[_F64, _I64]: ...
    @property
    def shape(self) -> tuple[int, int, int]: ...

# The multipath compensation of the scan extraction (rust/src/multipath.rs); its Python face is
# omnitof.scan.multipath.MultipathCompensation.
@final
class _MultipathCompensator:
    def __new__(
        cls,
        *,
        width: int,
        height: int,
        origins: _F64,
        directions: _F64,
        paths: _F64,
        labels: npt.NDArray[np.int32],
        solid_angles: _F64,
        emission: _F64,
        source_gain: _F64,
        targets: _U32,
        windows: _F64,
        k: float,
        amplitude_at_1m: float,
        mirror_reflectivity: float,
        stride: int,
        target_stride: int,
        normal_radius: int,
        smooth_radius: int,
        depth_tolerance: float,
        min_reflectance: float,
        min_cos: float,
        min_separation: float,
        max_ratio: float,
        visibility: bool = False,
        beyond_origins: _F64 | None = None,
        beyond_directions: _F64 | None = None,
        beyond_paths: _F64 | None = None,
        beyond_anchors: _U32 | None = None,
        beyond_factors: _F64 | None = None,
        threads: int | None = None,
    ) -> _MultipathCompensator: ...
    def correct(self, distances: _F32, amplitudes: _F32) -> _F32: ...

def sample_motion_odometry(
    pose: _F64, odom_prev: _F64, odom_cur: _F64, alphas: list[float], n: int, seed: int
) -> _F64: ...
def beam_likelihood(
    z: _F64,
    z_star: float,
    *,
    z_hit: float,
    z_short: float,
    z_max: float,
    z_rand: float,
    sigma_hit: float,
    lambda_short: float,
    max_range: float,
) -> _F64: ...
def neff(weights: _F64) -> float: ...
def low_variance_resample(weights: _F64, seed: int) -> _U64: ...
def rvl_decode(data: npt.NDArray[np.uint8], pixels: int) -> npt.NDArray[np.uint16]: ...
def rvl_encode(pixels: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint8]: ...
