"""The typed configuration of a SLAM run: YAML in, YAML out, every field documented.

One pydantic model per stage. Angles are in degrees here (the user's edge) and in radians
everywhere inside. A configuration file may give only some fields; the others keep their
defaults. Presets live in `omnitof/presets/*.yaml` and are loaded by name.

The Rust core reads every section as a dict, field by field (`config_section!` in
rust/src/lib.rs), and refuses a key it does not know: a new option is a field here plus the
same field there (and its use). Only the scan selection (`filter.linear_update`,
`filter.angular_update_deg`) stays in Python (omnitof.slam.driver).
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Iterator, Mapping
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import ConfigDict, Field, ValidationError, model_validator

from omnitof.settings_model import SettingsModel
from omnitof.errors import ConfigError, dump_yaml, load_yaml, yaml_problem
from omnitof.io.text import shorten
from omnitof.scan.extract import ScanSettings

# libyaml's emitter where PyYAML has it (the same text, 4x faster: `omnitof bench` writes one
# configuration per run to compare it with a resumed run's).


# Every number has its real domain here, not only its sign: a value outside it would not
# describe a sensor, a robot or a map (an alpha of 1e9, a 1 µm cell), and some would make the
# core run for ever or ask for terabytes. NaN and infinity are refused everywhere
# (allow_inf_nan). Whole numbers that the core reads as u32, usize or i32 are bounded so that
# they fit. How much memory a configuration needs for a given log is checked before a run
# (omnitof.slam.limits).
MAX_LOG_ODDS = 100.0  # a probability of 1 - 4e-44: certainty, far beyond any useful clamp
MAX_SEARCH_POSES = 1e6  # 70 times the laser180-scanmatch preset's wide search (13 671 poses)


class _Section(SettingsModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class MotionConfig(_Section):
    """Odometry motion model (Probabilistic Robotics, sample_motion_model_odometry).

    The alphas are variances: rotation noise variance = alpha1·rot² + alpha2·trans², translation
    noise variance = alpha3·trans² + alpha4·(rot1² + rot2²) (rot in rad, trans in m). At most 10:
    a noise three times the motion itself is no longer odometry.
    """

    alpha1: float = Field(0.05, ge=0, le=10, description="rotation variance per squared rotation (rad²/rad²)")
    alpha2: float = Field(0.01, ge=0, le=10, description="rotation variance per squared translation (rad²/m²)")
    alpha3: float = Field(0.02, ge=0, le=10, description="translation variance per squared translation (m²/m²)")
    alpha4: float = Field(0.01, ge=0, le=10, description="translation variance per squared rotation (m²/rad²)")


class SensorModelConfig(_Section):
    """Observation model p(z | m, x) that weighs particles drawn from the odometry proposal.

    `model: beam` is the paper's beam model (Probabilistic Robotics, section 6.3) with the
    mixture below; `model: likelihood_field` scores beam end points by their distance to the
    nearest obstacle (section 6.4, parameters in the `likelihood_field` section), smoother and
    cheaper. The scan-matching proposal always matches against the likelihood field.
    """

    model: Literal["beam", "likelihood_field"] = Field("beam", description="observation model: beam | likelihood_field")
    z_hit: float = Field(0.8, ge=0, description="weight of the Gaussian hit part")
    z_short: float = Field(0.05, ge=0, description="weight of the exponential short-reading part")
    z_max: float = Field(0.05, ge=0, description="weight of the max-reading point mass")
    z_rand: float = Field(0.1, ge=0, description="weight of the uniform random part")
    sigma_hit: float = Field(0.1, ge=0.001, le=10, description="standard deviation of the hit part (m)")
    lambda_short: float = Field(0.5, gt=0, le=1000, description="rate of the short-reading part (1/m)")
    max_range: float = Field(15.0, gt=0, description="largest range the model scores (m); longer readings are left out")
    beam_stride: int = Field(2, ge=1, le=100_000, description="score every n-th beam")
    effective_beams: float = Field(
        9.0, gt=0, le=100_000,
        description="a scan's log-likelihood is the mean over its scored beams times this: the scan counts as "
        "this many independent beams, which tempers the overconfidence of treating real beams as independent",
    )

    @model_validator(mode="after")
    def _weights_sum_to_one(self) -> "SensorModelConfig":
        total = self.z_hit + self.z_short + self.z_max + self.z_rand
        if not math.isclose(total, 1.0, abs_tol=1e-6):
            raise ValueError(f"z_hit + z_short + z_max + z_rand must be 1, got {total:g}")
        return self


class LikelihoodFieldConfig(_Section):
    """Likelihood field: p = z_hit·N(d; 0, sigma) + z_rand/max_range for an end point at
    distance d from the nearest occupied cell, searched up to window_cells cells away."""

    sigma: float = Field(0.05, ge=0.001, le=10, description="standard deviation of the end-point distance (m)")
    z_hit: float = Field(0.9, ge=0, le=1, description="weight of the Gaussian part")
    z_rand: float = Field(
        0.1, gt=0, le=1,
        description="weight of the uniform part (above 0: without it one reading far from every wall rules a pose out)",
    )
    window_cells: int = Field(3, ge=1, le=20, description="how far (cells) to search for the nearest obstacle")
    fit_walls: bool = Field(
        False,
        description="measure d to the wall fitted through the mean end points around the nearest obstacle "
        "(weighted by their end-point counts) instead of to the nearest mean end point, and let the Gaussian "
        "fall continuously to the floor at window_cells: the nearest point alone lies up to half a cell off "
        "along the wall and, as the beams clear the cells in front of a surface, behind it, which biases "
        "scan matching forward and scatters its heading (about 1 % stretch and 1° heading drift over the "
        "simulated corridor loop); set for sim2d, not (yet) tuned for the other presets",
    )


class ScanMatcherConfig(_Section):
    """The scan-matching proposal (Grisetti, Stachniss & Burgard 2007): hill climbing on the
    likelihood field from the odometry prediction, then a Gaussian fitted to the target at the
    3×3×3 poses around the mode."""

    step_xy: float = Field(0.05, gt=0, le=10, description="initial hill-climbing step in x and y (m)")
    step_deg: float = Field(2.0, gt=0, le=180, description="initial hill-climbing step in heading (deg)")
    refinements: int = Field(3, ge=0, le=20, description="how often the hill-climbing steps are halved")
    gauss_newton: int = Field(
        10, ge=0, le=100, description="Gauss-Newton iterations on the likelihood field after the hill climbing"
    )
    sample_xy: float = Field(0.01, gt=0, le=10, description="spacing in x and y of the poses the Gaussian is fitted to (m)")
    sample_deg: float = Field(0.25, gt=0, le=180, description="spacing in heading of those poses (deg)")
    odometry_prior: bool = Field(
        False,
        description="climb to the mode of likelihood × odometry prior instead of the likelihood alone: "
        "better where scans are ambiguous and odometry good, worse where odometry is poor",
    )
    prior_dof: float = Field(
        0.0, ge=0, le=1e6,
        description="the odometry prior (the climb's with odometry_prior, and always the proposal Gaussian's and the "
        "weight's) as a Student-t on the pose with this many degrees of freedom (0: a Gaussian): "
        "heavy-tailed, it holds the pose where the scan cannot (along a corridor the laser sees no end of) and "
        "gives way where the scan puts the pose many of the motion model's standard deviations from the "
        "wheels (a wheel that slips in a turn; a Gaussian prior there bent Freiburg 079's map by 30°); "
        "laser180-scanmatch takes 3",
    )
    min_matched: float = Field(
        0.5, ge=0, le=1,
        description="fall back to the odometry proposal when fewer end points than this share lie near an obstacle",
    )
    fallback: Literal["draw", "prediction"] = Field(
        "draw",
        description="a particle's pose where its match falls back (min_matched): a draw from the motion model (as "
        "GMapping does, and as the paper's filter always does), or the odometry's prediction; a scan too poor to "
        "match cannot tell the draws apart, so drawing adds the motion model's noise to the trajectory, but it "
        "keeps the particles apart at a wheel glitch that nothing else catches (presets laser180-scanmatch and "
        "tof-scanmatch take prediction; BENCHMARKS.md measures both against a glitch)",
    )
    climb_from_sample: bool = Field(
        False,
        description="start each particle's climb at a pose drawn from the odometry motion model instead of at "
        "the odometry prediction (as GMapping does): where the scan pins the pose down every start climbs to the "
        "same mode, where it does not (along a corridor) the particles keep the motion model's spread, "
        "which is what lets a later loop closure find the right one",
    )
    search_xy: float = Field(
        0.0, ge=0, le=5,
        description="check the odometry before each step with a wide correlative search of this half-width (m) "
        "on the best particle's map, and replace the step's odometry increment by the match found where "
        "it explains clearly more of the scan; catches wheel odometry glitches larger than the hill "
        "climbing can undo; the 3D filter searches its map's occupied columns between filter3d.project_z_min "
        "and project_z_max and judges the result in 3D; 0 = off",
    )
    search_deg: float = Field(15.0, ge=0, le=180, description="half-width of the wide search in heading (deg)")
    search_step_xy: float = Field(
        0.1, ge=0.005, le=5, description="spacing of the wide search's poses in x and y (m)"
    )
    search_step_deg: float = Field(
        1.0, ge=0.05, le=180, description="spacing of the wide search's poses in heading (deg)"
    )
    search_below: float = Field(
        0.8, ge=0, le=1,
        description="run the wide search only when fewer than this share of end points lie near an obstacle "
        "after the local match from the odometry, and (unless search_accept says otherwise) take its pose only "
        "where at least this share does (where no pose explains the scan, people beside the robot or open "
        "doors, a jump is as likely wrong)",
    )
    search_accept: float | None = Field(
        None, ge=0, le=1,
        description="take the wide search's pose only where at least this share of end points lie near an "
        "obstacle; None = search_below. Apart from search_below where a glitch leaves most of a scan on the "
        "map (tof3d: a 3D frame in a corridor keeps 0.85 of its rays on the side walls after a 0.6 m slip, so "
        "the search starts below 0.9, but after a glitch in the simulated room the right pose explains 0.8-0.9 of "
        "them and waited 13-103 scans for a frame that passed 0.9)",
    )
    search_distinct: float = Field(
        0.0, ge=0, le=1,
        description="take the wide search's pose only where it stands out: its score above the best of every "
        "position more than 3 search steps from it, as a share of the scan's end points (rust/src/correlative.rs, "
        "Found::distinct), is at least this; along a bare corridor, where the scan cannot tell one place from the "
        "next, it is near 0 and the odometry stands; 0 = any pose that passes search_below",
    )
    search_min_points: int = Field(
        20, ge=0, le=100_000,
        description="run the wide search only on scans of at least this many end points (after "
        "sensor_model.beam_stride; for the 3D filter, rays at the check's heights): on fewer, one end point "
        "is a twentieth or more of every share the check judges by, and a few points fit some wall within "
        "a metre by chance (a ToF scan of one reading in a bare corridor jumped the office 1 m); 0 = any",
    )

    @model_validator(mode="after")
    def _search_is_finite_work(self) -> "ScanMatcherConfig":
        # Every pose of the wide search costs a raster read per end point, at every scan it runs.
        n_xy = 2 * round(self.search_xy / self.search_step_xy) + 1
        n_th = 2 * round(self.search_deg / self.search_step_deg) + 1
        if self.search_xy > 0 and n_xy * n_xy * n_th > MAX_SEARCH_POSES:
            raise ValueError(
                f"the wide search would score {n_xy * n_xy * n_th:.3g} poses per scan (search_xy / "
                f"search_step_xy, search_deg / search_step_deg), more than {MAX_SEARCH_POSES:.0e}: "
                "widen the steps or narrow the window"
            )
        return self


class MapConfig(_Section):
    """Log-odds occupancy grid and its inverse sensor model (paper eq. 8)."""

    resolution: float = Field(
        0.05, ge=0.001, le=1,
        description="cell size (m); at least 1 mm, finer than any range sensor resolves (how much memory a "
        "resolution needs for a log is checked before the run)",
    )
    l_occ: float = Field(0.9, gt=0, le=MAX_LOG_ODDS, description="log-odds added to the cell that holds a beam's end point")
    l_free: float = Field(-0.4, lt=0, ge=-MAX_LOG_ODDS, description="log-odds added to every cell a beam passes through")
    l_min: float = Field(-2.0, lt=0, ge=-MAX_LOG_ODDS, description="lower clamp of a cell's log-odds")
    l_max: float = Field(3.5, gt=0, le=MAX_LOG_ODDS, description="upper clamp of a cell's log-odds")
    occupied_threshold: float = Field(
        0.0, description="log-odds above which a cell is an obstacle for the beam model's ray casting "
        "(within [l_min, l_max): else no cell, or every cell, would ever be one)"
    )
    max_range: float = Field(20.0, gt=0, description="readings beyond this (m) clear free space only")
    clear_no_echo: bool = Field(False, description="let no-echo beams clear free space up to max_range")
    footprint_radius: float = Field(
        0.0, ge=0, le=10,
        description="the robot's radius (m): in the map written at the end, every cell within it of the "
        "trajectory that holds no obstacle is free (the robot drove there; a sensor blind around its own "
        "base otherwise leaves unknown holes along the path; omnitof.slam.footprint). 0: off",
    )
    once_per_scan: bool = Field(
        False, description="update each cell at most once per scan: l_occ where a beam ends, else l_free where any "
        "passes (Cartographer's inserter); off: once per beam, the paper's eq. 8 as written",
    )
    max_beams: int = Field(
        8192, ge=1, le=100_000_000,
        description="scans with more beams are thinned before the filter: one beam per cell of half the "
        "resolution over their end points, then evenly to this many (omnitof.slam.thinning)",
    )
    thin_beams: Literal["dense", "always", "off"] = Field(
        "dense", description="which scans are thinned: those with more than max_beams beams (dense), every scan "
        "to one beam per end-point cell of half the resolution (always), or none (off)",
    )

    @model_validator(mode="after")
    def _threshold_within_the_clamp(self) -> "MapConfig":
        if not self.l_min <= self.occupied_threshold < self.l_max:
            raise ValueError(
                f"occupied_threshold {self.occupied_threshold:g} must lie in [l_min, l_max) = "
                f"[{self.l_min:g}, {self.l_max:g})"
            )
        return self


class FilterConfig(_Section):
    """The Rao-Blackwellized particle filter (paper section IV)."""

    particles: int = Field(30, ge=1, le=100_000, description="number of particles")
    proposal: Literal["odometry", "scanmatch"] = Field(
        "odometry", description="odometry: the paper's proposal; scanmatch: Grisetti et al. 2007"
    )
    resample_threshold: float = Field(
        0.5, gt=0, le=1, description="resample when Neff (eq. 10) falls below this fraction of the particles"
    )
    linear_update: float = Field(0.5, ge=0, description="integrate a scan after the robot moved this far (m)")
    match_between: bool = Field(
        False,
        description="pose every scan between integrated ones by one local match in the best map (else by odometry)",
    )
    final_match_passes: int = Field(
        0, ge=0, le=10,
        description="when the run is over, pose every scan once more by one local match in the finished map "
        "(built from the final, optimised poses), from the pose the run gave it, this many times, the map "
        "rebuilt from the new poses between passes and at the end; where too few of a scan's end points find "
        "the map (scan_matcher.min_matched) its pose stands (omnitof.slam.final_match). 0: off",
    )
    angular_update_deg: float = Field(25.0, ge=0, description="... or turned this much (deg)")
    moving_lookback: float = Field(
        0.0, ge=0, le=100,
        description="drop the readings of things that move before the filter sees them: a reading whose end "
        "point lies where the scan this many metres of odometry path before it saw through (by more than "
        "moving_margin, in a run of at least 3 neighbouring beams) reads as no echo (omnitof.slam.moving); "
        "people walking beside the robot otherwise drag the map along the corridor. 0: off",
    )
    moving_margin: float = Field(
        0.3, gt=0, le=10,
        description="how much farther (m) the earlier scan must have seen for a reading to count as moving",
    )
    seed: int = Field(0, ge=0, lt=2**63, description="seed of every random draw; same seed, same map")
    threads: int = Field(
        0, ge=0, le=1024, description="worker threads; 0 uses every core, more than the cores are the cores, with a warning "
        "(omnitof.slam.limits.within_cores); results do not depend on it"
    )


class BackendConfig(_Section):
    """The pose-graph back end behind the filter (Hess et al., ICRA 2016; omnitof.slam.backend).

    Every `submap_length` metres of the front end's trajectory closes a submap, a local grid of
    the scans integrated meanwhile. Each integrated scan is searched in the finished submaps
    near it by branch and bound (`linear_window`, `angular_window_deg`), and a match scoring at
    least `min_score` becomes a loop-closure edge of a pose graph whose nodes are the
    integrated scans and whose other edges are the front end's own motions. GTSAM optimises
    the graph (Levenberg-Marquardt) with a robust kernel on the closures, so that a false one
    cannot bend the map; where the optimum moves the robot's pose by more than `feedback_xy`
    or `feedback_deg`, the filter continues from the corrected pose and a map rebuilt from the
    optimised poses. The map written at the end is built from the optimised poses.
    """

    enabled: bool = Field(False, description="run the pose-graph back end")
    submap_length: float = Field(
        6.0, ge=0.1, le=1000, description="metres of trajectory per submap: long enough to hold a corner, short enough to stay straight"
    )
    search_every: int = Field(3, ge=1, description="search loop closures from every n-th integrated scan")
    search_radius: float = Field(
        10.0, gt=0, description="search the submaps whose centre lies within this (m) of the scan's estimated pose"
    )
    linear_window: float = Field(
        2.5, gt=0, le=50, description="half-width (m) of the search window around the estimated pose"
    )
    angular_window_deg: float = Field(25.0, gt=0, le=180, description="half-width (deg) of the search window's heading")
    min_score: float = Field(
        0.65, gt=0, lt=1, description="accept a match whose mean end-point occupancy probability reaches this"
    )
    max_closures_per_scan: int = Field(1, ge=1, description="search at most this many submaps (the nearest) per scan")
    skip_recent_submaps: int = Field(
        1, ge=0, description="never search the submap being built nor this many finished ones before it"
    )
    global_search_after: int = Field(
        0, ge=0, description="after this many integrated scans without a closure, search all submaps (0: never)"
    )
    global_min_score: float = Field(0.7, gt=0, lt=1, description="min_score of the global search")
    search_grids_kept: int = Field(
        64, ge=1,
        description="finished submaps whose branch-and-bound grids stay in memory, the most recently searched; "
        "the others drop them and make them again when next searched (tens of ms each). The grids cost about "
        "three times their submap: a long log kept them all (the Freiburg hospital log's 209 submaps: 1.4 GB)",
    )
    odometry_sigma_xy: float = Field(0.005, gt=0, description="front-end edge: position sigma (m) plus ...")
    odometry_sigma_xy_per_m: float = Field(0.01, ge=0, description="... this much per metre moved")
    odometry_sigma_deg: float = Field(0.1, gt=0, description="front-end edge: heading sigma (deg) plus ...")
    odometry_sigma_deg_per_m: float = Field(0.2, ge=0, description="... this much per metre moved")
    closure_sigma_xy_min: float = Field(0.02, gt=0, description="smallest position sigma (m) of a closure edge")
    closure_sigma_deg_min: float = Field(0.5, gt=0, description="smallest heading sigma (deg) of a closure edge")
    robust_kernel: Literal["cauchy", "huber", "none"] = Field(
        "cauchy", description="M-estimator on closure edges: cauchy | huber | none"
    )
    kernel_width: float = Field(1.0, gt=0, le=1000, description="the kernel's width, in standard deviations of the closure")
    optimize_every: int = Field(
        20, ge=1, description="optimise at most every n-th integrated scan, when a new closure disagrees with the estimate"
    )
    feedback_xy: float = Field(0.25, ge=0, description="feed the correction back when it moves the pose this far (m) ...")
    feedback_deg: float = Field(2.5, ge=0, description="... or turns it this much (deg)")
    relocalisation_margin: float | None = Field(
        0.1, ge=0, le=1,
        description="a correction of the odometry check (scan_matcher.search_below) counts as a relocalisation onto an "
        "older map, not a wheel slip, unless the map of the last relocalisation_recent_m metres explains this much "
        "more of the scan's end points at the corrected pose than at the wheels' one; a relocalisation's edge becomes "
        "the wheels' motion wherever the kept closures place the node as it did, so that the loop's drift is spread along the loop instead "
        "of kept in one jump (simulated worlds: glitches gain 0.17-0.92, loop ends at most 0.02). None: every "
        "correction stays in the front end's edge",
    )
    relocalisation_recent_m: float = Field(
        3.0, gt=0, le=1000, description="metres of the front end's trajectory before a correction that make the recent map"
    )


class Filter3DConfig(_Section):
    """The paper's 3D variant (sec. V, Fig. 11(b); rust/src/filter3d.rs): the filter above
    (particles, proposal, seed, threads, resampling; the motion model; the scan matcher's steps;
    the map's log-odds increments and threshold) with a 3D voxel map per particle, weighed by a
    3D likelihood field on a subsample of every mirror pixel's ray. ToF bags only; the pose stays
    planar (x, y, θ)."""

    enabled: bool = Field(False, description="run the 3D filter instead of the 2D one (`omnitof slam --filter 3d`)")
    pixel_stride: int = Field(4, ge=1, le=10_000, description="keep every n-th valid mirror pixel's ray of a frame")
    score_rays: int = Field(
        300, ge=1, le=1_000_000,
        description="of those, weigh the particles by at most this many, evenly spread (the scan matcher's cost)",
    )
    free_stride: int = Field(
        4, ge=1, le=10_000,
        description="of those, every n-th frees the voxels it passes through (all mark their end points)",
    )
    min_matched: float = Field(
        0.3, ge=0, le=1,
        description="scan-matching proposal: fall back to the odometry proposal when fewer of the scored rays than "
        "this share end near an occupied voxel (3D's own: rays to the ceiling and to unmapped space are many; "
        "scan_matcher.min_matched's 0.5 made 2 % of the office's proposals fall back and cost 0.05-0.12 m)",
    )
    climb_stride: int = Field(
        1, ge=1, le=10_000,
        description="scan-matching proposal: climb on every n-th scored ray (the Gaussian and the weight use all)",
    )
    resolution: float = Field(0.1, ge=0.01, le=10, description="voxel edge (m); the paper's Fig. 11(b): 0.1")
    max_range: float = Field(7.0, gt=0, le=100, description="rays longer than this (m) free space only")
    sigma: float = Field(0.05, ge=0.001, le=10, description="likelihood field: standard deviation of the end-point distance (m)")
    z_hit: float = Field(0.9, ge=0, le=1, description="likelihood field: weight of the Gaussian part")
    z_rand: float = Field(0.1, gt=0, le=1, description="likelihood field: weight of the uniform part")
    effective_rays: float = Field(
        9.0, gt=0, le=1e6,
        description="a frame's log-likelihood is the mean over its scored rays times this (rays are not independent)",
    )
    score_z_min: float = Field(0.1, ge=-100, le=100, description="score end points at this height (m) or above: the floor tells nothing of the pose")
    score_z_max: float = Field(100.0, ge=-100, le=1000, description="... and at this height (m) or below")
    project_z_min: float = Field(
        0.1, ge=-100, le=100,
        description="2D projection (map.pgm), and the rays the odometry check (scan_matcher.search_xy) matches: "
        "voxels and end points from this height (m) ...",
    )
    project_z_max: float = Field(2.0, ge=-100, le=1000, description="... up to this height (m)")

    @model_validator(mode="after")
    def _bands_are_bands(self) -> "Filter3DConfig":
        if self.score_z_max <= self.score_z_min or self.project_z_max <= self.project_z_min:
            raise ValueError("score_z_max must exceed score_z_min and project_z_max project_z_min")
        return self


class SlamConfig(_Section):
    """Everything a SLAM run needs besides its data."""

    filter: FilterConfig = FilterConfig()
    motion: MotionConfig = MotionConfig()
    sensor_model: SensorModelConfig = SensorModelConfig()
    likelihood_field: LikelihoodFieldConfig = LikelihoodFieldConfig()
    scan_matcher: ScanMatcherConfig = ScanMatcherConfig()
    map: MapConfig = MapConfig()
    backend: BackendConfig = BackendConfig()
    filter3d: Filter3DConfig = Filter3DConfig()
    # ToF bags only (laser logs ignore it): how each frame becomes a 1° scan, the slice, the
    # range limits, the pixel filter and the multipath compensation with the camera's figures
    # (omnitof.scan.ScanSettings). A real rig sets them here, e.g. --set scan.max_range=5.
    scan: ScanSettings = ScanSettings()

    @model_validator(mode="after")
    def _dropped_readings_stay_dropped(self) -> "SlamConfig":
        # Dropped readings read as no echo, which map.clear_no_echo would turn into free space
        # through the person out to map.max_range, wiping the walls behind them.
        if self.filter.moving_lookback > 0 and self.map.clear_no_echo:
            raise ValueError("filter.moving_lookback needs map.clear_no_echo off: the readings it drops read as "
                             "no echo, which would clear the walls behind the people")
        return self

    def to_yaml(self) -> str:
        return dump_yaml(self.model_dump(), sort_keys=False)


def preset_names() -> list[str]:
    """Names of the bundled presets."""
    folder = resources.files("omnitof") / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def _merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _read_yaml(text: str, source: str) -> dict[str, Any]:
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise ConfigError(f"{source}{'' if line is None else f':{line}'}: {problem}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a configuration must be a mapping of sections")
    for section, fields in data.items():
        # A scalar, list or empty section would otherwise vanish under the defaults.
        if not isinstance(fields, dict):
            got = "nothing" if fields is None else type(fields).__name__
            raise ConfigError(f"{source}: section {section}: expected a mapping of fields, got {got}")
    return data


# A layer of the configuration: where it came from, its nested fields, and how a bad value in it
# is named: "file" blames the source (a preset, a --config file), "settings" each field as
# `SOURCE FIELD=VALUE` (--set), "options" each field as the option that set it (--particles 0).
_Layer = tuple[str, dict[str, Any], Literal["file", "settings", "options"]]


def _validate(layers: list[_Layer]) -> SlamConfig:
    data: dict[str, Any] = {}
    for _, fields, _ in layers:
        data = _merge(data, fields)
    try:
        return SlamConfig.model_validate(data)
    except ValidationError as err:
        problems: dict[str, list[str]] = {}
        for e in err.errors():
            loc = tuple(str(p) for p in e["loc"])
            field = ".".join(loc) or "(top level)"
            # A check of ours: its own words, without pydantic's "Value error, ".
            message = str(e["ctx"]["error"]) if e["type"] == "value_error" else e["msg"]
            problems.setdefault(_blame(loc, layers), []).append(f"{field}: {message}")
        raise ConfigError(
            "; ".join(f"{source}: invalid configuration: " + "; ".join(found) for source, found in problems.items())
        ) from None


def _blame(loc: tuple[str, ...], layers: list[_Layer]) -> str:
    """The last layer that set the field at `loc` (or, for a section's own check, any field of it)."""
    for source, fields, style in reversed(layers):
        node: Any = fields
        found = True
        for part in loc:
            if not isinstance(node, dict):
                break  # the layer set a whole value that holds `loc` (an item of a list)
            if part not in node:
                found = False
                break
            node = node[part]  # None where the layer set it to null: that layer is to blame
        if not found:
            continue
        if style == "file":
            return source
        given = _flatten(fields, loc)
        if style == "options":
            return ", ".join(f"--{key.rsplit('.', 1)[-1]} {_shown(value)}" for key, value in given)
        return ", ".join(f"{source} {key}={_shown(value)}" for key, value in given)
    return "defaults"


def _flatten(fields: dict[str, Any], loc: tuple[str, ...]) -> list[tuple[str, Any]]:
    """The dotted keys and values that `fields` sets at or under `loc` (or above it, if set whole)."""
    node: Any = fields
    path: list[str] = []
    for part in loc:
        if not isinstance(node, dict):
            break
        node, path = node[part], [*path, part]
    return list(_leaves(node, path))


def _leaves(node: Any, path: list[str]) -> Iterator[tuple[str, Any]]:
    if isinstance(node, dict) and node:
        for key, value in node.items():
            yield from _leaves(value, [*path, str(key)])
    else:
        yield ".".join(path), node


def _shown(value: Any) -> str:
    """A value as the user wrote it, cut after 40 characters."""
    return shorten("true" if value is True else "false" if value is False else "null" if value is None else str(value))


def settings_overrides(settings: Mapping[str, Any], source: str = "settings") -> dict[str, Any]:
    """Nested overrides ({"filter": {"particles": 10}}) from dotted SECTION.FIELD settings
    ({"filter.particles": 10}; a field of a field as SECTION.FIELD.FIELD, e.g.
    scan.multipath.enabled), the form of `omnitof slam --set` and of an experiment's grid
    (omnitof.bench). Only the form is checked here; `load_config` checks names and values and
    names the field."""
    out: dict[str, Any] = {}
    paths = [str(key).split(".") for key in settings]
    for key, parts in zip(settings, paths):
        if len(parts) < 2 or not all(parts):
            raise ConfigError(f"{source}: {key!r}: expected SECTION.FIELD, e.g. filter.particles")
        # A field given whole and through one of its fields: which should win is not clear.
        if any(other != parts and other == parts[: len(other)] for other in paths):
            raise ConfigError(f"{source}: {key!r}: given twice (also through one of its fields)")
    for (key, value), parts in zip(settings.items(), paths):
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def parse_setting(text: str) -> tuple[str, Any]:
    """("SECTION.FIELD", value) from "SECTION.FIELD=VALUE", the value read as YAML (so that
    `true`, `30` and `0.5` are a bool, an int and a float)."""
    key, eq, value = text.partition("=")
    if not eq:
        raise ConfigError(f"--set {text!r}: expected SECTION.FIELD=VALUE")
    try:
        parsed = load_yaml(value)
    except yaml.YAMLError:
        raise ConfigError(f"--set {text!r}: the value is not valid YAML") from None
    settings_overrides({key: parsed}, "--set")  # the key's form
    return key, parsed


def load_preset(name: str) -> dict[str, Any]:
    """The raw settings of a bundled preset."""
    if name not in preset_names():
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(preset_names())}")
    return copy.deepcopy(_preset_settings(name))


@functools.cache
def _preset_settings(name: str) -> dict[str, Any]:
    # Read once per process: `omnitof bench` builds one configuration per run, and parsing the
    # preset's YAML in pure Python was a third of planning 2000 runs (14 of 36 s).
    text = (resources.files("omnitof") / "presets" / f"{name}.yaml").read_text(encoding="utf-8")
    return _read_yaml(text, f"preset {name}")


def load_config(
    path: str | Path | None = None,
    *,
    preset: str | None = None,
    overrides: dict[str, Any] | None = None,
) -> SlamConfig:
    """Defaults, then the preset, then the file, then explicit overrides (nested dicts). A bad
    override is named as `overrides FIELD=VALUE`."""
    return load_layers(path, preset=preset, settings=overrides, settings_source="overrides")


def load_layers(
    path: str | Path | None = None,
    *,
    preset: str | None = None,
    settings: dict[str, Any] | None = None,
    settings_source: str = "--set",
    options: dict[str, Any] | None = None,
) -> SlamConfig:
    """Defaults, then the preset, then the file, then `settings` (nested, from `--set`), then
    `options` (nested, from options like --particles), each bad value blamed on the layer that
    set it: `--set map.resolution=-1` or `--particles 0`, not the preset."""
    layers: list[_Layer] = []
    if preset is not None:
        layers.append((f"preset {preset}", load_preset(preset), "file"))
    if path is not None:
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as err:
            raise ConfigError(f"{path}: cannot read configuration: {err.strerror}") from None
        except UnicodeDecodeError:
            raise ConfigError(f"{path}: not a text file (a YAML configuration is UTF-8 text)") from None
        layers.append((str(path), _read_yaml(text, str(path)), "file"))
    _check_nested(settings, settings_source)
    layers += [(settings_source, settings or {}, "settings"), ("", options or {}, "options")]
    return _validate(layers)


def _check_nested(settings: Any, source: str) -> None:
    """Overrides in Python are nested sections of fields; a dotted key or a string is the
    command line's form, which pydantic would call an unknown field."""
    if settings is None:
        return
    if not isinstance(settings, Mapping):
        raise ConfigError(f"{source}: expected a mapping of sections, e.g. {{'filter': {{'particles': 30}}}}, "
                          f"got {type(settings).__name__}")
    for key in settings:
        if not isinstance(key, str):
            raise ConfigError(f"{source}: section names are strings, got {key!r}")
        if "." in key:
            raise ConfigError(f"{source}: {key!r}: nest the field ({{'filter': {{'particles': 30}}}}), or turn "
                              "dotted keys into sections with omnitof.slam.config.settings_overrides")
