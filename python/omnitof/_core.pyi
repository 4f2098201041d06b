# Type stubs of the compiled core (rust/src/lib.rs). Private: use omnitof.slam and friends.
from typing import final

import numpy as np
import numpy.typing as npt

__all__ = [
    "OccupancyGrid",
    "ParticleFilter",
    "VoxelGrid",
    "beam_likelihood",
    "low_variance_resample",
    "neff",
    "sample_motion_odometry",
]

_F64 = npt.NDArray[np.float64]
_F32 = npt.NDArray[np.float32]
_U64 = npt.NDArray[np.uint64]
_I64 = npt.NDArray[np.int64]

@final
class ParticleFilter:
    def __new__(
        cls,
        *,
        n_particles: int,
        seed: int,
        threads: int,
        alphas: list[float],
        z_hit: float,
        z_short: float,
        z_max: float,
        z_rand: float,
        sigma_hit: float,
        lambda_short: float,
        max_range: float,
        occupied_threshold: float,
        beam_stride: int,
        effective_beams: float,
        l_occ: float,
        l_free: float,
        l_min: float,
        l_max: float,
        resolution: float,
        map_max_range: float,
        clear_no_echo: bool,
        resample_threshold: float,
        angles: _F64,
        sensor_pose: _F64,
        proposal: str,
        observation: str,
        field_sigma: float,
        field_z_hit: float,
        field_z_rand: float,
        field_window: int,
        field_fit_walls: bool = False,
        match_step_xy: float,
        match_step_theta: float,
        match_refinements: int,
        match_gauss_newton: int,
        match_sample_xy: float,
        match_sample_theta: float,
        match_min_matched: float,
        match_odometry_prior: bool,
        match_climb_from_sample: bool = False,
        search_xy: float = 0.0,
        search_theta: float = 0.0,
        search_step_xy: float = 0.1,
        search_step_theta: float = 0.0175,
        search_below: float = 0.8,
    ) -> ParticleFilter: ...
    def step(self, odom_prev: _F64, odom_cur: _F64, ranges: _F32, scan: int) -> tuple[float, bool, bool]: ...
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
    def expected_ranges(self, sensor_pose: _F64, angles: _F64, max_range: float, occupied_threshold: float) -> _F64: ...

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
