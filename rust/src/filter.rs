//! The Rao-Blackwellized particle filter of the paper (section IV): each particle carries a pose,
//! a log-odds grid map (eq. 8) and a log importance weight (eq. 9). One `step` per integrated
//! scan: sample every particle's pose from the odometry motion model, weigh it with the beam
//! model in its own map, write the scan into its map, and resample (low variance) when the
//! effective sample size (eq. 10) falls below a threshold.
//!
//! Memory: maps share unchanged tiles (see grid.rs) and trajectories share their history
//! through parent links, so a resampled particle costs only what it changes afterwards.
//! Determinism: every random draw comes from a generator seeded by (seed, step, particle), and
//! the parallel loop writes each particle's result to its own slot, so the result does not
//! depend on the number of threads.

use std::collections::HashSet;
use std::sync::Arc;

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;

use crate::grid::{try_vec, GridError, LogOddsModel, TiledGrid};
use crate::motion::{compose, relative, OdometryMotion};
use crate::scan_match::{check_odometry, endpoints, gauss_newton, propose, FieldView, LikelihoodField, MatcherParams};
use crate::sensor_model::{integrate_scan, BeamModel, ScanGeometry};

/// Where a particle's new pose is drawn from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProposalKind {
    /// The paper's: the odometry motion model alone, weighed by the observation model.
    Odometry,
    /// Grisetti et al. 2007: a Gaussian around the scan-match mode in the particle's own map.
    ScanMatch,
}

/// A particle's new pose where its scan could not be matched (`Proposal::matched` false), or with
/// the odometry proposal. The paper's filter draws from the odometry motion model; so does the
/// scan-matching proposal with `fallback_draw` (GMapping's way, the default). Without it the
/// odometry's prediction stands: a scan too poor to be matched is also too poor to tell the
/// draws apart, so a draw adds the motion model's noise to the lineage, which on a robot whose
/// wheels are better than that model walks the heading away; but the draws' spread is also what
/// lets the particles get past a wheel glitch that no other check caught (BENCHMARKS.md, issue 13).
pub fn fallback_pose<R: rand::Rng>(
    proposal: ProposalKind,
    m: &MatcherParams,
    motion: &OdometryMotion,
    pose: [f64; 3],
    odom_prev: [f64; 3],
    odom_cur: [f64; 3],
    rng: &mut R,
) -> [f64; 3] {
    if proposal == ProposalKind::ScanMatch && !m.fallback_draw {
        compose(pose, relative(odom_prev, odom_cur))
    } else {
        motion.sample(pose, odom_prev, odom_cur, rng)
    }
}

/// The observation model that weighs particles drawn from the odometry proposal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObservationKind {
    Beam,
    LikelihoodField,
}

/// One pose of a particle's trajectory, linked to the pose before it. Children of one parent
/// share it, so the trajectories of all particles form a tree.
pub struct TrajectoryNode {
    pub pose: [f64; 3],
    pub scan: u64,
    pub parent: Option<Arc<TrajectoryNode>>,
}

impl TrajectoryNode {
    /// (scan index, pose) of this node and every node before it, oldest first.
    pub fn lineage(self: &Arc<Self>) -> Vec<(u64, [f64; 3])> {
        let mut out = Vec::new();
        let mut node = Some(self);
        while let Some(n) = node {
            out.push((n.scan, n.pose));
            node = n.parent.as_ref();
        }
        out.reverse();
        out
    }
}

impl Drop for TrajectoryNode {
    // Unlink iteratively: the default recursive drop of a chain of thousands of nodes would
    // overflow the stack.
    fn drop(&mut self) {
        let mut next = self.parent.take();
        while let Some(node) = next {
            match Arc::try_unwrap(node) {
                Ok(mut inner) => next = inner.parent.take(),
                Err(_) => break,
            }
        }
    }
}

#[derive(Clone)]
pub struct Particle {
    pub pose: [f64; 3],
    pub log_weight: f64,
    pub map: TiledGrid,
    pub trajectory: Arc<TrajectoryNode>,
}

impl Particle {
    /// A copy with weight `log_weight` (sharing the map's tiles and the trajectory), or
    /// NoMemory where `clone` would abort.
    fn try_copy(&self, log_weight: f64) -> Result<Particle, GridError> {
        Ok(Particle { pose: self.pose, log_weight, map: self.map.try_clone()?, trajectory: self.trajectory.clone() })
    }
}

/// `n` copies of `first`, or NoMemory.
fn copies(first: &Particle, n: usize) -> Result<Vec<Particle>, GridError> {
    let mut out = try_vec(n, "the particles")?;
    for _ in 0..n {
        out.push(first.try_copy(first.log_weight)?);
    }
    Ok(out)
}

#[derive(Clone, Debug)]
pub struct FilterParams {
    pub n_particles: usize,
    pub seed: u64,
    pub threads: usize,
    pub motion: OdometryMotion,
    pub proposal: ProposalKind,
    pub observation: ObservationKind,
    pub beam: BeamModel,
    pub field: LikelihoodField,
    pub matcher: MatcherParams,
    pub beam_stride: usize,
    /// The scan's log-likelihood is the mean over its scored beams times this number: the
    /// scan counts as that many independent beams, whatever the sensor's beam count. Real beams
    /// are far from independent, and counting every beam makes the weights collapse.
    pub effective_beams: f64,
    pub log_odds: LogOddsModel,
    pub resolution: f64,
    /// Readings beyond this (metres) update free space only.
    pub map_max_range: f64,
    pub clear_no_echo: bool,
    /// Each cell updated at most once per scan (`integrate_scan`), else once per beam.
    pub once_per_scan: bool,
    /// Resample when Neff < resample_threshold · N.
    pub resample_threshold: f64,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct StepInfo {
    pub neff: f64,
    pub resampled: bool,
    /// Particles that fell back to the odometry proposal because scan matching failed.
    pub fallbacks: usize,
    /// Whether the wide search replaced the odometry increment (see `check_odometry`).
    pub odometry_corrected: bool,
}

pub struct ParticleFilter {
    pub params: FilterParams,
    angles: Vec<f64>,
    sensor: [f64; 3],
    pub particles: Vec<Particle>,
    pub steps: u64,
    pub resamplings: u64,
    pub fallbacks: u64,
    best: usize,
    pool: rayon::ThreadPool,
}

/// Gauss-Newton iterations that pose a scan between integrated ones.
const BETWEEN_GAUSS_NEWTON: u32 = 6;

/// The odometry check (scan_match::check_odometry) runs from this step on (0: the first
/// integrated scan, which starts the map): not against a map of one scan. A scan that sees the
/// next stretch of the walls the first one saw is "unexplained" there for want of map, and the
/// wide search fitted its few end points onto the stretches already mapped (the office's first
/// frames: about ten readings each, a 0.3-0.4 m false jump at the second integrated scan that
/// the whole run kept, in 5 of 6 drives of benchmarks/filter3d.py's rendering). A glitch at the
/// second scan is not caught (nor was it before, on the simulated corridor loop); one at the
/// fifth still is.
const CHECK_FROM_STEP: u64 = 2;

/// SplitMix64 finaliser: decorrelates generator seeds built from (seed, step, particle).
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

pub fn rng_for(seed: u64, step: u64, stream: u64) -> Pcg64 {
    Pcg64::seed_from_u64(mix(mix(mix(seed) ^ step) ^ stream))
}

/// Effective sample size of normalised weights (eq. 10): 1 / Σ w̄ᵢ².
pub fn neff(normalised: &[f64]) -> f64 {
    1.0 / normalised.iter().map(|w| w * w).sum::<f64>()
}

/// Normalised weights from log weights (subtracting the maximum first, so none underflows).
pub fn normalise(log_weights: &[f64]) -> Vec<f64> {
    let max = log_weights.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let w: Vec<f64> = log_weights.iter().map(|l| (l - max).exp()).collect();
    let sum: f64 = w.iter().sum();
    w.into_iter().map(|x| x / sum).collect()
}

/// Low-variance (systematic) resampling (Probabilistic Robotics, table 4.4): one uniform offset
/// r in [0, 1/N), then the particles under the comb r + k/N. Each particle i is drawn either
/// ⌊N·wᵢ⌋ or ⌈N·wᵢ⌉ times; indices come out sorted.
pub fn low_variance_resample<R: rand::Rng>(normalised: &[f64], rng: &mut R) -> Vec<usize> {
    let n = normalised.len();
    let step = 1.0 / n as f64;
    let r: f64 = rng.random::<f64>() * step;
    let mut out = Vec::with_capacity(n);
    let mut c = normalised[0];
    let mut i = 0;
    for k in 0..n {
        let u = r + k as f64 * step;
        while u > c && i + 1 < n {
            i += 1;
            c += normalised[i];
        }
        out.push(i);
    }
    out
}

/// The end of a filter step, shared by the 2D and the 3D filter: the particles' log weights
/// normalised, their effective sample size (eq. 10), the heaviest particle, and, where the
/// effective size falls below `threshold`·N, the ancestors that low-variance resampling draws
/// (from the step's own random stream, so the thread count does not matter).
pub struct Weighing {
    pub n_eff: f64,
    /// The heaviest particle before any resampling.
    pub best: usize,
    /// The largest log weight, which the particles subtract where they are not resampled, so
    /// that their log weights stay near zero and never lose precision.
    pub max_log_weight: f64,
    /// Each new particle's ancestor, if the step resamples.
    pub ancestors: Option<Vec<usize>>,
}

impl Weighing {
    pub fn new(log_weights: &[f64], threshold: f64, seed: u64, step: u64) -> Self {
        let w = normalise(log_weights);
        let n_eff = neff(&w);
        let best = (0..w.len()).fold(0, |b, i| if w[i] > w[b] { i } else { b });
        let max_log_weight = log_weights.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let ancestors = (n_eff < threshold * w.len() as f64)
            .then(|| low_variance_resample(&w, &mut rng_for(seed, step, u64::MAX)));
        Weighing { n_eff, best, max_log_weight, ancestors }
    }

    /// Where the heaviest particle went: its first copy after resampling, else itself.
    pub fn best_after(&self) -> usize {
        match &self.ancestors {
            Some(idx) => idx.iter().position(|&j| j == self.best).unwrap_or(0),
            None => self.best,
        }
    }
}

impl ParticleFilter {
    pub fn new(params: FilterParams, angles: Vec<f64>, sensor: [f64; 3]) -> Result<Self, String> {
        if params.n_particles == 0 {
            return Err("n_particles must be at least 1".into());
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(params.threads)
            .build()
            .map_err(|e| e.to_string())?;
        Ok(ParticleFilter {
            params,
            angles,
            sensor,
            particles: Vec::new(),
            steps: 0,
            resamplings: 0,
            fallbacks: 0,
            best: 0,
            pool,
        })
    }

    pub fn n_beams(&self) -> usize {
        self.angles.len()
    }

    /// Every particle at `pose` with the first scan written into one shared map.
    fn initial_particles(p: &FilterParams, geom: &ScanGeometry, pose: [f64; 3], ranges: &[f32], scan: u64) -> Result<Vec<Particle>, GridError> {
        let mut map = TiledGrid::new(p.resolution);
        integrate_scan(&mut map, &p.log_odds, geom, pose, ranges, p.map_max_range, p.clear_no_echo, p.once_per_scan)?;
        let root = Arc::new(TrajectoryNode { pose, scan, parent: None });
        copies(&Particle { pose, log_weight: 0.0, map, trajectory: root }, p.n_particles)
    }

    /// Integrate one scan taken at odometry pose `odom_cur`, the robot having moved there from
    /// odometry pose `odom_prev` since the last integrated scan. The first call only starts the
    /// map, at `odom_cur`. `angles` are this scan's beam bearings where its geometry is its own
    /// (one per range); None: the filter's.
    ///
    /// Fails when a map cannot grow (a pose or reading beyond a grid's reach, memory that cannot
    /// be had); the filter is then spent, as a run that ran out of memory is: the caller stops.
    pub fn step(&mut self, odom_prev: [f64; 3], odom_cur: [f64; 3], ranges: &[f32], angles: Option<&[f64]>, scan: u64) -> Result<StepInfo, GridError> {
        let step_index = self.steps;
        self.steps += 1;
        let p = &self.params;
        let geom = ScanGeometry { angles: angles.unwrap_or(&self.angles), sensor: self.sensor };
        if self.particles.is_empty() {
            self.particles = Self::initial_particles(p, &geom, odom_cur, ranges, scan)?;
            return Ok(StepInfo { neff: p.n_particles as f64, resampled: false, fallbacks: 0, odometry_corrected: false });
        }
        let seed = p.seed;
        let pts = endpoints(&geom, ranges, p.beam_stride, p.field.max_range);
        let corrected = match (p.proposal, self.particles.get(self.best)) {
            (ProposalKind::ScanMatch, Some(best)) if step_index >= CHECK_FROM_STEP => {
                check_odometry(&p.field, &p.matcher, &best.map, &geom, &pts, best.pose, odom_prev, odom_cur)?
            }
            _ => None,
        };
        let odom_cur = corrected.unwrap_or(odom_cur);
        let outcomes: Vec<Result<usize, GridError>> = self.pool.install(|| {
            self.particles
                .par_iter_mut()
                .enumerate()
                .map(|(i, part)| {
                    let mut rng = rng_for(seed, step_index, i as u64);
                    let mut fell_back = false;
                    let mut drawn = None;
                    if p.proposal == ProposalKind::ScanMatch {
                        let prop = propose(&p.field, &p.matcher, &p.motion, &part.map, &geom, &pts, part.pose, odom_prev, odom_cur, &mut rng);
                        if prop.matched {
                            part.log_weight += prop.log_normaliser;
                            drawn = Some(prop.pose);
                        } else {
                            fell_back = true;
                        }
                    }
                    let pose = match drawn {
                        Some(pose) => pose,
                        None => {
                            let pose = fallback_pose(p.proposal, &p.matcher, &p.motion, part.pose, odom_prev, odom_cur, &mut rng);
                            let mean_ll = match p.observation {
                                ObservationKind::Beam => {
                                    p.beam.scan_log_likelihood(&part.map, &geom, pose, ranges, p.beam_stride).0
                                }
                                ObservationKind::LikelihoodField => p.field.score(&part.map, geom.sensor_pose(pose), &pts).0,
                            };
                            part.log_weight += p.effective_beams * mean_ll;
                            pose
                        }
                    };
                    part.pose = pose;
                    part.trajectory = Arc::new(TrajectoryNode { pose, scan, parent: Some(part.trajectory.clone()) });
                    integrate_scan(&mut part.map, &p.log_odds, &geom, pose, ranges, p.map_max_range, p.clear_no_echo, p.once_per_scan)?;
                    Ok(fell_back as usize)
                })
                .collect()
        });
        // In particle order, so that the error reported does not depend on the thread count.
        let mut fallbacks = 0;
        for outcome in outcomes {
            fallbacks += outcome?;
        }
        self.fallbacks += fallbacks as u64;
        let log_w: Vec<f64> = self.particles.iter().map(|q| q.log_weight).collect();
        let weighing = Weighing::new(&log_w, self.params.resample_threshold, seed, step_index);
        if let Some(idx) = &weighing.ancestors {
            let mut next = try_vec(idx.len(), "the resampled particles")?;
            for &j in idx {
                next.push(self.particles[j].try_copy(0.0)?);
            }
            self.particles = next;
            self.resamplings += 1;
        } else {
            for q in &mut self.particles {
                q.log_weight -= weighing.max_log_weight;
            }
        }
        self.best = weighing.best_after();
        let resampled = weighing.ancestors.is_some();
        Ok(StepInfo { neff: weighing.n_eff, resampled, fallbacks, odometry_corrected: corrected.is_some() })
    }

    /// One local match, from `start`, of a scan in the best particle's map (with the filter's
    /// likelihood field and matcher): the pose of a scan taken between integrated scans, and
    /// the share of its end points that found an obstacle of the map. None before the first scan.
    pub fn match_in_best(&self, start: [f64; 3], ranges: &[f32], angles: Option<&[f64]>) -> Option<([f64; 3], f64)> {
        let best = self.best()?;
        Some(self.match_in(&FieldView::new(&self.params.field, &best.map), start, ranges, angles))
    }

    /// `match_in_best` through a view of the best particle's map, which a chain of matches shares.
    fn match_in(&self, view: &FieldView, start: [f64; 3], ranges: &[f32], angles: Option<&[f64]>) -> ([f64; 3], f64) {
        let p = &self.params;
        let geom = ScanGeometry { angles: angles.unwrap_or(&self.angles), sensor: self.sensor };
        let pts = endpoints(&geom, ranges, p.beam_stride, p.field.max_range);
        if pts.is_empty() {
            return (start, 0.0);
        }
        // The start is already good (the previous scan's pose plus the odometry since, a few
        // centimetres of motion, well inside the likelihood field's window): Gauss-Newton alone
        // converges from there. A hill climb first cost four times as much for the same poses
        // (Intel: 4.2 of the back end's 11 s).
        let (pose, _, matched) = gauss_newton(view, &geom, &pts, p.matcher.effective_beams, None, start, BETWEEN_GAUSS_NEWTON);
        (pose, matched as f64 / pts.len() as f64)
    }

    /// Pose the scans taken between two integrated ones, in order, each by one local match
    /// (`match_in_best`) started where the pose before it and the odometry put it; where fewer
    /// than `min_matched` of its end points find the map, the odometry's prediction stands.
    /// `odometry` has one row more than there are scans: the odometry of the scan before the
    /// first. `ranges` (and `angles`, else the filter's) hold `beams` values per scan, padding
    /// as +inf ranges. Returns each pose relative to the best particle's pose, and whether the
    /// match stood; None before the first scan. Sequential by nature: each match starts from
    /// the one before.
    pub fn match_chain(&self, odometry: &[[f64; 3]], ranges: &[f32], angles: Option<&[f64]>, beams: usize, min_matched: f64) -> Option<(Vec<[f64; 3]>, Vec<bool>)> {
        let best = self.best()?;
        let view = FieldView::new(&self.params.field, &best.map);
        let anchor = best.pose;
        let mut pose = anchor;
        let mut out = Vec::with_capacity(odometry.len().saturating_sub(1));
        let mut matched = Vec::with_capacity(out.capacity());
        for (i, pair) in odometry.windows(2).enumerate() {
            let start = compose(pose, relative(pair[0], pair[1]));
            let scan_angles = angles.map(|a| &a[i * beams..(i + 1) * beams]);
            let found = self.match_in(&view, start, &ranges[i * beams..(i + 1) * beams], scan_angles);
            let good = Some(found).filter(|f| f.1 >= min_matched);
            pose = good.map_or(start, |f| f.0);
            out.push(relative(anchor, pose));
            matched.push(good.is_some());
        }
        Some((out, matched))
    }

    /// Restart every particle at `pose` with `map` (shared between them, copy-on-write), equal
    /// weights, and a trajectory that begins at scan `scan`: how a pose-graph back end feeds a
    /// correction back. The step counter goes on, so the random streams stay those of the
    /// steps to come and the run stays deterministic.
    pub fn reset(&mut self, pose: [f64; 3], scan: u64, map: TiledGrid) -> Result<(), GridError> {
        let root = Arc::new(TrajectoryNode { pose, scan, parent: None });
        self.particles = copies(&Particle { pose, log_weight: 0.0, map, trajectory: root }, self.params.n_particles)?;
        self.best = 0;
        Ok(())
    }

    /// The particle with the highest weight (after a resampling, a copy of the one that had it).
    pub fn best(&self) -> Option<&Particle> {
        self.particles.get(self.best)
    }

    /// (scan index, pose) of every integrated scan along a particle's trajectory, oldest first.
    pub fn trajectory_of(particle: &Particle) -> Vec<(u64, [f64; 3])> {
        particle.trajectory.lineage()
    }

    /// (distinct tiles over all particles, tile references over all particles).
    pub fn tile_counts(&self) -> (usize, usize) {
        let mut seen = HashSet::new();
        let mut refs = 0;
        for q in &self.particles {
            for t in q.map.tiles() {
                refs += 1;
                seen.insert(Arc::as_ptr(t) as usize);
            }
        }
        (seen.len(), refs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neff_of_uniform_and_degenerate_weights() {
        assert!((neff(&[0.25; 4]) - 4.0).abs() < 1e-12);
        assert!((neff(&[1.0, 0.0, 0.0]) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn low_variance_counts_are_floor_or_ceil() {
        let w = normalise(&[0.0, -1.0, -0.2, -3.0, 0.5, -0.7, -0.1]);
        for seed in 0..50 {
            let idx = low_variance_resample(&w, &mut rng_for(seed, 0, 0));
            assert!(idx.windows(2).all(|p| p[0] <= p[1]));
            for (i, wi) in w.iter().enumerate() {
                let count = idx.iter().filter(|&&j| j == i).count() as f64;
                let expect = wi * w.len() as f64;
                assert!(count >= expect.floor() - 1e-9 && count <= expect.ceil() + 1e-9);
            }
        }
    }

    #[test]
    fn long_trajectories_drop_without_overflowing_the_stack() {
        let mut node = Arc::new(TrajectoryNode { pose: [0.0; 3], scan: 0, parent: None });
        for k in 1..1_000_000 {
            node = Arc::new(TrajectoryNode { pose: [0.0; 3], scan: k, parent: Some(node) });
        }
        drop(node);
    }
}
